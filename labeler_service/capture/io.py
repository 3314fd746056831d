"""Reading and writing captures: C3D (ezc3d), TRC (text) and NPZ (numpy, lossless and fast).

Every reader returns a :class:`Capture` in millimetres, Z up, NaN for missing samples:
(0, 0, 0) samples, infinite ones, ones farther than 10 km (``MAX_COORD_MM``) and negative C3D
residuals become NaN, metres are converted, and a take recorded Y-up is rotated when the caller
says so (``up="y"``). What was changed is
recorded in ``Capture.notes``. A file whose labels carry no ``subject:`` prefix is one subject
named after the file stem. Problems raise :class:`CaptureError` naming the file, never a bare
traceback.

Points a processing model wrote beside the markers (angles, forces, virtual markers: the groups
the C3D's POINT parameters list) are left out with a note (:func:`_c3d_markers`).

A C3D that ends before the frames its header declares is read up to its last complete frame
(ezc3d does so silently); the reader adds the note ``truncated: K of N frames`` and logs it as a
warning (stderr from the CLI). A TRC is read from its own columns, split at tabs, commas or
spaces, each name on the columns it heads (:func:`_trc_names`); where they disagree with its
header (NumMarkers, NumFrames, a DataRate unlike the Time column) or a row is short or cut, the
reader says so in the notes (:func:`_read_trc`).

A frame rate no capture has (outside 1 to 10,000 Hz: :func:`~labeler_service.capture.model.
rate_problem`) is refused, naming it; a TRC whose DataRate is missing or such a rate is read at
its Time column's spacing instead, with a note (:func:`_trc_rate`).

Writers write a temporary file beside the target, check it (ezc3d reports no I/O error, so a
C3D must have its full size) and rename it over the target.
A C3D is written in millimetres with the labels as ``subject:marker`` and the Vicon ``SUBJECTS``
group (names and label prefixes).
"""

from __future__ import annotations

import contextlib
import logging
import math
import mmap
import os
import re
import signal
import struct
import threading
import time
import uuid
import zipfile
import zlib
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from labeler_service.capture.model import (
    MAX_COORD_MM,
    MAX_RATE_HZ,
    MIN_RATE_HZ,
    Capture,
    is_ghost,
    rate_problem,
    split_label,
)
from labeler_service.errors import CaptureError, CaptureFormatError
from labeler_service.wording import plural

log = logging.getLogger(__name__)

SUFFIXES = (".c3d", ".trc", ".npz")
_Writer = Callable[[Capture, Path], None]
_UNIT_SCALE = {
    **dict.fromkeys(("mm", "millimeter", "millimeters", "millimetre", "millimetres"), 1.0),
    **dict.fromkeys(("cm", "centimeter", "centimeters", "centimetre", "centimetres"), 10.0),
    **dict.fromkeys(("m", "meter", "meters", "metre", "metres"), 1000.0),
}


def read_capture(path: str | Path, up: str = "z", subject: str | None = None) -> Capture:
    """Reads a C3D, TRC or NPZ capture.

    ``up`` is the file's vertical axis (``"z"`` or ``"y"``); a Y-up take is rotated to Z up.
    ``subject`` forces one subject prefix on every label (replacing any prefix in the file).
    """
    p = Path(path)
    if up not in ("z", "y"):
        raise ValueError(f"up must be 'z' or 'y', got {up!r}")
    if p.is_dir():
        raise CaptureError(f"{p}: is a folder, not a capture file (.c3d, .trc, .npz)")
    if not p.is_file():
        if p.exists():  # a FIFO, a device: a capture is read twice (its header, its frames)
            raise CaptureError(f"{p}: not a regular file (a capture must be a file on disk)")
        raise CaptureError(f"{p}: no such file")
    suffix = p.suffix.lower()
    try:
        if suffix == ".c3d":
            cap = _read_c3d(p)
        elif suffix == ".trc":
            cap = _read_trc(p)
        elif suffix == ".npz":
            cap = _read_npz(p)
        else:
            raise CaptureError(f"{p}: unknown capture format {suffix!r} (use .c3d, .trc or .npz)")
    except (CaptureError, ValueError) as exc:
        if isinstance(exc, CaptureError):
            raise
        raise CaptureFormatError(f"{p}: {exc}") from exc
    except Exception as exc:  # a broken file makes ezc3d raise anything
        raise CaptureFormatError(f"{p}: cannot be read as {suffix[1:].upper()}: {exc}") from exc
    if up == "y":
        cap = _y_up_to_z_up(cap)
    if subject is not None:
        cap = cap.with_subject(subject)
    else:
        cap = _default_subject(cap, p.stem)
    return cap


def read_segment(spec: str | Path, up: str = "z") -> Capture:
    """Reads ``FILE[:start[:stop]]`` (frames, as ``train structure`` takes them): the whole
    capture, or that frame range of it (so a model trained on one segment of a take can be
    checked on another). A path that exists is read whole even if its name holds colons."""
    text = str(spec)
    path, start, stop = split_segment(text)
    cap = read_capture(path, up=up)
    if path == text:
        return cap
    if stop is not None and stop <= start:
        raise CaptureError(f"{text}: need start < stop (frames)")
    if start >= cap.n_frames:
        raise CaptureError(f"{text}: start {start} is past the capture's {cap.n_frames} frames")
    if stop is not None and stop > cap.n_frames:
        raise CaptureError(f"{text}: stop {stop} is past the capture's {cap.n_frames} frames")
    notes = (*cap.notes, f"frames {start}-{cap.n_frames if stop is None else stop} of {path}")
    source = segment_source(cap.source or path, start, stop)
    return replace(cap.frames(start, stop), notes=notes, source=source)


def segment_source(path: str | Path, start: int, stop: int | None) -> str:
    """How a segment of ``path`` names itself (its ``source``: a model trained on it says
    which frames, ``FILE:start[:stop]``)."""
    return f"{path}:{start}" + ("" if stop is None else f":{stop}")


def split_spec(text: str, fields: int) -> tuple[str, list[str]]:
    """``PATH[:field...]`` -> ``(PATH, fields)`` for a spec of at most ``fields`` fields after a
    path that may itself hold colons (``take:2.c3d:240``, ``a:b/walk.trc:0:y``). The path is,
    with at most ``fields`` fields after it, the longest prefix cut at a ``:`` that is a file
    named like a capture (``.c3d``, ``.trc``, ``.npz``), else that is any file; else the longest
    file before more fields (the caller says there are too many); else, when no file fits, the
    longest prefix named like a capture (the reader then says "no such file"), then one that
    exists (a folder: the reader says so), else the text up to its first ``:``. A capture file
    comes first: ``take.c3d:10:y`` is frame 10 of ``take.c3d`` beside a stray file
    ``take.c3d:10`` (no capture, by its name), and ``day:1/walk.c3d:5`` beside a folder ``day``
    looks for ``day:1/walk.c3d`` (frame '1/walk.c3d' of the folder ``day`` was read)."""
    parts = text.split(":")
    n = len(parts)
    heads = [(":".join(parts[:k]), parts[k:]) for k in range(n, 0, -1)]  # longest first
    fit = [(head, rest) for head, rest in heads if head and len(rest) <= fields]
    for head, rest in fit:
        if Path(head).suffix.lower() in SUFFIXES and Path(head).is_file():
            return head, rest
    for head, rest in fit:
        if Path(head).is_file():
            return head, rest
    for head, rest in heads:
        if head and Path(head).is_file():
            return head, rest
    for head, rest in fit:
        if Path(head).suffix.lower() in SUFFIXES:
            return head, rest
    for head, rest in fit:
        if Path(head).exists():
            return head, rest
    return parts[0], parts[1:]


def _frame_number(text: str) -> bool:
    """A frame number as a spec writes it: ASCII digits (``int`` takes ``'²'`` as no number
    but ``str.isdigit`` does)."""
    return text.isascii() and text.isdigit()


def split_segment(text: str) -> tuple[str, int, int | None]:
    """``FILE[:start[:stop]]`` -> ``(FILE, start, stop)``; FILE may hold colons
    (:func:`split_spec`: the longest prefix that is a capture file wins). A spec whose file does
    not exist and whose tail is not ``:digits`` is the whole file ``(text, 0, None)`` (the
    reader says "no such file")."""
    path, nums = split_spec(text, 2)
    if not nums:
        return path, 0, None
    if len(nums) > 2:
        raise CaptureError(
            f"{text}: too many ':' fields after {path}: expected FILE[:start[:stop]]"
        )
    if not all(x == "" or _frame_number(x) for x in nums):
        if Path(path).is_file():  # FILE:-5, FILE:a:b - the file exists, its range does not parse
            raise CaptureError(
                f"{text}: bad frame range {':'.join(nums)!r}: expected "
                "FILE[:start[:stop]] with frame numbers >= 0"
            )
        return text, 0, None
    start = int(nums[0]) if nums[0] else 0
    stop = int(nums[1]) if len(nums) == 2 and nums[1] else None
    return path, start, stop


