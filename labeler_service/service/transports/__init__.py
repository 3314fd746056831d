"""Transports: the interface (``base``), in-memory (tests), UDP and MQTT."""
