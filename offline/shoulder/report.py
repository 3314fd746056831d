"""Outputs of ``train shoulder``: skeleton files, error tables, plots, Markdown report.

Skeleton file (``skeleton_k<k>.json``, one per k; format ``mocap-labeler/shoulder-skeleton``
version 1, documented in docs/shoulder.md): markers and their rest pose, segments with parent,
joint centre (rest space, mm), core and reduced markers, dense skin weights, the marker surface.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from offline.shoulder.model import ShoulderSkeleton

FORMAT = "mocap-labeler/shoulder-skeleton"


def _r(x: np.ndarray, nd: int = 3) -> list:
    return np.round(np.asarray(x, dtype=np.float64), nd).tolist()


def skeleton_dict(model: ShoulderSkeleton, labels: Sequence[str]) -> dict:
    """The skeleton file content (module doc)."""
    S = model.n_segments_
    segs = []
    for s in range(S):
        p = int(model.parent_[s])
        segs.append(
            {
                "id": s,
                "parent": None if p < 0 else p,
                "joint_mm": None if p < 0 else _r(model.joints_[s]),
                "joint_rms_mm": None if p < 0 else round(float(model.joint_rms_[s]), 3),
                "markers": [labels[int(i)] for i in np.flatnonzero(model.labels_ == s)],
                "core": [labels[i] for i in model.fit_markers_[s]],
                "reduced": [labels[i] for i in model.reduced_[s]],
            }
        )
    surf = model.surface_
    return {
        "format": FORMAT,
        "version": 1,
        "units": "mm",
        "k_requested": int(model.n_segments),
        "n_segments": S,
        "structure": "chain" if model.is_chain_ else "tree",
        "order": model.chain_,
        "rest_frame": surf.rest_frame,
        "markers": list(labels),
        "rest_mm": _r(surf.rest),
        "segments": segs,
        "weights": _r(model.weights_, 4),
        "faces": surf.faces.tolist(),
        "clustered_faces": surf.kept.tolist(),
        "triangle_labels": model.triangle_labels_.tolist(),
        "sigma2_mm2": round(float(model.sigma2_), 3),
    }


def write_json(path: Path, obj: object) -> Path:
    """``obj`` as strict JSON: a measurement a run could not make is ``null``, not ``NaN``."""
    from labeler_service.tools.subscribe import strict_json

    path.write_text(strict_json(obj, indent=1) + "\n", encoding="utf-8")
    return path


# ---------------------------------------------------------------------------- plots
def plot_error_vs_k(
    path: Path, errors: dict, motions: Sequence[str], mset: str | None, title: str
) -> Path:
    """Error vs number of segments (Fig. 5-7 analogues). ``mset`` None plots full and reduced."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8), dpi=110)
    sets = ("full", "reduced") if mset is None else (mset,)
    for motion in motions:
        for s in sets:
            by_k = errors[motion][s]
            ks = sorted(int(k) for k in by_k)
            ys = [by_k[str(k)]["avg"] for k in ks]
            label = f"{motion} ({s})" if mset is None else motion
            ax.plot(ks, ys, marker="o", linestyle="-" if s == "full" else "--", label=label)
    all_ks = sorted({int(k) for m in motions for s in sets for k in errors[m][s]})
    ax.set_xticks(all_ks)
    ax.set_xlabel("number of segments k")
    ax.set_ylabel("average synthesis error (mm)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_segmentation(path: Path, model: ShoulderSkeleton, title: str) -> Path:
    """Rest-pose markers coloured by segment, joints as black crosses (Fig. 2-3 analogue)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rest = model.surface_.rest
    fig = plt.figure(figsize=(5, 4.5), dpi=110)
    ax = fig.add_subplot(projection="3d")
    cmap = plt.get_cmap("tab10")
    for s in range(model.n_segments_):
        pts = rest[model.labels_ == s]
        ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=10, color=cmap(s % 10), label=f"S{s}")
        red = rest[model.reduced_[s]]
        ax.scatter(red[:, 0], red[:, 1], red[:, 2], s=40, facecolors="none", edgecolors="k")
    j = model.joints_[np.isfinite(model.joints_).all(axis=1)]
    if len(j):
        ax.scatter(j[:, 0], j[:, 1], j[:, 2], marker="x", s=60, color="k", label="joints")
    lo, hi = rest.min(axis=0), rest.max(axis=0)
    mid, half = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- markdown
def _fmt(x: float) -> str:
    return "nan" if not np.isfinite(x) else f"{x:.2f}"


def error_table(errors: dict, ks: Sequence[int]) -> list[str]:
    """Table 2 analogue: avg / max (std) per motion, marker set and k."""
    head = "| motion | markers | " + " | ".join(f"k={k} avg | max | (std)" for k in ks) + " |"
    sep = "|---|---|" + "---|---|---|" * len(ks)
    lines = [head, sep]
    for motion, sets in errors.items():
        for mset, by_k in sets.items():
            cells = []
            for k in ks:
                v = by_k.get(str(k))
                cells.append(
                    " | ".join(["-", "-", "-"])
                    if v is None
                    else f"{_fmt(v['avg'])} | {_fmt(v['max'])} | ({_fmt(v['std'])})"
                )
            lines.append(f"| {motion} | {mset} | " + " | ".join(cells) + " |")
    return lines


def mg03_table(errors: dict, mg03: dict, k_ours: int = 4) -> list[str]:
    """Table 3 analogue: our k=4 model vs MG03, both marker sets."""
    lines = [
        f"| motion | markers | ours k={k_ours} avg | max | (std) | MG03 avg | max | (std) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for motion, sets in mg03.items():
        for mset, m in sets.items():
            o = errors.get(motion, {}).get(mset, {}).get(str(k_ours))
            ours = f"{_fmt(o['avg'])} | {_fmt(o['max'])} | ({_fmt(o['std'])})" if o else "- | - | -"
            lines.append(
                f"| {motion} | {mset} | {ours} | {_fmt(m['avg'])} | {_fmt(m['max'])} | "
                f"({_fmt(m['std'])}) |"
            )
    return lines
