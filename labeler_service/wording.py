"""Counts in messages: :func:`plural` writes ``1 frame`` and ``2 frames``, so a message whose
count can be 1 reads right (a new user's pass read "only 1 subjects" and "1 frames")."""

from __future__ import annotations


def plural(n: int | float, noun: str, many: str | None = None) -> str:
    """``n`` and ``noun`` in the number ``n`` needs: ``plural(1, "frame")`` is ``"1 frame"``,
    ``plural(2, "frame")`` ``"2 frames"``, ``plural(0, "frame")`` ``"0 frames"``. ``many``:
    the plural when it is not ``noun + "s"`` (``plural(3, "body", "bodies")``)."""
    word = noun if n == 1 else (many if many is not None else noun + "s")
    return f"{n} {word}"


def and_list(items: list[str]) -> str:
    """``"a"``, ``"a and b"``, ``"a, b and c"``."""
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"


def first_of(items: list[str], n: int) -> str:
    """The first ``n`` of ``items``, comma-separated, then ``and K more`` when there are more
    (a long list of marker names on one line of a summary)."""
    shown = ", ".join(items[:n])
    return shown + (f" and {len(items) - n} more" if len(items) > n else "")
