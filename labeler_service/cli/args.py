"""Argument types shared by the commands."""

from __future__ import annotations

import argparse


def seed(text: str) -> int:
    """``--seed``: a whole number >= 0 (numpy refuses a negative seed with a traceback)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed is a whole number >= 0, got {text!r}")
    return value
