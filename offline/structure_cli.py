"""``mocap-labeler train structure IN... --out MODEL``: subject templates from labeled captures.

Each ``IN`` is ``TAKE[:start[:stop]]``: a labeled capture and, optionally, the frame range to
train on (``start`` inclusive, ``stop`` exclusive, in the take's own frames), so that a model
can be trained on other segments of the takes a scene is made of. Subjects are named as
``compose`` names them: a take's own subject prefix, else its file stem (an unprefixed
single-person take ``walk.c3d`` trains subject ``walk``); ``--rename OLD=NEW`` renames a
subject of the model (repeatable), ``--rename K:OLD=NEW`` in the K-th input only (``compose``
names a second subject of the same name ``NAME_2``: ``--rename 2:NAME=NAME_2`` trains it apart).
One name in two inputs is one person's template; inputs whose marker sets under that name
share less than half of the smaller one are refused (two people under one name). A model whose
subject names match the scene's is what ``evaluate --model`` and ``label --model`` score and
label against.
"""

from __future__ import annotations

import argparse
import dataclasses
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
        metavar="[K:]OLD=NEW",
        help="rename subject OLD to NEW in every input, or in the K-th input only (from 1; "
        "e.g. 2:Derrick=Derrick_2, as compose names a second subject of the same name); "
        "repeatable",
    )
    p.add_argument("--out", required=True, metavar="MODEL", help="model file to write (JSON)")
    p.add_argument("--up", choices=("z", "y"), default="z", help="vertical axis of the files")
    p.add_argument("--tolerance-mm", type=float, default=6.0, help="largest A + w D in a body")
    p.add_argument(
        "--distance-weight", type=float, default=0.02, help="w: preference for close pairs"
    )
    p.add_argument("--min-size", type=int, default=3, help="fewest markers per body")
    p.add_argument("--max-size", type=int, default=6, help="most markers per body (<= 8)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    from labeler_service.labeling.templates import same_templates, save_model
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
    _check_present(model)
    save_model(model, args.out)
    twins = same_templates(model)
    summary = {
        "out": args.out,
        "frames": trainer.n_frames_,
        "same_template": [list(p) for p in twins],
        "subjects": {
            s.name: {
                "markers": len(s.markers),
                "bodies": len(s.bodies),
                "body_sizes": [len(b) for b in s.bodies],
                "chirality": len(s.chirality),
                "no_body": s.no_body,
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
        for a, b in twins:
            print(f"{a} and {b} have one template (same markers and distances): a boot cannot "
                  "tell them apart, so each keeps its name only by continuity and which one is "
                  "called which at the first boot is arbitrary")  # fmt: skip
        print(f"wrote {args.out}")
    return 0


def _check_present(model) -> None:
    """Refuses a model with a subject the labeler could never see present: fewer of its
    markers in rigid bodies (seen in 3 or more training frames) than the presence check needs
    (``LabelerConfig.presence_min_markers``). Such a template labels nothing, and the boot that
    then finds no one blamed the performers' distances (a hostile run: a take with one visible
    marker gave "39 markers in 1 rigid bodies" and exit 0)."""
    from labeler_service.errors import ModelError
    from labeler_service.labeling.config import LabelerConfig

    need = LabelerConfig().presence_min_markers
    thin = []
    for s in model.subjects:
        seen = len(s.markers) - len(s.no_body)
        if seen < need:
            thin.append(f"{s.name} ({seen} of {len(s.markers)})")
    if thin:
        raise ModelError(
            f"too few markers seen in the training frames to ever label "
            f"{'this subject' if len(thin) == 1 else 'these subjects'}: {', '.join(thin)}; a "
            f"subject needs {need} or more markers each seen in 3 or more frames. Train on "
            "frames where the subject is in view (TAKE:start:stop)"
        )


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
    """``TAKE[:start[:stop]]`` -> ``(path, start, stop)``; TAKE may hold colons: the longest
    prefix that is a capture file is the file (:func:`~labeler_service.capture.io.split_spec`)."""
    from pathlib import Path

    from labeler_service.capture.io import split_spec
    from labeler_service.errors import ModelError

    syntax = "expected TAKE[:start[:stop]] (frames)"
    path, nums = split_spec(text, 2)
    if len(nums) > 2:
        raise ModelError(f"bad take {text!r}: too many ':' fields after {path}: {syntax}")
    try:
        vals = [int(x) if x != "" else None for x in nums]
    except ValueError:
        missing = "" if Path(path).exists() else f" (and no file {text!r} exists)"
        raise ModelError(f"bad take {text!r}: {syntax}{missing}") from None
    start = vals[0] if vals and vals[0] is not None else 0
    stop = vals[1] if len(vals) > 1 else None
    if start < 0 or (stop is not None and stop <= start):
        raise ModelError(f"bad take {text!r}: need 0 <= start < stop")
    return path, start, stop


#: A subject name two takes share is one person only when their marker sets share at least this
#: fraction of the smaller one (:func:`_check_shared_names`).
SHARED_MARKERS_MIN = 0.5


def _renames(items: list[str]) -> dict[int | None, dict[str, str]]:
    """``--rename [K:]OLD=NEW`` -> per input (1-based ``K``; None: every input) ``{OLD: NEW}``."""
    from labeler_service.errors import ModelError

    out: dict[int | None, dict[str, str]] = {}
    for it in items:
        spec, sep, new = it.partition("=")
        k_text, colon, old = spec.rpartition(":")
        if not colon:
            k_text, old = "", spec
        digits = k_text.isascii() and k_text.isdigit()
        if not sep or not old or not new or ":" in new or "=" in new or (colon and not digits):
            raise ModelError(
                f"bad --rename {it!r}: expected OLD=NEW, or K:OLD=NEW for the K-th input only "
                "(no ':' or '=' in NEW)"
            )
        k = int(k_text) if colon else None
        if k is not None and k < 1:
            raise ModelError(f"bad --rename {it!r}: inputs are counted from 1")
        if out.get(k, {}).get(old, new) != new:
            raise ModelError(f"--rename {it!r}: {old} is renamed twice")
        out.setdefault(k, {})[old] = new
    return out


def _read_takes(texts: list[str], up: str, rename: dict[int | None, dict[str, str]]) -> list:
    """The takes, renamed; an OLD name no take has is an error (a misspelt one renamed
    nothing, and the model kept a name the scene does not use). A subject never seen in a
    take is left out of it, with a note (training stopped at it)."""
    import sys

    from labeler_service.errors import ModelError
    from labeler_service.wording import plural

    for k in rename:
        if k is not None and k > len(texts):
            raise ModelError(f"--rename {k}:...: only {plural(len(texts), 'input')} given")
    caps = []
    for text in texts:
        cap, absent = _read_take(text, up).without_absent_subjects()
        named = [x for x in cap.subjects if x]
        if "" in cap.subjects and named:
            # the reader names a take's bare labels after its file only when none has a
            # subject; beside named ones they are subject "" to info, evaluate and label, and a
            # model could only give them another name (evaluate then scored 955 of them
            # cross-subject: a hostile run)
            bare = [cap.labels[i] for i in cap.subject_columns("")]
            raise ModelError(
                f"{text}: {plural(len(bare), 'label')} name no subject ({', '.join(bare[:4])}"
                f"{', ...' if len(bare) > 4 else ''}) beside subject {', '.join(named)}: a model "
                "names every marker SUBJECT:MARKER; label them so (a take whose labels all lack "
                "a subject is named after its file)"
            )
        for name in absent:
            print(
                f"note: {text}: subject {name} is never seen in the take: left out", file=sys.stderr
            )
        caps.append(cap)
    for k, names in rename.items():
        scope = caps if k is None else [caps[k - 1]]
        found = {s for c in scope for s in c.subjects if s}
        for old, new in names.items():
            if old not in found:
                where = "the takes" if k is None else f"input {k} ({texts[k - 1]})"
                raise ModelError(
                    f"--rename {'' if k is None else f'{k}:'}{old}={new}: no subject {old!r} in "
                    f"{where} (found {', '.join(sorted(found))})"
                )
    out, given = [], []
    for i, c in enumerate(caps):
        ren = {**rename.get(None, {}), **rename.get(i + 1, {})}
        after: dict[str, str] = {}  # new name -> the take's subject it came from
        for subj in (s for s in c.subjects if s):
            name = ren.get(subj, subj)
            if name in after:  # (two people of one take merged into one template, silently)
                a, b = sorted((after[name], subj), key=lambda x: x != name)
                raise ModelError(
                    f"--rename: input {i + 1} ({texts[i]}) would have subjects {a} and {b} both "
                    f"named {name}: two people under one name (rename one of them to a name the "
                    "take does not use)"
                )
            after[name] = subj
        out.append(_renamed(c, ren))
        given.append({new: old for old, new in ren.items()})  # model name -> the take's
    _check_shared_names(out, texts, given)
    return out


def _check_shared_names(caps: list, texts: list[str], given: list[dict[str, str]]) -> None:
    """Takes that give one subject name marker sets sharing less than
    :data:`SHARED_MARKERS_MIN` of the smaller are two people under one name: refused (their
    markers were merged into one template that fitted neither, silently). ``given[i]``: input
    ``i``'s renames, model name -> the name in the take (what ``--rename i:`` must name)."""
    from labeler_service.capture import split_label
    from labeler_service.errors import ModelError

    seen: dict[str, tuple[int, set[str]]] = {}
    for i, cap in enumerate(caps):
        for subj in cap.subjects:
            if not subj:
                continue
            markers = {split_label(cap.labels[j])[1] for j in cap.subject_columns(subj)}
            if subj not in seen:
                seen[subj] = (i, markers)
                continue
            j, first = seen[subj]
            common = len(markers & first)
            if common < SHARED_MARKERS_MIN * min(len(markers), len(first)):
                raise ModelError(
                    f"subject {subj}: input {j + 1} ({texts[j]}) has {len(first)} markers, "
                    f"input {i + 1} ({texts[i]}) {len(markers)}, {common} of them in common: two "
                    f"people under one name? Name one apart with --rename "
                    f"{i + 1}:{given[i].get(subj, subj)}=NEW "
                    "(compose names a second subject of the same name NAME_2)"
                )


def _read_take(text: str, up: str):
    """The capture of ``TAKE[:start[:stop]]``, its subjects named as ``compose`` names them."""
    from pathlib import Path

    from labeler_service.capture import read_capture
    from labeler_service.capture.io import segment_source
    from labeler_service.errors import ModelError

    path, start, stop = parse_take(text)
    if not Path(path).exists():
        raise ModelError(f"{path}: no such file")
    cap = read_capture(path, up=up)
    if start >= cap.n_frames:
        raise ModelError(f"{text}: start {start} is past the take's {cap.n_frames} frames")
    if stop is not None and stop > cap.n_frames:
        raise ModelError(f"{text}: stop {stop} is past the take's {cap.n_frames} frames")
    cap = cap.frames(start, stop)
    if text != path:  # (the model's ``source`` says which frames)
        cap = dataclasses.replace(cap, source=segment_source(path, start, stop))
    if not [s for s in cap.subjects if s]:
        cap = cap.with_subject(Path(path).stem.replace(":", "_") or "subject")
    return cap


def _renamed(cap, rename: dict[str, str]):
    """``cap`` with its subjects OLD named NEW (``--rename [K:]OLD=NEW``)."""
    from labeler_service.capture import Capture, split_label

    if not rename:
        return cap
    labels = []
    for lab in cap.labels:
        subj, marker = split_label(lab)
        labels.append(f"{rename[subj]}:{marker}" if subj in rename else lab)
    return Capture(cap.positions, tuple(labels), cap.rate, source=cap.source)
