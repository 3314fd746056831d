"""Where the real captures live: ``MOCAP_DATA_DIR``, else ``../shared/data/real`` when present."""

from __future__ import annotations

import os
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parents[2]


def real_data_dir() -> Path | None:
    """The folder of real captures, or ``None`` when there is none.

    ``MOCAP_DATA_DIR`` wins when set (an empty or missing folder then means none); otherwise
    ``../shared/data/real`` beside the project root, then beside the current directory.
    """
    env = os.environ.get("MOCAP_DATA_DIR")
    if env is not None:
        p = Path(env).expanduser()
        return p if p.is_dir() and any(p.glob("*.c3d")) else None
    for base in (PROJECT_ROOT, Path.cwd()):
        p = (base / ".." / "shared" / "data" / "real").resolve()
        if p.is_dir() and any(p.glob("*.c3d")):
            return p
    return None


def real_file(name: str) -> Path | None:
    """A named file in the real-data folder, or ``None`` when it is not there."""
    d = real_data_dir()
    if d is None:
        return None
    p = d / name
    return p if p.is_file() else None
