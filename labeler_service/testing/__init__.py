"""Helpers for tests, benchmarks and the demo: a local Mosquitto broker, the in-process pipeline
harness, real-data discovery. Nothing in ``service`` imports it."""