def write_capture(
    capture: Capture,
    path: str | Path,
    like: str | Path | None = None,
    kept: list[str] | None = None,
    calculated: np.ndarray | None = None,
) -> Path:
    """Writes a capture as C3D, TRC or NPZ (by suffix), creating parent folders.

    The file is written to a temporary name next to the target, checked (a C3D must hold every
    frame) and renamed over the target, so a failed write never leaves a half file behind. A
    symbolic link is followed (the file it points to is replaced); a target that exists but is
    not a regular file (a device such as ``/dev/full``, a FIFO) is written through directly.
    Any failure raises :class:`CaptureError` naming the file.

    ``like``: the capture ``capture`` was made from (``FILE[:start[:stop]]``, its frames, in its
    axes, in millimetres). When both are C3D the output keeps everything of ``like`` but its
    points (:func:`_write_c3d_like`: analog channels, events, force plates, every parameter
    group, the time base, the units); otherwise a C3D or TRC output keeps ``like``'s time base
    (the number and time of its first frame, :func:`_time_base`). ``kept`` (a list) is filled
    with what was kept, in words. ``calculated`` (``(F, M)`` bool): samples estimated, not
    observed (a hidden marker's recovered position); a C3D gives them the residual 0, C3D's
    mark of a calculated point, and every other present sample the residual 1.
    """
    p = Path(path)
    target, suffix = _target(p, SUFFIXES)
    said = kept if kept is not None else []
    source, start = (None, 0)
    if like is not None:
        name, start, _ = split_segment(str(like))
        source = Path(name) if Path(name).is_file() else None

    def base() -> tuple[int, float] | None:
        got = None if source is None else _time_base(source, start)
        if got is not None and got[0] != 1:
            said[:] = [f"time base (first frame {got[0]})"]
        return got

    def write_c3d(cap: Capture, tmp: Path) -> None:
        if source is not None and source.suffix.lower() == ".c3d":
            try:
                said[:] = _write_c3d_like(cap, tmp, source, start, calculated)
                return
            except (CaptureError, OSError):
                raise
            except Exception as exc:  # a source ezc3d cannot write back: the points alone
                log.warning("%s: written without the rest of %s (%s: %s)", p, source,
                            type(exc).__name__, exc)  # fmt: skip
        _write_c3d(cap, tmp, base(), calculated)

    writer: _Writer = {
        ".c3d": write_c3d,
        ".trc": lambda cap, tmp: _write_trc(cap, tmp, target.name, base()),
        ".npz": _write_npz,
    }[suffix]
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.exists() and not target.is_file():
            _write_through(capture, target, writer, suffix)
        else:
            # (a TRC's header names the file: the target's name, not the temporary one's)
            replace_file(target, lambda tmp: writer(capture, tmp), suffix)
    except OSError as exc:
        raise CaptureError(f"{p}: cannot write: {os_reason(exc)}") from exc
    except CaptureError as exc:
        raise CaptureError(f"{p}: cannot write: {exc}") from exc
    return p


def check_writable(
    path: str | Path,
    suffixes: tuple[str, ...] | None = SUFFIXES,
    inputs: tuple[str | Path, ...] = (),
) -> Path:
    """Refuses, before any work is done, an output path that :func:`write_capture` could not
    write: unknown suffix (unless ``suffixes`` is ``None``: any file), a directory, a parent
    folder that cannot be created or written, or one of the command's ``inputs`` (files,
    ``FILE:start:stop`` segments): the run would replace the capture it reads."""
    p = Path(path)
    target, suffix = _target(p, suffixes)
    for spec in inputs:
        src = Path(os.path.realpath(split_segment(str(spec))[0]))
        if src == target:
            raise CaptureError(
                f"{p}: is the input {spec}: writing it would replace the capture being read; "
                "choose another output"
            )
    # folders the probe makes are removed again: the writers make them when they write, and a
    # run that fails later leaves no empty folders behind
    created = []
    parent = target.parent
    while not parent.exists() and parent != parent.parent:
        created.append(parent)
        parent = parent.parent
    if not parent.is_dir():  # (mkdir would say only "File exists")
        raise CaptureError(f"{p}: cannot write: {parent} is a file, not a folder")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.exists() and not target.is_file():  # a device or FIFO: opening could block
            if not os.access(target, os.W_OK):
                raise PermissionError(13, "Permission denied")
        else:
            probe = _temp_name(target, suffix)
            fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        raise CaptureError(f"{p}: cannot write: {os_reason(exc)}") from exc
    finally:
        for folder in created:  # deepest first
            with contextlib.suppress(OSError):
                folder.rmdir()
    return p


def _target(p: Path, suffixes: tuple[str, ...] | None) -> tuple[Path, str]:
    """``(the file a write of p replaces, p's lower-case suffix)``: the suffix must be one of
    ``suffixes`` (``None``: any) and the path not a directory; symbolic links resolved."""
    suffix = p.suffix.lower()
    target = Path(os.path.realpath(p))
    if target.is_dir():
        raise CaptureError(f"{p}: cannot write: is a directory")
    if suffixes is not None and suffix not in suffixes:
        raise CaptureError(f"{p}: unknown capture format {suffix!r} (use .c3d, .trc or .npz)")
    return target, suffix


def os_reason(exc: OSError) -> str:
    """``[Errno 28] No space left on device`` without the (temporary) file name."""
    return f"[Errno {exc.errno}] {exc.strerror}" if exc.errno and exc.strerror else str(exc)


def _temp_name(target: Path, suffix: str) -> Path:
    # ends in the real suffix: ezc3d and numpy append one to a name that lacks it
    return target.parent / f".{target.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp{suffix}"


def replace_file(target: Path, write: Callable[[Path], object], suffix: str = "") -> None:
    """Writes ``target`` (a resolved path) through ``write(tmp)`` on a temporary file next to
    it (ending in ``suffix``), synced and renamed over it: the file is complete or untouched,
    and a failed or interrupted write leaves no temporary behind. Captures and models."""
    tmp = _temp_name(target, suffix)
    fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)  # umask applies
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _write_through(capture: Capture, target: Path, writer: _Writer, suffix: str) -> None:
    import shutil
    import tempfile

    with tempfile.TemporaryDirectory(prefix="mocap-write-") as d:
        tmp = Path(d) / f"capture{suffix}"
        writer(capture, tmp)
        with open(tmp, "rb") as src, open(target, "wb") as dst:
            shutil.copyfileobj(src, dst)


# ------------------------------------------------------------------------------ helpers
def _finish(
    positions: np.ndarray, labels: list[str], rate: float, source: Path, notes: list[str]
) -> Capture:
    """Applies the shared missing-sample and label rules, then builds the Capture. A frame
    rate no capture has (:func:`~labeler_service.capture.model.rate_problem`) is refused."""
    why = rate_problem(rate)
    if why is not None:
        raise CaptureFormatError(f"{source}: frame rate {why}")
    with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: inf, mapped below
        pos = np.ascontiguousarray(positions, dtype=np.float32)
    infinite = np.isinf(pos).any(axis=2)
    if infinite.any():  # the labeler takes finite points only: missing, as NaN is
        pos[infinite] = np.nan
        notes.append(f"{int(infinite.sum())} infinite samples mapped to missing")
    nan = np.isnan(pos)
    partial = nan.any(axis=2) & ~nan.all(axis=2)
    if partial.any():  # a sample is a point or missing: one NaN coordinate makes it missing
        pos[partial] = np.nan
        notes.append(
            f"{plural(int(partial.sum()), 'sample')} with some coordinates missing (NaN) mapped "
            "to missing"
        )
    with np.errstate(invalid="ignore"):  # NaN compares False
        far = (np.abs(pos) > MAX_COORD_MM).any(axis=2)
    if far.any():  # garbage (a writer's sentinel, a corrupt file): missing, with a note
        pos[far] = np.nan
        msg = (
            f"{plural(int(far.sum()), 'sample')} beyond {MAX_COORD_MM:g} mm of the origin "
            "mapped to missing (no capture volume is that large)"
        )
        notes.append(msg)
        log.warning("%s: %s", source, msg)
    zero = np.all(pos == 0.0, axis=2)
    if zero.any():
        pos[zero] = np.nan
        notes.append(f"{int(zero.sum())} (0,0,0) samples mapped to missing")
    labels = _unique_labels(_no_empty_prefix([x.strip() for x in labels], notes), notes)
    copies = _exact_copies(pos, labels)
    if copies:
        said = ", ".join(f"{labels[i]} = {labels[j]}" for i, j in copies[:4])
        notes.append(
            f"{plural(len(copies), 'point')} that {'repeats' if len(copies) == 1 else 'repeat'} "
            "another point exactly in every frame left out "
            f"(a computed point, not a marker): {said}{', ...' if len(copies) > 4 else ''}"
        )
        gone = {i for i, _ in copies}
        keep = [k for k in range(len(labels)) if k not in gone]
        pos, labels = np.ascontiguousarray(pos[:, keep]), [labels[k] for k in keep]
    return Capture(
        positions=pos, labels=tuple(labels), rate=rate, source=str(source), notes=tuple(notes)
    )


#: two points closer than this (mm) in every frame where both are seen are one point twice
#: (float32 storage: ~1e-4 mm of rounding at a few metres)
COPY_TOL_MM = 0.01
#: frames sampled to find candidate copies before the full check
COPY_PROBE_FRAMES = 16
#: a point's copies are looked for among its this many nearest points (within COPY_TOL_MM)
COPY_NEIGHBOURS = 8


def _exact_copies(pos: np.ndarray, labels: list[str]) -> list[tuple[int, int]]:
    """``(copy, kept)`` pairs: a column that repeats an earlier one exactly wherever both are
    seen (at least 2 such frames, and never seen alone while the other is missing - a marker
    filled from another's gap is not a copy). Two markers cannot share a position; a processing
    pipeline writes the same computed point under two names (a toe segment's proximal axis
    point is the foot's origin), and such a pair can only be scored half wrong. A named
    column is kept over an unlabeled ``*N`` one."""
    n_frames, n = pos.shape[:2]
    if n < 2 or n_frames == 0:
        return []
    from scipy.spatial import cKDTree

    seen = np.isfinite(pos[..., 0])
    probe = np.unique(np.linspace(0, n_frames - 1, COPY_PROBE_FRAMES).astype(int))
    candidates: set[tuple[int, int]] = set()
    for f in probe:
        idx = np.flatnonzero(seen[f])
        if idx.size > 1:
            # each point with its nearest few within the tolerance, not every close pair: k
            # points written at one place (a broken export) have k^2 / 2 pairs (3,333 markers
            # at one position took 28 s and 2.2 GB); a point's copies are its nearest ones
            k = min(idx.size, COPY_NEIGHBOURS + 1)
            xyz = pos[f, idx].astype(np.float64)
            dist, near = cKDTree(xyz).query(xyz, k=k, distance_upper_bound=COPY_TOL_MM)
            src, col = np.nonzero(np.isfinite(dist))
            dst = near[src, col]
            keep = src != dst
            a, b = idx[src[keep]], idx[dst[keep]]
            lo, hi = np.minimum(a, b).tolist(), np.maximum(a, b).tolist()
            candidates |= set(zip(lo, hi, strict=True))
    if not candidates:
        return []
    out: list[tuple[int, int]] = []
    dropped: set[int] = set()
    for a, b in sorted(candidates):
        if a in dropped or b in dropped:
            continue
        common = seen[:, a] & seen[:, b]
        if common.sum() < 2 or np.any(seen[:, a] != seen[:, b]):
            continue
        d = np.linalg.norm(pos[common, a].astype(np.float64) - pos[common, b], axis=1)
        if float(d.max()) > COPY_TOL_MM:
            continue
        copy, kept = (a, b) if is_ghost(labels[a]) and not is_ghost(labels[b]) else (b, a)
        out.append((copy, kept))
        dropped.add(copy)
    return out


