"""Scenes: multi-person composition from real takes, simulation, seeded corruptions."""
