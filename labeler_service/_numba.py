"""The one place for numba options.

``njit`` compiles with ``cache=True`` (compile once per machine, not per process) and a fastmath
set that keeps NaN/inf semantics: a NaN is how a missing marker is spelled in this project, so
``nnan``/``ninf`` are never enabled.
"""

from __future__ import annotations

from typing import Any

import numba

FASTMATH = frozenset({"nsz", "arcp", "contract", "afn", "reassoc"})


def njit(*args: Any, **kwargs: Any) -> Any:
    """``numba.njit`` with the project's defaults (``cache=True``, NaN-safe fastmath)."""
    kwargs.setdefault("cache", True)
    kwargs.setdefault("fastmath", set(FASTMATH))
    kwargs.setdefault("nogil", True)
    return numba.njit(*args, **kwargs)
