"""``mocap-labeler compose OUT TAKE[:start[:up[:subject]]]... --radius MM --frames N --seed S
[--rate HZ]``.

Builds a multi-person scene from labeled takes (see :mod:`labeler_service.scenes.compose`) and
writes it in any format ``write_capture`` supports. Prints one summary line, then one line per
decision compose made (up axis, subject, facing, resampling, markers dropped, leaving).
"""

from __future__ import annotations

import argparse

from labeler_service.cli.args import rate, seed
from labeler_service.wording import plural


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="output capture (.c3d, .trc or .npz)")
    p.add_argument(
        "takes",
        nargs="+",
        metavar="TAKE[:start[:up[:subject]]]",
        help="labeled take; start = first frame (default 0); up = z, y or auto (default: "
        "detected, an ambiguous take must say); subject = the one to take from a "
        "multi-subject file",
    )
    p.add_argument("--radius", type=float, required=True, help="circle radius in mm (e.g. 300)")
    p.add_argument("--frames", type=int, required=True, help="frames in the scene (output rate)")
    p.add_argument("--seed", type=seed, required=True, help="seed for phase and yaw offsets")
    p.add_argument(
        "--rate",
        type=rate,
        default=None,
        help="resample every take to this rate (Hz, at most the lowest take rate)",
    )


def run(args: argparse.Namespace) -> int:
    from labeler_service.capture import c3d_frames_fit, check_writable, write_capture
    from labeler_service.scenes.compose import TakeSpec, compose_scene

    specs = [TakeSpec.parse(t) for t in args.takes]
    check_writable(args.out, inputs=tuple(s.path for s in specs if s.path is not None))
    c3d_frames_fit(args.out, args.frames)
    scene = compose_scene(specs, args.radius, args.frames, args.seed, rate=args.rate)
    path = write_capture(scene, args.out)
    subjects = scene.subjects
    print(
        f"{path}: {plural(len(subjects), 'subject')} ({', '.join(subjects)}), "
        f"{plural(scene.n_markers, 'marker')}, {plural(scene.n_frames, 'frame')} at "
        f"{scene.rate:g} Hz"
    )
    for note in scene.notes:
        print(f"  {note}")
    return 0