#: names other systems give a trajectory nobody labeled (Vicon writes ``*N``): OptiTrack
#: Motive ``Unlabeled 1234`` / ``Unlabeled:1234`` (``_0001`` when told to rename them), other
#: exporters ``Unidentified 3``, ``Unnamed 12``, ``unknown``; with or without a subject prefix
_UNLABELED_NAME = re.compile(
    r"^(?:(?:unlabell?ed|unidentified|unnamed|unknown)(?:[\s_:#.-]*\d+)?|_\d+)$", re.IGNORECASE
)


def _names_no_marker(label: str) -> bool:
    """True for a vendor's name of an unlabeled trajectory (:data:`_UNLABELED_NAME`)."""
    return bool(_UNLABELED_NAME.match(label) or _UNLABELED_NAME.match(split_label(label)[1]))


def _no_empty_prefix(labels: list[str], notes: list[str]) -> list[str]:
    """``:CLAV`` -> ``CLAV``: an empty subject prefix is no prefix (kept, the name split into
    subject ``""`` and joined back without the colon: a marker nothing could find)."""
    empty = [x for x in labels if x.startswith(":")]
    if not empty:
        return labels
    said = ", ".join(repr(x) for x in empty[:3]) + (", ..." if len(empty) > 3 else "")
    notes.append(
        f"{plural(len(empty), 'label')} with an empty subject prefix ({said}) read without it"
    )
    return [x[1:].strip() if x.startswith(":") else x for x in labels]


def _unique_labels(labels: list[str], notes: list[str]) -> list[str]:
    """Empty labels, and the names other systems give unlabeled trajectories
    (:data:`_UNLABELED_NAME`), become unlabeled tracks ``*N``; a repeated name gets a ``~k``
    suffix, and a repeated ``*N`` a fresh ``*N`` (it stays an unlabeled track, never becomes
    a marker). Read as markers, a Motive take's hundreds of short unlabeled tracks would be
    scored and trained as markers nobody can label."""
    taken = set(labels)
    seen: dict[str, int] = {}
    out = []
    free = 0
    empty = sum(1 for x in labels if not x)
    if empty:
        notes.append(f"{plural(empty, 'empty label')} read as unlabeled tracks *N")
    renamed = [x for x in labels if x and _names_no_marker(x)]
    if renamed:
        said = ", ".join(repr(x) for x in renamed[:3]) + (", ..." if len(renamed) > 3 else "")
        notes.append(f"{len(renamed)} unlabeled trajectories ({said}) read as unlabeled tracks *N")
    for i, label in enumerate(labels):
        name = f"*{i}" if not label or _names_no_marker(label) else label
        if name in seen:
            seen[name] += 1
            if is_ghost(name):
                while f"*{free}" in taken or f"*{free}" in seen:
                    free += 1
                new = f"*{free}"
            else:
                new = f"{name}~{seen[name]}"
            notes.append(f"duplicate label {name!r} renamed {new!r}")
            name = new
        seen.setdefault(name, 0)
        out.append(name)
    return out


def _default_subject(cap: Capture, stem: str) -> Capture:
    named = [x for x in cap.labels if not is_ghost(x)]
    if named and all(split_label(x)[0] is None for x in named):
        subject = stem.replace(":", "_") or "subject"
        return replace(cap.with_subject(subject), default_subject=subject)
    return cap


def _y_up_to_z_up(cap: Capture) -> Capture:
    x, y, z = (cap.positions[..., i] for i in range(3))
    rotated = np.stack([x, -z, y], axis=-1)
    return cap.with_positions(rotated, notes=(*cap.notes, "rotated from Y up to Z up"))


#: with no UNITS parameter, coordinates all within this of the origin are metres: no person
#: fits within 50 mm, and a capture volume in metres is well inside 50 m
METRE_GUESS_MAX = 50.0


def _c3d_unit(point: dict, pos: np.ndarray, notes: list[str]) -> str:
    """A C3D's point units as read: its ``POINT:UNITS``, or without one the guess from its
    coordinates ``pos (F, M, 3)`` (:func:`_guess_units`: ``"m"``, or ``""`` for millimetres).
    The reader converts from them and a labeled copy is written back in them."""
    units = point.get("UNITS", {}).get("value", [])
    unit = str(units[0]) if len(units) else ""
    return unit if unit.strip() else _guess_units(pos, notes)


def _guess_units(pos: np.ndarray, notes: list[str]) -> str:
    """The units of a C3D without a UNITS parameter: ``"m"`` when every captured coordinate
    (not the (0,0,0) of a gap) lies within :data:`METRE_GUESS_MAX` of the origin (a take in
    metres read as millimetres is a body 2 mm tall that no labeler gate fits), else ``""``
    (millimetres, :func:`_unit_scale` notes it)."""
    seen = np.isfinite(pos).all(axis=2) & np.any(pos != 0.0, axis=2)
    if not seen.any():
        return ""
    reach = float(np.abs(pos[seen]).max())
    if reach >= METRE_GUESS_MAX:
        return ""
    notes.append(
        f"no UNITS parameter and every coordinate within {reach:.3g} of the origin: read as metres"
    )
    return "m"


#: coordinates said to be in metres (or cm) that reach this far from the origin, in those
#: units, are millimetres: no capture volume is 200 m across
MILLIMETRE_GUESS_MIN = 200.0


def _units_doubt(said: str, unit: str, pos: np.ndarray, path: Path, notes: list[str]) -> None:
    """Notes and logs units the coordinates ``pos`` (as stored) contradict: millimetres on a
    take whose every coordinate lies within :data:`METRE_GUESS_MAX` of the origin (a body a
    few millimetres tall), or metres/centimetres on one reaching past
    :data:`MILLIMETRE_GUESS_MIN` (a body a kilometre tall). ``said``: where the units came
    from (``UNITS``, ``Units``)."""
    if not unit.strip():
        return
    scale = _unit_scale(unit, path, [])
    seen = np.isfinite(pos).all(axis=2) & np.any(pos != 0.0, axis=2)
    reach = float(np.abs(pos[seen]).max()) if seen.any() else 0.0
    msg = None
    if scale == 1.0 and seen.any() and reach < METRE_GUESS_MAX:
        msg = (
            f"{said} says {unit.strip()} but every coordinate is within {METRE_GUESS_MAX:g} of "
            "the origin: the take may be in metres (nothing can be labeled on a body a few "
            "millimetres tall)"
        )
    elif scale > 1.0 and reach >= MILLIMETRE_GUESS_MIN:
        msg = (
            f"{said} says {unit.strip()} but coordinates reach {reach:.4g} from the origin "
            f"({reach * scale / 1e6:.3g} km): the take may be in millimetres (nothing can be "
            "labeled on a body a kilometre tall)"
        )
    if msg is not None:
        notes.append(msg)
        log.warning("%s: %s", path, msg)


def _unit_scale(units: str, source: Path, notes: list[str]) -> float:
    u = units.strip().lower()
    if not u:
        notes.append("no UNITS parameter: assumed mm")
        return 1.0
    if u not in _UNIT_SCALE:
        raise CaptureFormatError(f"{source}: unknown point units {units!r}")
    scale = _UNIT_SCALE[u]
    if scale != 1.0:
        notes.append(f"converted {u} to mm")
    return scale


# --------------------------------------------------------------------------------- C3D
def _c3d_labels(point: dict, n: int) -> list[str]:
    labels: list[str] = list(point.get("LABELS", {}).get("value", []))
    k = 2
    while len(labels) < n and f"LABELS{k}" in point:
        labels += list(point[f"LABELS{k}"]["value"])
        k += 1
    if len(labels) < n:
        labels += [f"*{i}" for i in range(len(labels), n)]
    for i, lab in enumerate(labels[:n]):
        try:
            lab.encode("utf-8")
        except UnicodeEncodeError:  # ezc3d hands undecodable bytes over as surrogates
            raw = lab.encode("utf-8", "surrogateescape")
            raise ValueError(f"POINT:LABELS entry {i + 1} ({raw!r}) is not valid UTF-8") from None
    return labels[:n]


def _c3d_header_rate(path: Path) -> float | None:
    """The 3D frame rate in a C3D file's header (bytes 20-23, a float in the byte order of
    its processor type: Intel or MIPS), or None when the file is too short or of another
    processor type (DEC floats). ezc3d divides by it before any check of ours can run: a NaN
    rate ends in its ``vector::_M_default_append``."""
    import struct

    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
            if len(head) < 24 or head[0] < 2:
                return None
            fh.seek(512 * (head[0] - 1))
            param = fh.read(4)
    except OSError:
        return None
    order = {84: "<", 86: ">"}.get(param[3] if len(param) == 4 else 0)
    if order is None:
        return None
    return float(struct.unpack(order + "f", head[20:24])[0])


#: parameter data types of C3D (bytes per element): char, byte, 16-bit int, float
_C3D_TYPES = {-1: 1, 1: 1, 2: 2, 4: 4}


