"""``mocap-labeler simulate-shoulder OUT``: synthetic dense shoulder captures plus ground truth.

Writes ``OUT/rom.<fmt>`` (training, range of motion), ``OUT/jumping_jack.<fmt>``,
``OUT/swimming.<fmt>``, ``OUT/curls.<fmt>`` (test motions) and ``OUT/truth.npz`` (true segment
and blend weights of every marker, rest pose, true SC / GH / elbow centres per frame of every
motion; keys in docs/shoulder.md). ``train shoulder OUT/rom.c3d --test ... --truth OUT/truth.npz``
checks its results against it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from labeler_service.cli.args import seed


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="output folder")
    p.add_argument("--frames", type=int, default=4000, help="training (rom) frames [4000]")
    p.add_argument("--test-frames", type=int, default=800, help="frames per test motion [800]")
    p.add_argument("--spacing", type=float, default=27.0, help="marker spacing, mm [27]")
    p.add_argument("--noise", type=float, default=2.5, help="soft-tissue noise std, mm [2.5]")
    p.add_argument(
        "--gap-rate", type=float, default=0.0, help="occlusion gaps per marker per 1000 frames [0]"
    )
    p.add_argument("--rate", type=float, default=120.0, help="frame rate, 10-10000 Hz [120]")
    p.add_argument("--seed", type=seed, default=0, help="random seed [0]")
    p.add_argument(
        "--format", choices=("c3d", "npz", "trc"), default="c3d", help="capture format [c3d]"
    )


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from labeler_service.capture import write_capture
    from labeler_service.errors import SceneError
    from offline.shoulder.simulate import (
        MOTIONS,
        build_body,
        check_motion,
        simulate_motion,
        truth_arrays,
    )

    out = Path(args.out)
    # every argument checked before the first file is written (a refused --test-frames left
    # a new rom capture beside an earlier run's test captures and truth)
    for n, option in ((args.frames, "--frames"), (args.test_frames, "--test-frames")):
        check_motion(n, args.rate, args.noise, args.gap_rate, frames_name=option)
    if out.exists() and not out.is_dir():
        raise SceneError(f"{out}: exists and is not a folder")
    body = build_body(args.spacing)
    rng = np.random.default_rng(args.seed)
    motions = []
    written = {}
    for name in MOTIONS:
        n = args.frames if name == "rom" else args.test_frames
        m = simulate_motion(
            body, name, n, rate=args.rate, noise_mm=args.noise, gap_rate=args.gap_rate,
            random_state=rng,
        )  # fmt: skip
        path = write_capture(m.capture, out / f"{name}.{args.format}")
        motions.append(m)
        written[name] = str(path)
    truth = out / "truth.npz"
    arrays: dict = truth_arrays(body, motions)
    np.savez_compressed(truth, **arrays)
    print(
        json.dumps(
            {
                "markers": body.n_markers,
                "segments": {
                    n: int(c)
                    for n, c in zip(
                        ("chest", "girdle", "upper_arm", "forearm"),
                        np.bincount(body.segment, minlength=4),
                        strict=True,
                    )
                },
                "captures": written,
                "truth": str(truth),
            }
        )
    )
    return 0
