"""``mocap-labeler train structure IN... --out MODEL``: subject templates from labeled captures.

Each ``IN`` is ``TAKE[:start[:stop]]``: a labeled capture and, optionally, the frame range to
train on (``start`` inclusive, ``stop`` exclusive, in the take's own frames), so that a model
can be trained on other segments of the takes a scene is made of. Subjects are named as
``compose`` names them: a take's own subject prefix, else its file stem (an unprefixed
single-person take ``walk.c3d`` trains subject ``walk``); ``--rename OLD=NEW`` renames a
subject of the model (repeatable). A model whose subject names match the scene's is what
``evaluate --model`` and ``label --model`` score and label against.
"""

from __future__ import annotations

import argparse
import json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "inputs",
        nargs="+",
        metavar="IN",
        help="labeled captures (.c3d/.trc/.npz), each TAKE[:start[:stop]] (frames)",
    )
    p.add_argument(
        "--rename",
        action="append",
        default=[],
        metavar="OLD=NEW",
        help="rename subject OLD of the model to NEW (repeatable)",
    )
    p.add_argument("--out", required=True, metavar="MODEL", help="model file to write (JSON)")
    p.add_argument("--up", choices=("z", "y"), default="z", help="vertical axis of the files")
    p.add_argument("--tolerance-mm", type=float, default=6.0, help="largest A + w D in a body")
    p.add_argument("--distance-weight", type=float, default=0.02, help="w: preference for close")
    p.add_argument("--min-size", type=int, default=3, help="fewest markers per body")
    p.add_argument("--max-size", type=int, default=6, help="most markers per body (<= 8)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    from labeler_service.labeling.templates import save_model
    from labeler_service.labeling.training import DUPLICATE_MM
    from offline.structure import StructureTrainer

    _check_out(args.out, [parse_take(t)[0] for t in args.inputs])  # (bad takes said first)
    trainer = StructureTrainer(
        tolerance_mm=args.tolerance_mm,
        distance_weight=args.distance_weight,
        min_size=args.min_size,
        max_size=args.max_size,
        up=args.up,
    ).fit(_read_takes(args.inputs, args.up, _renames(args.rename)))
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
                "chirality": len(s.chirality),
                "no_body": sorted(set(s.markers) - {s.markers[i] for b in s.bodies for i in b}),
            }
            for s in model.subjects
        },
    }
    if args.json:
        print(json.dumps(summary))
    else:
        for name, s in summary["subjects"].items():
            hand = (
                f"{s['chirality']} chirality quadruples"
                if s["chirality"]
                else "no chirality quadruples (a boot cannot refuse a mirrored reading)"
            )
            print(f"{name}: {s['markers']} markers in {s['bodies']} rigid bodies, {hand}")
            if s["no_body"]:
                print(f"  never labeled (no body: seen in fewer than 3 frames, or a duplicate "
                      f"track within {DUPLICATE_MM:g} mm of another marker): "
                      f"{', '.join(s['no_body'])}")  # fmt: skip
        print(f"wrote {args.out}")
    return 0


def _check_out(out: str, inputs: list[str]) -> None:
    """Refuses, before the training, a model path that could not be written or that would
    replace a capture: a directory, an unwritable folder, one of the inputs, or a name with a
    capture's suffix (a model is JSON: ``--out take.c3d`` would overwrite a take)."""
    from pathlib import Path

    from labeler_service.capture import SUFFIXES, check_writable
    from labeler_service.errors import ModelError

    if Path(out).suffix.lower() in SUFFIXES:
        raise ModelError(
            f"{out}: a model is JSON, not a capture ({Path(out).suffix}): "
            "name it e.g. model.json (this would replace a capture file)"
        )
    check_writable(out, suffixes=None, inputs=tuple(inputs))


def parse_take(text: str) -> tuple[str, int, int | None]:
    """``TAKE[:start[:stop]]`` -> ``(path, start, stop)``; a ``TAKE`` that exists as a file is
    taken whole even if its name holds colons."""
    from pathlib import Path

    from labeler_service.errors import ModelError

    if Path(text).exists():
        return text, 0, None
    parts = text.rsplit(":", 2)
    path, nums = parts[0], parts[1:]
    try:
        vals = [int(x) if x != "" else None for x in nums]
    except ValueError:
        raise ModelError(f"bad take {text!r}: expected TAKE[:start[:stop]] (frames)") from None
    start = vals[0] if vals and vals[0] is not None else 0
    stop = vals[1] if len(vals) > 1 else None
    if start < 0 or (stop is not None and stop <= start):
        raise ModelError(f"bad take {text!r}: need 0 <= start < stop")
    return path, start, stop


def _renames(items: list[str]) -> dict[str, str]:
    from labeler_service.errors import ModelError

    out = {}
    for it in items:
        old, sep, new = it.partition("=")
        if not sep or not old or not new or ":" in new:
            raise ModelError(f"bad --rename {it!r}: expected OLD=NEW (no ':' in NEW)")
        out[old] = new
    return out


def _read_takes(texts: list[str], up: str, rename: dict[str, str]) -> list:
    """The takes, renamed; an OLD name no take has is an error (a misspelt one renamed
    nothing, and the model kept a name the scene does not use). A subject never seen in a
    take is left out of it, with a note (training stopped at it)."""
    import sys

    from labeler_service.errors import ModelError

    caps = []
    for text in texts:
        cap, absent = _read_take(text, up).without_absent_subjects()
        for name in absent:
            print(
                f"note: {text}: subject {name} is never seen in the take: left out", file=sys.stderr
            )
        caps.append(cap)
    found = {s for c in caps for s in c.subjects if s}
    for old in rename:
        if old not in found:
            raise ModelError(
                f"--rename {old}={rename[old]}: no subject {old!r} in the takes "
                f"(found {', '.join(sorted(found))})"
            )
    return [_renamed(c, rename) for c in caps]


def _read_take(text: str, up: str):
    """The capture of ``TAKE[:start[:stop]]``, its subjects named as ``compose`` names them."""
    from pathlib import Path

    from labeler_service.capture import read_capture
    from labeler_service.errors import ModelError

    path, start, stop = parse_take(text)
    if not Path(path).exists():
        raise ModelError(f"{path}: no such capture")
    cap = read_capture(path, up=up)
    if start >= cap.n_frames:
        raise ModelError(f"{text}: start {start} is past the take's {cap.n_frames} frames")
    cap = cap.frames(start, stop)
    if not [s for s in cap.subjects if s]:
        cap = cap.with_subject(Path(path).stem.replace(":", "_") or "subject")
    return cap


def _renamed(cap, rename: dict[str, str]):
    """``cap`` with its subjects OLD named NEW (``--rename OLD=NEW``)."""
    from labeler_service.capture import Capture, split_label

    if not rename:
        return cap
    labels = []
    for lab in cap.labels:
        subj, marker = split_label(lab)
        labels.append(f"{rename[subj]}:{marker}" if subj in rename else lab)
    return Capture(cap.positions, tuple(labels), cap.rate, source=cap.source)
