"""The streaming service: settings, wire protocol, server, per-stream state, metrics and
transports."""
