"""``mocap-labeler simulate OUT --performers N --seconds S --scenario {walk,hug,pile} --seed K
[--rate HZ] [--ghosts R]``: a simulated, labeled multi-person capture.

See :mod:`labeler_service.scenes.simulate` for the body model, motion, occlusion and ghosts.
"""

from __future__ import annotations

import argparse

from labeler_service.cli.args import rate, seed
from labeler_service.scenes.sim import SCENARIOS
from labeler_service.wording import plural


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="output capture (.c3d, .trc or .npz)")
    p.add_argument("--performers", type=int, required=True, help="number of people, 1-10")
    p.add_argument("--seconds", type=float, required=True, help="scene length in seconds")
    p.add_argument("--scenario", choices=SCENARIOS, required=True, help="what the people do")
    p.add_argument("--seed", type=seed, required=True, help="seed (bodies, motion, noise)")
    p.add_argument(
        "--rate", type=rate, default=120.0, help="frame rate in Hz, at most 2000 (default 120)"
    )
    p.add_argument(
        "--ghosts", type=float, default=1.0, help="mean ghost points per frame (default 1)"
    )


def run(args: argparse.Namespace) -> int:
    from labeler_service.capture import check_writable, write_capture
    from labeler_service.scenes.simulate import simulate_scene

    check_writable(args.out)
    scene = simulate_scene(
        args.performers, args.seconds, args.scenario, args.seed, rate=args.rate, ghosts=args.ghosts
    )
    path = write_capture(scene, args.out)
    ghosts = int(scene.ghost_mask.sum())
    labeled = scene.n_markers - ghosts
    print(
        f"{path}: {args.scenario}, {plural(len(scene.subjects), 'subject')} "
        f"({', '.join(scene.subjects)}), {plural(labeled, 'marker')} + "
        f"{plural(ghosts, 'ghost column')}, {plural(scene.n_frames, 'frame')} at "
        f"{scene.rate:g} Hz, {scene.missing_fraction:.1%} of marker samples occluded"
    )
    return 0
