"""``mocap-labeler train shoulder TRAIN --out DIR``: the data-driven shoulder skeleton of Hong,
Park and Hodgins (2009).

::

    mocap-labeler train shoulder TRAIN.c3d [--test NAME=FILE | FILE ...] --out DIR
        [--k 3 4 5 6] [--restarts 1000] [--seed 0] [--faces FILE] [--truth FILE]
        [--subject NAME] [--max-strain 2.0] [--structure auto|chain|tree] [--no-plots]

TRAIN is the training capture (range of motion). Each ``--test`` is a test motion with the same
markers (labels matched by name; a marker the test lacks counts as missing); its name is NAME or
the file stem. TRAIN and each test FILE may be ``FILE[:start[:stop]]`` (a frame range, as
``train structure`` and ``label`` take it). ``--faces`` gives the marker surface (else built
from the rest pose, see :mod:`offline.shoulder.triangles`); ``--truth`` a ``truth.npz`` from
``simulate-shoulder`` to check segments and joint centres. With several subjects in TRAIN,
``--subject`` picks the one to segment (default: the one with most markers); other subjects
(e.g. a handled box) and unlabeled tracks are excluded. Writes to DIR: ``report.md``,
``results.json``, ``skeleton_k<k>.json``, ``faces.txt``, plots ``error_train.png``,
``error_test_full.png``, ``error_test_reduced.png``, ``segments_k<k>.png``; those files of an
earlier run in DIR that this run does not write (another ``--k``, ``--no-plots``) are removed,
with a note. The last stdout line is a JSON summary.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from labeler_service.cli.args import seed, strain_ratio
from labeler_service.errors import ModelError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("train", help="training capture (.c3d, .trc, .npz)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--test", action="append", default=[], metavar="NAME=FILE",
        help="test motion (repeatable); NAME defaults to the file stem",
    )  # fmt: skip
    p.add_argument("--k", type=int, nargs="+", default=[3, 4, 5, 6], help="segment counts")
    p.add_argument("--restarts", type=int, default=1000, help="k-means restarts [1000]")
    p.add_argument("--seed", type=seed, default=0, help="random seed [0]")
    p.add_argument("--faces", help="marker-surface triangles (three marker names per line)")
    p.add_argument("--truth", help="ground truth truth.npz from simulate-shoulder")
    p.add_argument("--subject", help="subject to segment (default: the one with most markers)")
    p.add_argument("--up", choices=("z", "y"), default="z", help="vertical axis of the files")
    p.add_argument(
        "--max-strain", type=strain_ratio, default=2.0,
        help="near-rigid triangle filter: an edge's 95th / 5th percentile length, > 1 [2.0]",
    )  # fmt: skip
    p.add_argument(
        "--structure", choices=("auto", "chain", "tree"), default="auto",
        help="skeleton structure [auto: the paper's chain unless the tree reproduces the "
        "training surface better]",
    )  # fmt: skip
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")


def _parse_tests(items: list[str]) -> list[tuple[str, Path]]:
    from labeler_service.errors import CaptureError

    out, seen = [], set()
    for item in items:
        name, sep, path = item.partition("=")
        if not sep:
            name, path = Path(item).stem, item
        if not name or not path:
            raise CaptureError(f"--test expects NAME=FILE or FILE, got {item!r}")
        if name in seen:
            raise CaptureError(f"--test name {name!r} given twice")
        seen.add(name)
        out.append((name, Path(path)))
    return out


def _command_line(args: argparse.Namespace) -> str:
    """The command as it would be typed (for the report), rebuilt from the parsed options."""
    parts = ["mocap-labeler", "train", "shoulder", str(args.train)]
    parts += [x for t in args.test for x in ("--test", t)]
    parts += ["--out", str(args.out), "--k", *map(str, sorted(set(args.k)))]
    parts += ["--restarts", str(args.restarts), "--seed", str(args.seed)]
    for flag, value in (("--faces", args.faces), ("--truth", args.truth),
                        ("--subject", args.subject)):  # fmt: skip
        if value:
            parts += [flag, str(value)]
    if args.up != "z":
        parts += ["--up", args.up]
    if args.max_strain != 2.0:
        parts += ["--max-strain", str(args.max_strain)]
    if args.structure != "auto":
        parts += ["--structure", args.structure]
    if args.no_plots:
        parts.append("--no-plots")
    return " ".join(parts)


def run(args: argparse.Namespace) -> int:
    from offline.shoulder.pipeline import TrainConfig, train

    cfg = TrainConfig(
        train=Path(args.train),
        tests=_parse_tests(args.test),
        out=Path(args.out),
        ks=tuple(sorted(set(args.k))),
        restarts=args.restarts,
        seed=args.seed,
        faces=Path(args.faces) if args.faces else None,
        truth=Path(args.truth) if args.truth else None,
        subject=args.subject,
        up=args.up,
        max_strain=args.max_strain,
        structure=args.structure,
        plots=not args.no_plots,
        argv=_command_line(args),
    )
    t0 = time.perf_counter()
    try:
        summary = train(cfg)
    except OSError as exc:  # a full disk, a folder gone meanwhile
        where = exc.filename or cfg.out
        raise ModelError(f"{where}: cannot write: {exc.strerror or exc}") from exc
    summary["wall_s"] = round(time.perf_counter() - t0, 2)
    from labeler_service.tools.subscribe import strict_json

    print(strict_json(summary))
    return 0
