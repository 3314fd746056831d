"""Recovery error vs gap length, both recovery methods (seed 003 Fig. 8 analogue).

For every gap length (default 5-40 frames) the capture is corrupted like
``evaluate --gaps K --gap-frames L`` (per subject K markers removed for L frames, repeatedly),
labeled with ``recovery=kabsch`` and ``recovery=displacement``, and every removed sample the
labeler reports as RECOVERED is compared with the truth. The ratio divides each error by the
longest marker-pair distance of the marker's rigid body (``Labeler.body_extent``), as in the
paper's Fig. 8. Prints one JSON object; ``--plot`` writes the figure.

    .venv/bin/python benchmarks/recovery_vs_gap.py --capture /tmp/a.c3d \
        --plot docs/plots/recovery_vs_gap.png
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from _common import emit

from labeler_service.capture import Capture, read_capture
from labeler_service.evaluation.scoring import score_labeler
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.labeler import Labeler
from labeler_service.scenes.corrupt import CorruptionSpec, corrupt

INIT = 50
METHODS = ("kabsch", "displacement")


def measure(cap: Capture, method: str, gaps: int, length: int, seed: int) -> dict:
    """Recovery errors (mm and ratio) and labeling accuracy for one setting, scored by
    :func:`labeler_service.evaluation.scoring.score_labeler` (what ``evaluate`` reports)."""
    spec = CorruptionSpec(gaps=gaps, gap_frames=length, protect_frames=INIT, seed=seed)
    stream = corrupt(cap, spec)
    lab = Labeler(stream.marker_names, stream.rate, LabelerConfig(recovery=method))
    s = score_labeler(lab, stream, INIT, method)

    def r(x: float | None, nd: int) -> float | None:
        return None if x is None else round(x, nd)

    return {
        "gap_frames": length,
        "method": method,
        "recovered": s.recovered,
        "removed": s.removed,
        "recovery_rate": r(s.recovery_rate, 4),
        "mean_mm": r(s.recovery_mean_mm, 3),
        "p95_mm": r(s.recovery_p95_mm, 3),
        "mean_ratio": r(s.recovery_mean_ratio, 5),
        "accuracy": round(s.accuracy, 6),
    }


def plot(rows: list[dict], path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for method, style in zip(METHODS, ("o-", "s--"), strict=True):
        rs = [r for r in rows if r["method"] == method and r["mean_ratio"] is not None]
        x = [r["gap_frames"] for r in rs]
        ax[0].plot(x, [r["mean_ratio"] for r in rs], style, label=method)
        ax[1].plot(x, [r["mean_mm"] for r in rs], style, label=method)
    ax[0].set_ylabel("error / max distance in rigid body")
    ax[1].set_ylabel("mean error (mm)")
    for a in ax:
        a.set_xlabel("gap length (frames)")
        a.grid(alpha=0.3)
        a.legend()
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--capture", help="labeled capture (default: simulated 3-person walk)")
    p.add_argument("--lengths", default="5,10,15,20,25,30,35,40", help="gap lengths (frames)")
    p.add_argument("--gaps", type=int, default=2, help="markers removed per subject per event")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--plot", help="PNG to write")
    p.add_argument("--out", help="also write the JSON here")
    args = p.parse_args(argv)
    if args.capture:
        cap = read_capture(args.capture)
        source = args.capture
    else:
        from labeler_service.scenes.simulate import simulate_scene

        cap = simulate_scene(3, 10.0, "walk", args.seed)
        source = f"simulate 3 walk seed {args.seed}"
    lengths = [int(x) for x in args.lengths.split(",") if x.strip()]
    rows = []
    for length in lengths:
        for method in METHODS:
            row = measure(cap, method, args.gaps, length, args.seed)
            rows.append(row)
            if sys.stderr.isatty():
                print(json.dumps(row), file=sys.stderr)
    result = {"source": source, "gaps": args.gaps, "seed": args.seed, "rows": rows}
    if args.plot:
        plot(rows, args.plot, f"recovery vs gap length ({Path(source).name}, {args.gaps} gaps)")
        result["plot"] = args.plot
    emit(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
