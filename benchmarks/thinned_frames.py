"""Frames thinned for everyone (a system dropout): errors with and without the vanish check.

A subject labeled with fewer than ``presence_drop`` of the markers observed in the previous
frame is checked as absent (docs/algorithm.md, "A subject vanishing at once"). A frame that
keeps only a share of *every* performer's points, drawn at random over the volume, is no one
leaving. Per rate: simulated ``walk`` x2 and ``hug`` x3, seeds 1-10, labeled for 0.5 s, a
frame (or three) at 2 s thinned to ``keep`` of its points; the errors after the labeled start
(samples whose point carries another label or none), summed over the runs, per
``presence_drop`` value, so ``--drops 0.25 0`` compares the check on and off.

    .venv/bin/python benchmarks/thinned_frames.py --rate 30 120 --drops 0.25 0
"""

from __future__ import annotations

import argparse

from _common import emit

from labeler_service.labeling.config import LabelerConfig
from labeler_service.testing.dropout import thinned_errors

#: (kept share of the points, frames thinned in a row)
CASES = ((0.1, 1), (0.2, 3), (0.3, 3))
SCENES = ((2, "walk"), (3, "hug"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, nargs="+", default=[30.0, 120.0])
    ap.add_argument("--drops", type=float, nargs="+", default=[0.25, 0.0])
    ap.add_argument("--seeds", type=int, default=10, help="seeds 1..N per scene")
    ap.add_argument("--out", help="also write the JSON here")
    a = ap.parse_args(argv)
    rows = []
    for rate in a.rate:
        for keep, length in CASES:
            row = {"rate": rate, "keep": keep, "frames": length, "errors": {}}
            for drop in a.drops:
                config = LabelerConfig(presence_drop=drop)
                runs = [
                    thinned_errors(config, rate, keep, length, n, scenario, seed)
                    for n, scenario in SCENES
                    for seed in range(1, a.seeds + 1)
                ]
                row["errors"][str(drop)] = {"sum": sum(runs), "max": max(runs)}
            rows.append(row)
    emit({"cases": rows}, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
