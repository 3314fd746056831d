"""Scoring labelers on labeled captures: one scorer for ``evaluate``, ``demo`` and the
benchmarks."""