def _c3d_structure_problem(path: Path) -> str | None:
    """What in a C3D's parameter section points outside the file or makes no sense as C3D (a
    pointer backwards, an unknown data type, data past the end), or None. ezc3d follows these
    values unchecked: a few damaged bytes there (a helper's 8 bytes of 0xFF at offset 520 of a
    real take) end the process with a segmentation fault, no error, no output. Only the
    structure ezc3d walks is checked (entry names, next-entry offsets, types, dimensions, data
    and description sizes); values are ezc3d's and ours to judge later."""
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size < 512:
                return None  # (too short for ezc3d to get that far: its own error)
            # mapped, not read: the walk touches the parameter blocks, never the frames
            with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                block = mm[0]
                if block < 2:
                    return f"its header points to parameter block {block} (the header is block 1)"
                start = 512 * (block - 1)
                if start + 4 > size:
                    return f"its parameters start at byte {start}, past its end ({size:,} bytes)"
                section = memoryview(mm)[start:]
                try:
                    return _c3d_walk(section, start)
                finally:
                    section.release()
    except OSError:
        return None  # (the reader's own error says it)


def _c3d_int_order(processor: int) -> str:
    """The ``struct`` byte order of a C3D's integers for its processor type byte (the fourth
    of its parameter section): big-endian for MIPS (86), else little-endian (Intel, DEC)."""
    return ">" if processor == 86 else "<"


def _c3d_walk(section: memoryview, start: int) -> str | None:
    """:func:`_c3d_structure_problem` over the parameter section ``section`` (to the end of the
    file), which starts at byte ``start`` of the file."""
    order = _c3d_int_order(section[3])
    pos = 4
    for _ in range(65536):  # (every step moves forward: this bounds a loop, not a file)
        if pos + 2 > len(section):
            return f"its parameter list runs past the end of the file (byte {start + pos:,})"
        n_chars = abs(struct.unpack_from("b", section, pos)[0])
        ident = struct.unpack_from("b", section, pos + 1)[0]
        if n_chars == 0:
            return None  # the end of the list
        at = start + pos
        link = pos + 2 + n_chars
        if ident == 0 or link + 2 > len(section):
            return f"a damaged parameter entry at byte {at:,}"
        offset = struct.unpack_from(order + "h", section, link)[0]
        nxt = link + offset
        if offset != 0 and (offset < 0 or nxt > len(section)):
            return (
                f"the parameter entry at byte {at:,} points to byte {start + nxt:,}, "
                f"{'backwards' if offset < 0 else 'past the end of the file'}"
            )
        body = link + 2
        if ident > 0:  # a parameter: type, dimensions, data
            if body + 2 > len(section):
                return f"a damaged parameter entry at byte {at:,}"
            kind, n_dims = struct.unpack_from("bB", section, body)
            if kind not in _C3D_TYPES or n_dims > 7:
                return (
                    f"the parameter entry at byte {at:,} has data type {kind} and {n_dims} "
                    "dimensions (C3D knows types -1, 1, 2, 4 and at most 7 dimensions)"
                )
            dims = bytes(section[body + 2 : body + 2 + n_dims])
            if len(dims) < n_dims:
                return f"a damaged parameter entry at byte {at:,}"
            body += 2 + n_dims + _C3D_TYPES[kind] * math.prod(dims)
        if body + 1 > len(section) or body + 1 + section[body] > len(section):
            return f"the parameter entry at byte {at:,} runs past the end of the file"
        if offset == 0:
            return None  # the last entry
        pos = nxt
    return "its parameter list does not end"


#: seconds the forked reader of :func:`_ezc3d_trouble` gets, plus this per MB of file (a real
#: 2 MB take reads in 0.07 s)
EZC3D_PROBE_S, EZC3D_PROBE_S_PER_MB = 10.0, 2.0


def _ezc3d_trouble(path: Path) -> str | None:
    """Why ezc3d cannot read ``path`` without taking the process down, or None: it is read in
    a forked child, which a signal may kill (a segmentation fault: ezc3d trusts every value of
    the parameter section, e.g. a ``POINT:USED`` stored as text) or which may not finish
    (:data:`EZC3D_PROBE_S`). The child costs one to two reads (25-90 ms; copy-on-write makes
    its read slower than the parent's), once per file content (:data:`_EZC3D_PROBED`).
    Skipped (None) where there is no ``fork`` or the process runs other threads (a fork
    copies none of them, and a lock one of them holds would stay held in the child): the
    structure check (:func:`_c3d_structure_problem`) alone stands there."""
    if not hasattr(os, "fork") or threading.active_count() > 1:
        return None
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key in _EZC3D_PROBED:  # (a file read again unchanged: the tests' fixtures)
        return _EZC3D_PROBED[key]
    if len(_EZC3D_PROBED) >= 256:
        _EZC3D_PROBED.clear()
    _EZC3D_PROBED[key] = why = _ezc3d_probe(path, st.st_size)
    return why


#: :func:`_ezc3d_trouble`'s answers by (path, size, modification time)
_EZC3D_PROBED: dict[tuple[str, int, int], str | None] = {}


def _ezc3d_probe(path: Path, size: int) -> str | None:
    """:func:`_ezc3d_trouble`'s forked read."""
    limit = EZC3D_PROBE_S + EZC3D_PROBE_S_PER_MB * size / 1e6
    pid = os.fork()
    if pid == 0:  # the child: read, and leave without running anything of the parent's
        code = 0
        try:
            import faulthandler

            import ezc3d

            faulthandler.disable()  # (pytest's or a user's dump of the expected crash)
            with open(os.devnull, "w") as null:
                os.dup2(null.fileno(), 1)
                os.dup2(null.fileno(), 2)
            ezc3d.c3d(str(path))
        except BaseException:
            code = 1  # (an exception is the parent's to report, from its own read)
        finally:
            os._exit(code)
    deadline = time.monotonic() + limit
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return f"the C3D reader (ezc3d) does not finish reading it in {limit:.0f} s"
        time.sleep(0.002)
    if os.WIFSIGNALED(status):
        name = signal.Signals(os.WTERMSIG(status)).name
        return f"the C3D reader (ezc3d) crashes on it ({name})"
    return None


def _read_c3d(path: Path) -> Capture:
    import ezc3d

    problem = _c3d_structure_problem(path)
    if problem is None:
        problem = _ezc3d_trouble(path)
    if problem is not None:
        raise CaptureFormatError(
            f"{path}: cannot be read as C3D (damaged or truncated?): {problem}"
        )
    try:
        c = ezc3d.c3d(str(path))
    except Exception as exc:  # ezc3d's own words, e.g. "Data::frame method is trying to ..."
        if "maximum number of frames is 0" in str(exc):
            raise CaptureFormatError(
                f"{path}: holds no frame data: the file ends before its first frame (truncated?)"
            ) from exc
        rate = _c3d_header_rate(path)
        if rate is not None and not 0 < rate < float("inf"):
            raise CaptureFormatError(
                f"{path}: its frame rate (C3D header) is {rate:g}: a capture needs a positive "
                "frame rate (Hz)"
            ) from exc
        raise CaptureFormatError(
            f"{path}: cannot be read as C3D (damaged or truncated?): {exc}"
        ) from exc
    point = c["parameters"]["POINT"]
    data = np.asarray(c["data"]["points"], dtype=np.float64)  # (4, M, F)
    n_markers = data.shape[1]
    notes: list[str] = []
    rate_values = point.get("RATE", {}).get("value", [])
    if len(rate_values) == 0:
        raise CaptureFormatError(f"{path}: no POINT:RATE")
    rate = float(rate_values[0])
    why = rate_problem(rate)
    if why is not None:  # (a C3D has no clock of its own to read the rate from instead)
        raise CaptureFormatError(f"{path}: frame rate (POINT:RATE) {why}")
    pos = np.transpose(data[:3], (2, 1, 0))  # (F, M, 3)
    unit = _c3d_unit(point, pos, notes)
    _units_doubt("UNITS", unit, pos, path, notes)
    pos = pos * _unit_scale(unit, path, notes)
    residuals = np.asarray(c["data"]["meta_points"]["residuals"], dtype=np.float64)  # (1, M, F)
    if residuals.size:
        neg = residuals[0].T < 0
        # the usual way to write "not captured" (coordinates NaN or 0): no news; coordinates
        # that a negative residual discards are (a label run's missing samples are the former)
        held = neg & np.isfinite(pos).all(axis=2) & (pos != 0).any(axis=2)
        pos[neg] = np.nan
        if held.any():
            notes.append(f"{int(held.sum())} samples with coordinates but a negative residual "
                         "(not captured) mapped to missing")  # fmt: skip
    counts = _c3d_frame_counts(path, point)
    if counts is not None and counts.past:
        msg = (
            f"holds data for about {counts.held:,} frames past its {C3D_MAX_FRAMES:,}-frame count "
            f"(C3D counts frames in 16 bits): only the first {pos.shape[0]:,} frames are read"
        )
        notes.append(msg)
        log.warning("%s: %s", path, msg)
    elif (
        counts is not None
        and counts.held < counts.declared
        # no frame at all is no cut: ezc3d read the file, so its POINT:FRAMES says 0 (ezc3d's
        # own writer puts frames 1 to 1 in the header then); a file cut before its first frame
        # is an ezc3d error, above
        and 0 < pos.shape[0] < counts.declared
    ):
        msg = f"truncated: {pos.shape[0]} of {counts.declared} frames (the file ends early)"
        notes.append(msg)
        log.warning("%s: %s", path, msg)
    labels = _c3d_labels(point, n_markers)
    keep = _c3d_markers(point, labels, notes)
    if keep is not None:
        pos, labels = pos[:, keep], [labels[i] for i in keep]
    return _finish(pos, labels, rate, path, notes)


#: POINT parameters that list, by label, points that are not physical markers: a processing
#: model's outputs (Vicon Plug-in Gait: joint angles, forces, moments, powers; scalars, ground
#: reactions) and its virtual markers (joint centres, markers reconstructed from a static
#: trial), which no camera sees. ``TYPE_GROUPS`` names more such lists (``USERMOS``: a model's
#: user outputs, EMG, ...). C3D stores all of them as points beside the markers.
_NON_MARKER_GROUPS = (
    "ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS", "MODELED_MARKERS",
    "USERMOS",
)  # fmt: skip


