"""The per-marker error raster (``evaluate --plot FILE.png`` also writes ``FILE_errors.png``).

One row per marker, one column per frame: white = correct, light grey = not visible (or in the
init window), orange = another marker of the same subject, red = a marker of another subject,
blue = left unlabeled. Rows are grouped by subject; with many markers only the markers with
errors are drawn (the title says how many were left out).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labeler_service.evaluation.scoring import (
    CORRECT,
    CROSS_SUBJECT,
    NOT_VISIBLE,
    SAME_SUBJECT,
    UNLABELED,
    MethodScore,
)
from labeler_service.wording import plural

MAX_ROWS = 80  # above this, only markers with errors are drawn
_COLOURS = {
    NOT_VISIBLE: "#e6e6e6",
    CORRECT: "#ffffff",
    SAME_SUBJECT: "#f28e2b",
    CROSS_SUBJECT: "#d62728",
    UNLABELED: "#1f77b4",
}


def errors_path(plot: Path) -> Path:
    """``FILE.png`` -> ``FILE_errors.png``."""
    return plot.with_name(f"{plot.stem}_errors{plot.suffix or '.png'}")


def plot_error_raster(
    score: MethodScore, out: Path, rate: float, init_frames: int, title: str = ""
) -> Path:
    """Draws ``score.raster`` (frames x markers) as a coloured image and saves it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    raster = score.raster
    names = score.marker_names
    rows = np.arange(raster.shape[1])
    hidden = 0
    if rows.size > MAX_ROWS:
        bad = ((raster != CORRECT) & (raster != NOT_VISIBLE)).sum(axis=0)
        keep = np.flatnonzero(bad > 0)
        if keep.size > MAX_ROWS:
            keep = np.sort(np.argsort(-bad, kind="stable")[:MAX_ROWS])
        hidden = rows.size - keep.size
        rows = keep
    img = raster[:, rows].T
    cmap = ListedColormap([_COLOURS[k] for k in range(5)])
    height = 1.5 + 0.14 * max(rows.size, 8)
    fig, ax = plt.subplots(figsize=(11, min(height, 16)), dpi=110)
    n = raster.shape[0]
    ax.imshow(
        img,
        aspect="auto",
        interpolation="nearest",
        cmap=cmap,
        vmin=-0.5,
        vmax=4.5,
        # no row (every marker correct): one row's height, not an empty range (matplotlib
        # warned "Attempting to set identical low and high ylims")
        extent=(-0.5 / rate, (n - 0.5) / rate, max(rows.size, 1) - 0.5, -0.5),
    )
    if rows.size == 0:
        ax.text(0.5, 0.5, "no marker with errors", transform=ax.transAxes, ha="center")
    if init_frames:
        ax.axvline(init_frames / rate, color="k", lw=0.8, ls="--")
    if rows.size <= MAX_ROWS:
        ax.set_yticks(np.arange(rows.size), labels=[names[i] for i in rows], fontsize=6)
    ax.set_xlabel("capture time (s)")
    kept = f" ({plural(hidden, 'marker')} without errors not drawn)" if hidden else ""
    acc = "" if not np.isfinite(score.accuracy) else f", accuracy {100 * score.accuracy:.2f} %"
    ax.set_title(f"errors per marker {title}{acc}{kept}".strip(), fontsize=9)
    handles = [
        Patch(color=_COLOURS[SAME_SUBJECT], label="same subject"),
        Patch(color=_COLOURS[CROSS_SUBJECT], label="other subject"),
        Patch(color=_COLOURS[UNLABELED], label="unlabeled"),
        Patch(color=_COLOURS[NOT_VISIBLE], label="not visible"),
    ]
    ax.legend(handles=handles, loc="upper right", fontsize=7, ncol=4, framealpha=0.9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
