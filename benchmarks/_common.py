"""What the benchmark scripts share. They run as ``python benchmarks/NAME.py``, so the
script's folder is on ``sys.path`` and ``from _common import emit`` resolves."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def emit(result: dict[str, Any], out: str | Path | None = None) -> None:
    """Prints ``result`` as one JSON line on stdout and, with ``out``, writes the same line
    there (creating its folder)."""
    line = json.dumps(result)
    print(line)
    if out:
        path = Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(line + "\n")