def _c3d_markers(point: dict, labels: list[str], notes: list[str]) -> list[int] | None:
    """Indices of the points that are markers, or None when all are: the points a processing
    model wrote (:data:`_NON_MARKER_GROUPS` and the groups ``TYPE_GROUPS`` names) are left
    out, with a note naming them. Without them a take labels like what cameras see; with them
    a jump take's ten model outputs (forces, EMG, angles near the origin) and eight virtual
    markers were scored as markers nobody could label (accuracy 0.74)."""
    groups = list(_NON_MARKER_GROUPS)
    type_groups = [str(x) for x in point.get("TYPE_GROUPS", {}).get("value", [])]
    groups += [g for g in type_groups[0::2] if g and g not in groups]
    listed: dict[str, str] = {}
    for g in groups:
        for x in point.get(g, {}).get("value", []):
            if isinstance(x, str) and x.strip():
                listed.setdefault(x.strip(), g)
    drop = [i for i, x in enumerate(labels) if x.strip() in listed]
    if not drop:
        return None
    by_group: dict[str, list[str]] = {}
    for i in drop:
        x = labels[i].strip()
        by_group.setdefault(listed[x], []).append(x)
    said = "; ".join(
        f"{g} {len(xs)} ({', '.join(xs[:4])}{', ...' if len(xs) > 4 else ''})"
        for g, xs in by_group.items()
    )
    notes.append(
        f"{plural(len(drop), 'point')} a processing model wrote left out (not markers): {said}"
    )
    dropped = set(drop)
    return [i for i in range(len(labels)) if i not in dropped]


class _C3DFrames(NamedTuple):
    """Frame counts of a C3D's raw header and size (:func:`_c3d_frame_counts`)."""

    declared: int  # the header's count
    held: int  # whole frames the file's data holds
    past: bool  # the 16-bit count is full (65,535) and the data goes on past it


