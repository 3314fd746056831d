"""``mocap-labeler info FILE``: rate, frames, subjects, markers, missing fraction, gaps."""

from __future__ import annotations

import argparse
import json

import numpy as np

from labeler_service.capture import Capture, read_segment
from labeler_service.wording import first_of, plural


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="capture file (.c3d, .trc, .npz), FILE[:start[:stop]] (frames)")
    p.add_argument("--up", choices=("z", "y"), default="z", help="vertical axis of the file")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")


def up_hint(cap: Capture) -> str | None:
    """A note when every subject of the capture, as read, looks Y-up (``detect_up`` on each
    subject's markers: a composed scene of Z-up people spread wide is not mistaken): the
    commands read Z up unless told ``--up y``. None otherwise (Z up, or undecided). The
    labeler does not depend on the axis (BTS's walk: the same accuracy read either way)."""
    from labeler_service.errors import SceneError
    from labeler_service.scenes.compose import detect_up

    facts = []
    for s in cap.subjects:
        try:
            up, why = detect_up(cap.select(cap.subject_columns(s)), s or "take")
        except SceneError:
            return None
        if up != "y":
            return None
        facts.append(why)
    if not facts:
        return None
    return (
        f"looks Y-up ({facts[0]}): read it with --up y (compose: TAKE:start:y) where the "
        "vertical axis matters (a composed scene, the live view); labeling does not depend on it"
    )


def summarize(cap: Capture) -> dict:
    """The numbers ``info`` prints, as a plain dict."""
    gaps = cap.gaps()
    lengths = np.array([g[2] for g in gaps], dtype=np.int64)
    vis = cap.visible
    subjects = {}
    for s in cap.subjects:
        cols = cap.subject_columns(s)
        subjects[s or "(no prefix)"] = {
            "markers": int(cols.size),
            "missing_fraction": round(float(1 - vis[:, cols].mean()), 4)
            if cols.size and cap.n_frames
            else 0.0,
        }
    ghosts = int(cap.ghost_mask.sum())
    return {
        "file": cap.source,
        "rate_hz": cap.rate,
        "frames": cap.n_frames,
        "duration_s": round(cap.duration, 3),
        "markers": cap.n_markers,
        "unlabeled_tracks": ghosts,
        "subjects": subjects,
        "missing_fraction": round(cap.missing_fraction, 4),
        "never_visible": [cap.labels[i] for i in cap.empty_columns()],
        "gaps": int(len(gaps)),
        "gap_frames_max": int(lengths.max()) if lengths.size else 0,
        "gap_frames_median": float(np.median(lengths)) if lengths.size else 0.0,
        "notes": list(cap.notes)
        + [n for n in (up_hint(cap),) if n is not None]
        + (["holds no frames: nothing to label"] if cap.n_frames == 0 else []),
    }


def run(args: argparse.Namespace) -> int:
    cap = read_segment(args.file, up=args.up)
    s = summarize(cap)
    s["file"] = str(args.file)  # as given: FILE:start:stop keeps its range
    if args.json:
        print(json.dumps(s))
        return 0
    print(f"{s['file']}")
    # the fraction is of the labeled markers' samples (the unlabeled tracks are said below;
    # "136 markers, 100 % missing" of a label output read as if nothing was there)
    named = s["markers"] - s["unlabeled_tracks"]
    cols = plural(named, "marker") if named else plural(s["unlabeled_tracks"], "unlabeled track")
    print(
        f"  {plural(s['frames'], 'frame')} at {s['rate_hz']:g} Hz ({s['duration_s']:.2f} s), "
        f"{cols}, {s['missing_fraction']:.1%} of their samples missing"
    )
    for name, sub in s["subjects"].items():
        print(
            f"  subject {name}: {plural(sub['markers'], 'marker')}, "
            f"{sub['missing_fraction']:.1%} missing"
        )
    if s["unlabeled_tracks"]:
        print(f"  {plural(s['unlabeled_tracks'], 'unlabeled track')} (*N)")
    if s["never_visible"]:
        print(f"  never visible: {_some(s['never_visible'])}")
    print(
        f"  {plural(s['gaps'], 'gap')} inside tracks "
        f"(longest {plural(s['gap_frames_max'], 'frame')}, "
        f"median {s['gap_frames_median']:g})"
    )
    for note in s["notes"]:
        print(f"  note: {note}")
    return 0


#: names the text summary lists before "and N more" (the JSON lists them all)
LISTED = 12


def _some(names: list[str]) -> str:
    """``names`` for one line of the summary: all of them up to :data:`LISTED`, else the first
    ones and how many more (a recording of a model's 500 markers printed every name on one
    line); ``--json`` keeps the whole list."""
    head = f"{len(names)} markers: " if len(names) > LISTED else ""
    return head + first_of(names, LISTED)
