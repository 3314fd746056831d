"""``mocap-labeler train structure IN... --out MODEL``: subject templates from labeled captures."""

from __future__ import annotations

import argparse
import json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", nargs="+", metavar="IN", help="labeled captures (.c3d/.trc/.npz)")
    p.add_argument("--out", required=True, metavar="MODEL", help="model file to write (JSON)")
    p.add_argument("--up", choices=("z", "y"), default="z", help="vertical axis of the files")
    p.add_argument("--tolerance-mm", type=float, default=6.0, help="largest A + w D in a body")
    p.add_argument("--distance-weight", type=float, default=0.02, help="w: preference for close")
    p.add_argument("--min-size", type=int, default=3, help="fewest markers per body")
    p.add_argument("--max-size", type=int, default=6, help="most markers per body (<= 8)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    from labeler_service.labeling.templates import save_model
    from offline.structure import StructureTrainer

    trainer = StructureTrainer(
        tolerance_mm=args.tolerance_mm,
        distance_weight=args.distance_weight,
        min_size=args.min_size,
        max_size=args.max_size,
        up=args.up,
    ).fit(args.inputs)
    model = trainer.model_
    save_model(model, args.out)
    summary = {
        "out": args.out,
        "frames": trainer.n_frames_,
        "subjects": {
            s.name: {
                "markers": len(s.markers),
                "bodies": len(s.bodies),
                "body_sizes": [len(b) for b in s.bodies],
            }
            for s in model.subjects
        },
    }
    if args.json:
        print(json.dumps(summary))
    else:
        for name, s in summary["subjects"].items():
            print(f"{name}: {s['markers']} markers in {s['bodies']} rigid bodies")
        print(f"wrote {args.out}")
    return 0