def _c3d_frame_counts(path: Path, point: dict) -> _C3DFrames | None:
    """The frames a C3D's raw header declares and the whole frames its size holds: ezc3d
    silently reads the complete frames of a file that ends early (and rewrites its own header
    counts), and the first 65,535 of one written past the 16-bit count. ``None`` when the header
    cannot tell."""
    with open(path, "rb") as f:
        header = f.read(512)
        if len(header) < 512 or header[0] < 1:
            return None
        f.seek((header[0] - 1) * 512 + 3)
        proc = f.read(1)
    words = struct.unpack(_c3d_int_order(proc[0] if proc else 0) + "256H", header)
    n_points, n_analog, first, last, data_block = words[1], words[2], words[3], words[4], words[8]
    full = last == 0xFFFF and first == 1  # the 16-bit count is full: data may run past it
    if (last == 0xFFFF and not full) or last < first or data_block < 1:
        return None
    scale = point.get("SCALE", {}).get("value", [-1.0])
    item = 4 if len(scale) == 0 or float(scale[0]) < 0 else 2
    declared = last - first + 1
    frame_bytes = (4 * n_points + n_analog) * item
    data = path.stat().st_size - (data_block - 1) * 512
    if frame_bytes == 0:
        return _C3DFrames(declared, declared if data >= 0 else 0, False)
    # past the count: more than the last 512-byte block's padding beyond the declared frames
    past = full and data - declared * frame_bytes >= 512 + frame_bytes
    return _C3DFrames(declared, data // frame_bytes, past)


#: frames a C3D can hold: its header counts them in 16 bits (ezc3d writes more and reads back
#: 65,535, silently)
C3D_MAX_FRAMES = 65535


def _too_many_frames(n_frames: int) -> str:
    return (
        f"a C3D holds at most {C3D_MAX_FRAMES:,} frames (its header counts them in 16 bits), "
        f"not {n_frames:,}: write .npz or .trc, which hold any number"
    )


def c3d_frames_fit(path: str | Path, n_frames: int) -> None:
    """Refuses ``n_frames`` for a ``.c3d`` output (other suffixes take any count): raises
    :class:`CaptureError` naming the formats that hold them."""
    if Path(path).suffix.lower() == ".c3d" and n_frames > C3D_MAX_FRAMES:
        raise CaptureError(f"{path}: {_too_many_frames(n_frames)}")


def _c3d_fits(capture: Capture) -> None:
    """Refuses a capture a C3D cannot hold (no frame, or more than the 16-bit count)."""
    if capture.n_frames == 0:  # (ezc3d fails with a ZeroDivisionError)
        raise CaptureError("a C3D holds at least one frame; this capture has none")
    if capture.n_frames > C3D_MAX_FRAMES:
        raise CaptureError(_too_many_frames(capture.n_frames))


def _c3d_subjects(c, capture: Capture) -> None:
    """The Vicon ``SUBJECTS`` group of the ezc3d file ``c``: the labels' ``subject:marker``
    prefixes, for tools that list subjects from it rather than from the labels."""
    named = [s for s in capture.subjects if s]
    if named:
        c.add_parameter("SUBJECTS", "NAMES", named)
        c.add_parameter("SUBJECTS", "LABEL_PREFIXES", [f"{s}:" for s in named])
        c.add_parameter("SUBJECTS", "USED", [len(named)])
        c.add_parameter("SUBJECTS", "IS_STATIC", [0] * len(named))


def _c3d_points(
    capture: Capture, scale: float = 1.0, calculated: np.ndarray | None = None
) -> tuple[np.ndarray, dict]:
    """ezc3d's ``data["points"]`` and ``data["meta_points"]`` of ``capture`` (mm, divided by
    ``scale`` into the file's units): a missing sample (NaN) has the residual -1, as C3D marks
    one not captured; with ``calculated`` (``(F, M)`` bool), those samples have the residual 0
    (C3D's calculated point) and the other present ones 1 (without it, every present one 0)."""
    m, n = capture.n_markers, capture.n_frames
    pts = np.ones((4, m, n), dtype=np.float64)
    pts[:3] = np.transpose(capture.positions.astype(np.float64), (2, 1, 0)) / scale
    residuals = np.zeros((1, m, n), dtype=np.float64)
    if calculated is not None:
        residuals[0] = np.where(np.asarray(calculated, dtype=bool).T, 0.0, 1.0)
    residuals[0, np.isnan(pts[0])] = -1.0
    return pts, {"residuals": residuals, "camera_masks": np.zeros((7, m, n), dtype=bool)}


def _write_c3d(
    capture: Capture,
    path: Path,
    base: tuple[int, float] | None = None,
    calculated: np.ndarray | None = None,
) -> None:
    """``base``: the number (1-based) and time of the first frame (:func:`_time_base`)."""
    import ezc3d

    _c3d_fits(capture)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [capture.rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(capture.labels)
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = [""] * capture.n_markers
    c.add_parameter("POINT", "UNITS", ["mm"])
    _c3d_subjects(c, capture)
    c["data"]["points"], c["data"]["meta_points"] = _c3d_points(capture, 1.0, calculated)
    if base is not None:
        c["header"]["points"]["first_frame"] = base[0] - 1
    c.write(str(path))
    _check_c3d_written(path, 16 * capture.n_markers * capture.n_frames)


def _time_base(source: Path, start: int) -> tuple[int, float] | None:
    """The number (1-based) and time (s) of frame ``start`` of ``source``, as its file states
    them: a C3D's header first frame (its time: frames before it at its rate), a TRC's Frame#
    and Time cells of that row; None for an NPZ, a row without them or a file that cannot say
    (a capture's frames are then numbered from 1 at 0 s)."""
    try:
        if source.suffix.lower() == ".c3d":
            import ezc3d

            c = ezc3d.c3d(str(source))
            first = int(c["header"]["points"]["first_frame"]) + start
            rate = float(c["parameters"]["POINT"]["RATE"]["value"][0])
            return first + 1, first / rate
        if source.suffix.lower() == ".trc":
            lines = source.read_text(encoding="utf-8", errors="replace").splitlines()[5:]
            rows = [x for x in lines if x.strip()]
            cells = _trc_cells(rows[start])
            return int(float(cells[0])), float(cells[1])
    except (OSError, ValueError, IndexError, RuntimeError):
        return None
    return None


#: groups every C3D (or every file ezc3d writes) has: not worth naming as kept
_C3D_OWN_GROUPS = ("POINT", "ANALOG", "SUBJECTS", "EZC3D", "ROTATION")
#: POINT parameters of a source C3D that name its points: the written file's points are others
_POINT_OWN = ("LABELS", "DESCRIPTIONS", "USED", "FRAMES", "DATA_START", "TYPE_GROUPS")


def _write_c3d_like(
    capture: Capture,
    path: Path,
    source: Path,
    start: int,
    calculated: np.ndarray | None = None,
) -> list[str]:
    """Writes ``capture`` (frames ``start``... of the C3D ``source``, in its axes, in mm) as
    ``source`` with only its points replaced, so a labeled take overlays the take it came from:
    its analog channels (force plates, EMG) cut to the same frames, its events, its force
    platform and trial parameters, every other parameter group, its first frame (the time
    base: header and ``TRIAL:ACTUAL_START_FIELD``) and its point units (the points are
    converted back). The points a processing model wrote (left out when read) are not written:
    they were computed from the labels this file replaces. ``SUBJECTS`` names the capture's
    subjects. Returns what was kept, in words."""
    import ezc3d

    _c3d_fits(capture)
    c = ezc3d.c3d(str(source))
    params = c["parameters"]
    point = params["POINT"]
    data = c["data"]
    n_src = int(np.asarray(data["points"]).shape[2])
    n, m = capture.n_frames, capture.n_markers
    if start + n > n_src:
        raise CaptureError(f"{source}: frames {start}-{start + n} are past its {n_src} frames")
    # the units the reader converted from (a file without UNITS: as it guessed)
    xyz = np.transpose(np.asarray(data["points"], dtype=np.float64)[:3], (2, 1, 0))
    unit = _c3d_unit(point, xyz, []).strip() or "mm"
    scale = _unit_scale(unit, source, [])
    for key in [k for k in point if k in _POINT_OWN or k.startswith(("LABELS", "DESCRIPTIONS"))]:
        del point[key]
    for key in [k for k in point if k in _NON_MARKER_GROUPS]:
        del point[key]  # (their points are not written)
    c.add_parameter("POINT", "LABELS", list(capture.labels))
    c.add_parameter("POINT", "DESCRIPTIONS", [""] * m)
    c.add_parameter("POINT", "UNITS", [unit])
    if float(np.asarray(point.get("SCALE", {}).get("value", [-1.0]))[0]) > 0:
        point["SCALE"]["value"] = np.array([-1.0])  # the points are written as floats
    data["points"], data["meta_points"] = _c3d_points(capture, scale, calculated)
    kept: list[str] = []
    analogs = np.asarray(data["analogs"])
    per = analogs.shape[2] // n_src if n_src else 0
    if analogs.shape[1]:
        if not per or analogs.shape[2] != per * n_src:
            raise ValueError(f"{analogs.shape[2]} analog samples for {n_src} frames")
        data["analogs"] = np.ascontiguousarray(analogs[:, :, start * per : (start + n) * per])
        kept.append(f"{plural(analogs.shape[1], 'analog channel')}")
    else:
        data["analogs"] = np.zeros((1, 0, n * max(per, 1)))
    if "rotations" in data:
        rot = np.asarray(data["rotations"])
        per_r = rot.shape[3] // n_src if rot.ndim == 4 and n_src else 0
        if rot.ndim == 4 and rot.shape[2] and per_r:
            data["rotations"] = rot[..., start * per_r : (start + n) * per_r]
        else:
            del data["rotations"]
    first = int(c["header"]["points"]["first_frame"]) + start
    n_events, n_out = _c3d_events_within(params, first, n, _c3d_rate(params))
    if n_events or n_out:
        left = f" ({n_out} outside its frames left out)" if n_out else ""
        kept.append(f"{plural(n_events, 'event') if n_events else 'no event'}{left}")
    c["header"]["points"]["first_frame"] = first
    trial = params.get("TRIAL", {})
    for key, frame in (("ACTUAL_START_FIELD", first + 1), ("ACTUAL_END_FIELD", first + n)):
        if key in trial and len(trial[key]["value"]) == 2:  # 1-based, in two 16-bit words
            trial[key]["value"] = np.array([frame & 0xFFFF, frame >> 16])
    if first:
        kept.append(f"time base (first frame {first + 1})")
    if any(capture.subjects):  # (the source's names its own subjects, not the capture's)
        if "SUBJECTS" in params:
            del params["SUBJECTS"]
        _c3d_subjects(c, capture)
    other = sorted(g for g in params if g not in _C3D_OWN_GROUPS and g.strip())
    if other:
        kept.append(f"parameter groups {', '.join(other)}")
    c.write(str(path))
    width = 16 * m + 4 * int(np.asarray(data["analogs"]).shape[1]) * max(per, 1)
    _check_c3d_written(path, width * n)
    return kept


def _c3d_rate(params: dict) -> float:
    """A C3D's point rate from its parameters (0 when it has none)."""
    rate = params.get("POINT", {}).get("RATE", {}).get("value", [])
    return float(np.asarray(rate).ravel()[0]) if len(rate) else 0.0


#: every EVENT parameter with one entry per event (TIMES: one column per event)
_EVENT_LISTS = ("LABELS", "CONTEXTS", "DESCRIPTIONS", "ICON_IDS", "GENERIC_FLAGS")


def _c3d_events_within(params: dict, first: int, n: int, rate: float) -> tuple[int, int]:
    """Keeps in ``params["EVENT"]`` the events within the frames ``first`` (0-based, on the
    file's time base: frame k at k / rate s) to ``first + n - 1``, half a frame either side;
    returns how many were kept and how many left out. A group it cannot read is kept whole."""
    ev = params.get("EVENT", {})
    used = np.asarray(ev.get("USED", {}).get("value", [0])).ravel()
    total = int(used[0]) if used.size else 0
    times = np.asarray(ev.get("TIMES", {}).get("value", []), dtype=np.float64)
    if not total or rate <= 0 or times.ndim != 2 or times.shape != (2, total):
        return total, 0
    t = 60.0 * times[0] + times[1]
    half = 0.5 / rate
    keep = (t >= first / rate - half) & (t <= (first + n - 1) / rate + half)
    if keep.all():
        return total, 0
    idx = np.flatnonzero(keep)
    for key in _EVENT_LISTS:
        if key in ev:
            vals = ev[key]["value"]
            if len(vals) == total:
                ev[key]["value"] = (
                    [vals[i] for i in idx] if isinstance(vals, list) else np.asarray(vals)[idx]
                )
    ev["TIMES"]["value"] = times[:, idx]
    ev["USED"]["value"] = np.array([idx.size])
    return int(idx.size), total - int(idx.size)


def _check_c3d_written(path: Path, data_bytes: int) -> None:
    """ezc3d reports no I/O error (a full disk): the file must hold its header, its parameter
    section and every frame after the data start the header names, and that start must lie past
    the parameter section (a write cut short left it at block 1, and the file read back
    misaligned: 97 % of the samples wrong)."""
    size = path.stat().st_size if path.exists() else 0
    head = b""
    if size >= 512:
        with path.open("rb") as f:
            head = f.read(512)
            param_block = head[0]
            f.seek(max(param_block - 1, 0) * 512)
            param_head = f.read(4)
    if len(head) < 512 or param_block < 2 or len(param_head) < 4:
        raise CaptureError(f"C3D writer stored {size} bytes, no complete header (disk full?)")
    data_block = int.from_bytes(head[16:18], "little")
    first_free = param_block + param_head[2]  # the block after the parameter section
    need = (max(data_block, first_free) - 1) * 512 + data_bytes
    if data_block < first_free or size < need:
        raise CaptureError(
            f"C3D writer stored {size} bytes, at least {need} expected, data from block "
            f"{data_block} (after the parameters: {first_free}; disk full?)"
        )


# --------------------------------------------------------------------------------- TRC
#: the header's DataRate and the rate the Time column's spacing gives may differ by this
#: fraction (times are written rounded: to 1 ms, 50 frames at 240 Hz are 0.5 % off at worst)
TRC_RATE_TOL = 0.01


def _trc_sep(line: str) -> str:
    """The separator of one TRC line: tabs (the format's), else commas, else spaces."""
    return "\t" if "\t" in line else "," if "," in line else " "


def _trc_cells(line: str) -> list[str]:
    """One line's cells, stripped. Between tabs or commas a cell may be empty (a missing
    coordinate); between spaces none can be."""
    sep = _trc_sep(line)
    return line.split() if sep == " " else [x.strip() for x in line.split(sep)]


class _TRCRow(NamedTuple):
    """A data row as text: its line number, its cells, and whether they must all be there
    (cells between spaces: none can be empty, so a short row cannot say which are missing)."""

    lineno: int
    cells: list[str]
    exact: bool


def _trc_data_row(line: str, lineno: int, path: Path) -> _TRCRow:
    """One data row's cells, refusing a row whose cells cannot be told apart."""
    sep, cells = _trc_sep(line), _trc_cells(line)
    if sep == "," and any(len(x.split()) > 1 for x in cells):
        raise CaptureFormatError(
            f"{path}: line {lineno}: cells separated by both commas and spaces (decimal "
            "commas?): cannot tell the cells apart"
        )
    return _TRCRow(lineno, cells, exact=sep == " ")


def _trc_row(row: _TRCRow, n_markers: int, path: Path) -> list[float]:
    """One data row's coordinates (``3 * n_markers``, NaN where a cell is empty or absent)."""
    if row.exact and len(row.cells) != 2 + 3 * n_markers:
        raise CaptureFormatError(
            f"{path}: line {row.lineno}: {len(row.cells)} cells separated by spaces, "
            f"{2 + 3 * n_markers} expected (between spaces no cell can be empty: a missing "
            "sample needs tab-separated cells or NaN)"
        )
    values = row.cells[2 : 2 + 3 * n_markers]
    values += [""] * (3 * n_markers - len(values))
    try:
        return [float(v) if v else math.nan for v in values]
    except ValueError as exc:
        bad = next(v for v in values if v and not _is_number(v))
        raise CaptureFormatError(f"{path}: line {row.lineno}: {bad!r} is not a number") from exc


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _trc_names(line: str) -> list[str]:
    """The name row's marker names, one per marker. Between tabs or commas each name heads
    its marker's three columns (cells 2, 5, 8, ...): a blank name there is an unnamed marker
    (read as an unlabeled track), not a reason to shift the names after it onto the columns
    before theirs. Names packed into adjacent cells, or separated by spaces, are read in
    order."""
    cells = _trc_cells(line)[2:]
    named = [i for i, x in enumerate(cells) if x]
    if _trc_sep(line) == " " or any(i % 3 for i in named):
        return [cells[i] for i in named]
    return [cells[i] for i in range(0, named[-1] + 1, 3)] if named else []


def _trc_labels(
    names: list[str], n_data: int, *, declared: str, spaced: bool, path: Path, notes: list[str]
) -> list[str]:
    """The markers' labels: one per named column and one (empty: an unlabeled track) per
    unnamed column the data rows hold. The header's NumMarkers is only checked (noted)."""
    if spaced and len(names) != n_data:
        raise CaptureFormatError(
            f"{path}: the marker-name row names {len(names)} markers, the data rows hold "
            f"{n_data} (a name with a space in a file not separated by tabs?)"
        )
    if len(names) < n_data:
        notes.append(
            f"the marker-name row names {len(names)}, the data rows hold "
            f"{plural(n_data, 'marker')}: the unnamed ones read as unlabeled tracks"
        )
    elif len(names) > n_data:
        gone = ", ".join(names[n_data:][:3]) + (", ..." if len(names) - n_data > 3 else "")
        notes.append(
            f"the marker-name row names {len(names)}, the data rows hold "
            f"{plural(n_data, 'marker')}: {gone} missing in every frame"
        )
    labels = names + [""] * (n_data - len(names))
    if not labels:
        raise CaptureFormatError(f"{path}: the TRC names no marker and its rows hold none")
    if declared != str(len(labels)):
        msg = f"header NumMarkers {declared or '(none)'}, the file holds " + (
            f"{plural(len(labels), 'marker')}: all read"
        )
        notes.append(msg)
        log.warning("%s: %s", path, msg)
    return labels


def _trc_short_rows(
    rows: list[_TRCRow], expected: int, *, cut: bool, path: Path, notes: list[str]
) -> None:
    """Notes rows short of ``expected`` cells (their last samples are missing). ``cut``: the
    file ends inside the last row, perhaps inside a number: its last cell is dropped too."""
    if cut:
        last = rows[-1]
        msg = (
            f"truncated: line {last.lineno} ends mid-row ({len(last.cells)} of {expected} "
            "cells): its last cell and the samples after it read as missing"
        )
        notes.append(msg)
        log.warning("%s: %s", path, msg)
        rows[-1] = _TRCRow(last.lineno, last.cells[:-1], exact=False)  # the leading cells
    short = [row.lineno for row in rows[: len(rows) - cut] if len(row.cells) < expected]
    if short:
        notes.append(
            f"{plural(len(short), 'row')} short of the {expected} cells of its markers (line "
            f"{short[0]}{', ...' if len(short) > 1 else ''}): the samples past the row's end "
            "read as missing"
        )


def _trc_column(rows: list[_TRCRow], k: int) -> np.ndarray:
    """Column ``k`` of the rows as numbers (NaN where a cell is empty, absent or not one)."""
    cells = [row.cells[k] if len(row.cells) > k else "" for row in rows]
    return np.array([float(x) if x and _is_number(x) else math.nan for x in cells])


def _trc_time_rate(rows: list[_TRCRow]) -> tuple[float | None, str]:
    """The rate the Time column's spacing gives: frames between the first and the last timed
    row (by Frame# where it counts up, else rows) over their time apart, or ``(None, why)``.
    A rate within the rounding of the written times of a whole number of Hz is that number
    (240 Hz written to 1 ms gives 240.2 over 50 frames)."""
    frames, times = _trc_column(rows, 0), _trc_column(rows, 1)
    timed = np.flatnonzero(np.isfinite(times))
    if timed.size < 2:
        return None, "the Time column holds fewer than 2 times"
    t = times[timed]
    if np.any(np.diff(t) <= 0):
        return None, "Time does not increase row by row"
    f = frames[timed]
    steady = bool(np.all(np.isfinite(f) & (f == np.round(f)))) and bool(np.all(np.diff(f) > 0))
    span = f[-1] - f[0] if steady else timed[-1] - timed[0]
    said = float(span / (t[-1] - t[0]))
    cells = [rows[i].cells[1] for i in timed]
    if not any("e" in x.lower() for x in cells):
        # the times' resolution: their last written non-zero decimal (0.204000 is 1 ms)
        decimals = max(len(x.partition(".")[2].rstrip("0")) for x in cells)
        whole = round(said)
        if whole > 0 and abs(whole - said) <= said * 10.0**-decimals / (t[-1] - t[0]):
            said = float(whole)
    return said, ""


def _trc_rate(
    header: dict[str, str], rows: list[_TRCRow], path: Path, notes: list[str]
) -> tuple[float, str]:
    """The frame rate and where it came from: DataRate when it is a plausible rate
    (:func:`~labeler_service.capture.model.rate_problem`); else, with a note, the Time
    column's spacing, else CameraRate; neither: a one-line error naming both."""
    text = header.get("DataRate", "").strip()
    if _is_number(text) and rate_problem(float(text)) is None:
        return float(text), "header DataRate"
    plausible = f"{MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} Hz"
    if not text:
        said = "no DataRate in the header"
    elif _is_number(text):
        said = f"header DataRate {float(text):g} Hz is no frame rate ({plausible})"
    else:
        said = f"header DataRate {text!r} is not a number"
    timed, no_time = _trc_time_rate(rows) if rows else (None, "no data row holds a time")
    if timed is not None and rate_problem(timed) is None:
        msg = f"{said}: read at {timed:g} Hz, the Time column's spacing"
        notes.append(msg)
        log.warning("%s: %s", path, msg)
        return timed, "the Time column"
    if timed is not None:
        no_time = f"the Time column's spacing gives {timed:g} Hz"
    camera = header.get("CameraRate", "").strip()
    if _is_number(camera) and rate_problem(float(camera)) is None:
        msg = f"{said} and {no_time}: read at CameraRate {float(camera):g} Hz"
        notes.append(msg)
        log.warning("%s: %s", path, msg)
        return float(camera), "header CameraRate"
    raise CaptureFormatError(
        f"{path}: {said} and {no_time}: no frame rate to read it at (give DataRate, "
        f"{plausible}, or a Time column in seconds)"
    )


#: frame numbers that skip frames place the rows by them while the frames they span are at most
#: this many times the rows (a stray huge number must not allocate gigabytes)
TRC_SKIP_SPAN = 10


def _trc_clock(
    rows: list[_TRCRow], rate: float, origin: str, path: Path, notes: list[str]
) -> np.ndarray | None:
    """Checks the Frame# and Time columns against reading the rows in file order at ``rate``
    (from ``origin``): frame numbers out of order, repeated or skipped, and a Time column whose
    spacing gives a rate more than :data:`TRC_RATE_TOL` from it, are noted. Frame numbers that
    count up and skip some (frames the exporter left out: nothing seen) give each row's frame
    from the first, returned; the skipped frames are read empty. None: rows in file order."""
    frames = _trc_column(rows, 0)
    whole = np.isfinite(frames) & (frames == np.round(frames))
    if not whole.all():
        notes.append(f"{plural(int((~whole).sum()), 'row')} without a frame number in Frame#")
    known = frames[whole]
    step = np.diff(known)
    back, same = int((step < 0).sum()), int((step == 0).sum())
    if back:
        notes.append(f"Frame# out of order ({plural(back, 'step')} back): rows read in file order")
    if same:
        notes.append(f"Frame# repeated ({plural(same, 'row')}): rows read in file order")
    skipped = int(known.max() - known.min() + 1) - np.unique(known).size if known.size else 0
    placed = None
    if skipped:
        span = int(known.max() - known.min() + 1)
        if whole.all() and not (back or same) and span <= TRC_SKIP_SPAN * len(rows):
            placed = (known - known.min()).astype(np.int64)
            notes.append(
                f"Frame# numbers skip {plural(skipped, 'frame')}: read as frames with no marker "
                "seen (each row at its frame number)"
            )
        else:
            notes.append(
                f"Frame# numbers skip {plural(skipped, 'frame')}: rows read as consecutive frames"
            )
    if origin == "the Time column":
        return placed
    said, why = _trc_time_rate(rows)
    if said is None:
        if why.startswith("Time does not increase") and not (back or same):
            notes.append("Time does not increase row by row: its spacing is not checked")
        return placed
    if abs(said / rate - 1.0) > TRC_RATE_TOL:
        msg = (
            f"{origin} {rate:g} Hz, the Time column's spacing gives {said:.4g} Hz: read "
            f"at {rate:g} Hz"
        )
        notes.append(msg)
        log.warning("%s: %s", path, msg)
    return placed


def _read_trc(path: Path) -> Capture:
    """Reads a TRC: five header lines, then a row per frame (Frame#, Time, X Y Z per marker).

    A line is split at tabs, else at commas, else at spaces (tools write all three). The file's
    columns are trusted over the header's counts: every named column and every column with data
    is read, and a NumMarkers or NumFrames that disagrees with them is noted. Rows are read in
    file order at DataRate (missing or implausible: the Time column's rate, :func:`_trc_rate`),
    except that Frame# numbers counting up with frames skipped place each row at its frame
    (the skipped ones empty); Frame# numbers out of order, repeated or skipped, and a Time column
    spaced more than 1 % off DataRate are noted (:func:`_trc_clock`). A row short of cells (at
    tabs or commas) misses its last samples, with a note; a file that ends mid-row loses that
    row's last cell too (it may be part of a number)."""
    raw = path.read_text(encoding="utf-8", errors="replace")
    text = raw.splitlines()
    if not text or not text[0].startswith("PathFileType"):
        raise CaptureFormatError(f"{path}: not a TRC file (no PathFileType header)")
    if len(text) < 5:
        raise CaptureFormatError(
            f"{path}: the TRC ends inside its header ({len(text)} of 5 lines; truncated?)"
        )
    header = dict(zip(_trc_cells(text[1]), _trc_cells(text[2]), strict=False))
    notes: list[str] = []
    scale = _unit_scale(header.get("Units", "mm"), path, notes)
    names = _trc_names(text[3])
    rows = [
        _trc_data_row(line, lineno, path)
        for lineno, line in enumerate(text[5:], start=6)
        if line.strip()
    ]
    if not rows and header.get("NumFrames") == "0":  # an empty capture, as written
        rate, _ = _trc_rate(header, rows, path, notes)
        return _finish(np.empty((0, len(names), 3)), names, rate, path, notes)
    if not rows:
        raise CaptureFormatError(
            f"{path}: the TRC holds no frame data (truncated after its header?)"
        )
    width = max(_filled(row.cells) for row in rows)
    n_data = max(0, -(-(width - 2) // 3))  # the widest row's markers (the last may be partial)
    labels = _trc_labels(
        names,
        n_data,
        declared=header.get("NumMarkers", ""),
        spaced=_trc_sep(text[3]) == " ",
        path=path,
        notes=notes,
    )
    expected = 2 + 3 * len(labels)
    last = rows[-1].cells  # cut: the file ends mid-row (no line end, a cell short or a '-')
    cut = not raw.endswith(("\n", "\r")) and (
        len(last) < expected or bool(last[-1]) and not _is_number(last[-1])
    )
    if cut and len(rows) == 1:
        raise CaptureFormatError(
            f"{path}: the TRC ends inside its first data row (line {rows[0].lineno}; truncated?)"
        )
    _trc_short_rows(rows, expected, cut=cut, path=path, notes=notes)
    rate, origin = _trc_rate(header, rows, path, notes)
    placed = _trc_clock(rows, rate, origin, path, notes)
    declared = header.get("NumFrames", "")
    if declared and declared != str(len(rows)):
        notes.append(f"header NumFrames {declared}, {plural(len(rows), 'data row')} read")
    pos = np.array([_trc_row(row, len(labels), path) for row in rows], dtype=np.float64)
    pos = pos.reshape(len(rows), len(labels), 3)
    _units_doubt("Units", header.get("Units", "mm"), pos, path, notes)
    pos = pos * scale
    if placed is not None:  # (frames the Frame# numbers skip: nothing seen)
        full = np.full((int(placed[-1]) + 1, len(labels), 3), np.nan)
        full[placed] = pos
        pos = full
    return _finish(pos, labels, rate, path, notes)


def _filled(cells: list[str]) -> int:
    """The number of cells up to the last non-empty one (trailing tabs hold nothing)."""
    return next((i + 1 for i in range(len(cells) - 1, -1, -1) if cells[i]), 0)


def _write_trc(
    capture: Capture, path: Path, name: str | None = None, base: tuple[int, float] | None = None
) -> None:
    """``name``: the file name the header states (the target's, not the temporary file's);
    ``base``: the number and time of the first frame (default 1 and 0 s)."""
    # a TRC is tab-separated lines: a name with a tab or a line break shifts every column
    # after it (the header's NumMarkers then disagrees with the file), silently
    bad = [x for x in capture.labels if any(c < " " or c == "\x7f" for c in x)]
    if bad:
        raise CaptureError(
            f"marker name {bad[0]!r} holds a tab, a line break or another control character, "
            "which a TRC cannot hold (write .c3d or .npz, or rename the marker)"
        )
    f, m = capture.n_frames, capture.n_markers
    first, t0 = base if base is not None else (1, 0.0)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{name or path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
        "OrigDataStartFrame\tOrigNumFrames",
        f"{capture.rate:g}\t{capture.rate:g}\t{f}\t{m}\tmm\t{capture.rate:g}\t{first}\t{f}",
        "Frame#\tTime\t" + "\t".join(f"{x}\t\t" for x in capture.labels).rstrip("\t"),
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(m)),
        "",
    ]
    pos = capture.positions
    for i in range(f):
        cells = ["" if np.isnan(v) else repr(float(v)) for v in pos[i].reshape(-1)]
        lines.append(f"{first + i}\t{t0 + i / capture.rate:.6f}\t" + "\t".join(cells))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


# --------------------------------------------------------------------------------- NPZ
#: Largest declared (uncompressed) NPZ content read: above a 10-minute 10-person take at 240 Hz
#: (144,000 frames x 600 markers x 3 x 4 bytes = 1.04 GB). ``MOCAP_MAX_NPZ_BYTES`` overrides it.
MAX_NPZ_BYTES = 1_300_000_000
#: Largest compression ratio of an NPZ member larger than :data:`NPZ_RATIO_MIN_BYTES`
#: (real marker data compresses 1-3x; a decompression bomb 1000x).
MAX_NPZ_RATIO = 100.0
NPZ_RATIO_MIN_BYTES = 1 << 20


def max_npz_bytes() -> int:
    """The largest capture content read (bytes): :data:`MAX_NPZ_BYTES`, or
    ``MOCAP_MAX_NPZ_BYTES``."""
    raw = os.environ.get("MOCAP_MAX_NPZ_BYTES")
    if raw is None:
        return MAX_NPZ_BYTES
    try:
        return int(raw)
    except ValueError:
        raise CaptureError(f"MOCAP_MAX_NPZ_BYTES={raw!r} is not an integer") from None


#: What reading a damaged or cut zip member raises (zip's "Bad CRC-32", zlib's "invalid block
#: type", a local header past the end)
_ZIP_DAMAGE = (OSError, EOFError, zipfile.BadZipFile, zlib.error)

#: Most bytes numpy's header takes in an NPZ member of a capture (it writes 128 for each of
#: ``positions``, ``labels`` and ``rate``; 256 leaves room).
NPZ_HEADER_BYTES = 256


def npz_bytes(n_frames: int, labels: Sequence[str]) -> int:
    """The declared (uncompressed) size :func:`check_npz` counts for the NPZ :func:`_write_npz`
    writes of ``n_frames`` frames of ``labels``: float32 positions, the labels as a fixed-width
    unicode array (4 bytes a character of the longest), the float64 rate, and their headers."""
    width = max((len(x) for x in labels), default=1)
    markers = len(labels)
    return n_frames * markers * 3 * 4 + markers * 4 * max(width, 1) + 8 + 3 * NPZ_HEADER_BYTES


#: the members of a capture NPZ the reader loads
_NPZ_READ = ("positions.npy", "labels.npy", "rate.npy")


def check_npz(path: Path, max_bytes: int | None = None) -> None:
    """Refuses, before decompressing anything, an NPZ whose declared size exceeds
    ``max_bytes`` (default :data:`MAX_NPZ_BYTES`), whose members compress more than
    :data:`MAX_NPZ_RATIO`, or whose array headers declare more data than the member holds."""
    cap = max_npz_bytes() if max_bytes is None else max_bytes
    try:
        zf = zipfile.ZipFile(path)
    except zipfile.BadZipFile as exc:
        raise CaptureFormatError(
            f"{path}: not an NPZ (zip) archive (damaged or truncated?): {exc}"
        ) from exc
    except OSError as exc:  # (permission denied, a folder: not a damaged archive)
        raise CaptureFormatError(f"{path}: cannot be read: {exc}") from exc
    with zf:
        infos = zf.infolist()
        total = sum(i.file_size for i in infos)
        if total > cap:
            raise CaptureFormatError(
                f"{path}: NPZ declares {total} bytes uncompressed, more than the cap {cap} "
                "(MOCAP_MAX_NPZ_BYTES)"
            )
        for info in infos:
            if info.file_size > NPZ_RATIO_MIN_BYTES:
                ratio = info.file_size / max(info.compress_size, 1)
                if ratio > MAX_NPZ_RATIO:
                    raise CaptureFormatError(
                        f"{path}: NPZ member {info.filename} compresses {ratio:.0f}x "
                        f"(more than {MAX_NPZ_RATIO:g}x): refused as a decompression bomb"
                    )
            if not info.filename.endswith(".npy"):
                continue
            try:
                with zf.open(info) as f:
                    version = np.lib.format.read_magic(f)
                    if version == (1, 0):
                        shape, _, dtype = np.lib.format.read_array_header_1_0(f)
                    else:
                        shape, _, dtype = np.lib.format.read_array_header_2_0(f)
            except ValueError as exc:
                raise CaptureFormatError(
                    f"{path}: NPZ member {info.filename} has no valid array header: {exc}"
                ) from exc
            except _ZIP_DAMAGE as exc:  # a small member is read whole: its CRC is checked here
                raise CaptureFormatError(
                    f"{path}: NPZ member {info.filename} cannot be read (damaged or truncated?): "
                    f"{exc}"
                ) from exc
            if dtype.hasobject and info.filename in _NPZ_READ:
                # numpy: "Object arrays cannot be loaded when allow_pickle=False"; a member the
                # reader does not read (a producer's own metadata) is left alone
                raise CaptureFormatError(
                    f"{path}: NPZ member {info.filename} holds Python objects (a pickle), which "
                    "are not read: a capture NPZ holds numbers and strings"
                )
            nbytes = math.prod(shape) * dtype.itemsize
            if nbytes > info.file_size:
                raise CaptureFormatError(
                    f"{path}: NPZ member {info.filename} declares shape {shape} "
                    f"({nbytes} bytes) but holds {info.file_size}"
                )


def _read_npz(path: Path) -> Capture:
    check_npz(path)
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in ("positions", "labels", "rate") if k not in z.files]
        if missing:  # (numpy's KeyError text read "lacks 'positions is not a file in ...'")
            raise CaptureFormatError(
                f"{path}: not a capture NPZ: it lacks {', '.join(missing)} "
                f"(it holds {', '.join(z.files) or 'nothing'})"
            )
        positions = _npz_member(z, "positions", path)
        if positions.ndim != 3 or positions.shape[2] != 3:  # (numpy: "axis 2 is out of bounds")
            raise CaptureFormatError(
                f"{path}: positions must be (frames, markers, 3), got shape {positions.shape}"
            )
        if positions.dtype.kind not in "iuf":  # text, complex numbers, booleans
            raise CaptureFormatError(
                f"{path}: positions must be real numbers, got dtype {positions.dtype}"
            )
        raw = _npz_member(z, "labels", path)
        if raw.ndim != 1:  # a (M, 1) column read as "['Derrick:C7']"
            raise CaptureFormatError(f"{path}: labels must be a 1-D array, got shape {raw.shape}")
        # bytes (an ``S`` array) read as "b'Derrick:C7'"
        labels = [x.decode("utf-8", "replace") if isinstance(x, bytes) else str(x) for x in raw]
        rate = _npz_member(z, "rate", path)
        if rate.size != 1 or rate.dtype.kind not in "iuf":
            said = repr(rate.reshape(-1)[0].item()) if rate.size == 1 else f"shape {rate.shape}"
            raise CaptureFormatError(f"{path}: rate must be one number (Hz), got {said}")
    return _finish(positions, labels, float(rate.reshape(-1)[0]), path, [])


def _npz_member(z: np.lib.npyio.NpzFile, key: str, path: Path) -> np.ndarray:
    """``z[key]``; a member cut short or damaged (numpy's "EOF: reading array data", zip's
    "Bad CRC-32", zlib's "invalid block type") is a :class:`CaptureFormatError` saying so."""
    try:
        return z[key]
    except (ValueError, *_ZIP_DAMAGE) as exc:
        raise CaptureFormatError(
            f"{path}: NPZ member {key}.npy cannot be read (damaged or truncated?): {exc}"
        ) from exc


def _write_npz(capture: Capture, path: Path) -> None:
    np.savez_compressed(
        path,
        positions=capture.positions,
        labels=np.asarray(capture.labels, dtype=str),
        rate=np.float64(capture.rate),
    )
