"""The ``Capture`` value: labeled (or not) marker trajectories in millimetres, NaN = missing."""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from labeler_service.errors import CaptureFormatError

_GHOST = re.compile(r"^\*\d+$")
#: largest coordinate a point may have, mm (10 km): beyond it a sample is garbage (no capture
#: volume is that large), and near the float32 limit (3.4e38) the labeler's arithmetic overflows.
#: Readers map such samples to missing; the service refuses such frames (``out_of_range``).
MAX_COORD_MM = 1.0e7
#: Frame rates (Hz) a capture may be read, composed or streamed at: optical systems record at
#: tens to hundreds of Hz and reach a few kHz in windowed high-speed modes; 10 kHz is past all
#: of them. Below 1 Hz a marker moves metres between frames (nothing to label); a rate of 0,
#: NaN or 1e7 is a header or a flag typed wrong. One check for every place a rate comes in
#: (:func:`rate_problem`): the CLI's ``--rate`` options, the readers, the service's settings.
MIN_RATE_HZ = 1.0
MAX_RATE_HZ = 10_000.0


def rate_problem(rate: object, low: float = MIN_RATE_HZ, high: float = MAX_RATE_HZ) -> str | None:
    """Why ``rate`` is no plausible frame rate, a phrase to follow the rate's name
    (``f"--rate {why}"`` reads ``--rate is 0 Hz: expected 1 to 10000 Hz``), or None when it is
    one. ``low``, ``high``: a narrower range of a caller's own (a simulator's filter)."""
    if isinstance(rate, bool) or not isinstance(rate, int | float | np.integer | np.floating):
        return f"is {rate!r}: expected {low:g} to {high:g} Hz"
    if low <= float(rate) <= high:  # (NaN compares False)
        return None
    return f"is {float(rate):g} Hz: expected {low:g} to {high:g} Hz"


def split_label(label: str) -> tuple[str | None, str]:
    """``"subj:LASI"`` -> ``("subj", "LASI")``; ``"LASI"`` -> ``(None, "LASI")``.

    The split is at the first colon, Vicon style.
    """
    subject, sep, marker = label.partition(":")
    if not sep:
        return None, label
    return subject, marker


def join_label(subject: str | None, marker: str) -> str:
    """The inverse of :func:`split_label`: ``("subj", "LASI")`` -> ``"subj:LASI"``; a subject
    ``""`` or ``None`` (labels that carried no prefix, :func:`subject_groups`) -> ``"LASI"``."""
    return f"{subject}:{marker}" if subject else marker


def is_ghost(label: str) -> bool:
    """True for an unlabeled track (``*N``, with or without a subject prefix)."""
    return bool(_GHOST.match(split_label(label)[1]))


def subject_groups(labels: Iterable[str], *, skip_ghosts: bool = False) -> dict[str, list[int]]:
    """Subject name -> indices of its labels, subjects in order of first appearance.

    The one grouping of ``subject:marker`` names by subject (capture columns, the labeler's
    marker list, the model message). A label without a prefix belongs to subject ``""``;
    ``skip_ghosts`` leaves unlabeled tracks (``*N``) out.
    """
    out: dict[str, list[int]] = {}
    for i, label in enumerate(labels):
        if skip_ghosts and is_ghost(label):
            continue
        out.setdefault(split_label(label)[0] or "", []).append(i)
    return out


@dataclass(frozen=True, eq=False)
class Capture:
    """Marker trajectories of one take.

    ``positions`` is ``(frames, markers, 3)`` float32 in millimetres, right-handed, Z up, NaN
    where a marker is missing. ``labels`` are ``subject:marker`` (or ``*N`` for unlabeled
    tracks). ``notes`` records what the reader changed on load (unit conversion, axis rotation,
    zero samples mapped to NaN) so summaries can say so.
    """

    positions: np.ndarray
    labels: tuple[str, ...]
    rate: float
    source: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)
    #: the subject a reader gave labels that named none (the file's stem), else None: a tool
    #: writing them back writes the bare names its input had
    default_subject: str | None = None

    def __post_init__(self) -> None:
        pos = np.asarray(self.positions)
        if pos.ndim != 3 or pos.shape[2] != 3:
            raise CaptureFormatError(
                f"{self.source or 'capture'}: positions must be (frames, markers, 3), "
                f"got shape {pos.shape}"
            )
        if pos.dtype != np.float32 or not pos.flags.c_contiguous:
            pos = np.ascontiguousarray(pos, dtype=np.float32)
        object.__setattr__(self, "positions", pos)
        labels = tuple(str(x) for x in self.labels)
        if len(labels) != pos.shape[1]:
            raise CaptureFormatError(
                f"{self.source or 'capture'}: {len(labels)} labels for {pos.shape[1]} markers"
            )
        object.__setattr__(self, "labels", labels)
        if not (np.isfinite(self.rate) and self.rate > 0):
            raise CaptureFormatError(f"{self.source or 'capture'}: invalid frame rate {self.rate}")
        object.__setattr__(self, "rate", float(self.rate))
        object.__setattr__(self, "notes", tuple(self.notes))

    # ----------------------------------------------------------------- shape and naming
    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.positions.shape[1])

    @property
    def duration(self) -> float:
        return self.n_frames / self.rate

    @property
    def times(self) -> np.ndarray:
        """Capture time of every frame in seconds (first frame at 0)."""
        return np.arange(self.n_frames, dtype=np.float64) / self.rate

    @property
    def ghost_mask(self) -> np.ndarray:
        """``(markers,)`` bool: columns that are unlabeled tracks (``*N``)."""
        return np.array([is_ghost(x) for x in self.labels], dtype=bool)

    @property
    def subjects(self) -> tuple[str, ...]:
        """Subject names in order of first appearance (ghost columns excluded)."""
        return tuple(subject_groups(self.labels, skip_ghosts=True))

    def subject_columns(self, subject: str) -> np.ndarray:
        """Column indices of one subject's (non-ghost) markers."""
        cols = subject_groups(self.labels, skip_ghosts=True).get(subject, [])
        return np.asarray(cols, dtype=np.intp)

    # --------------------------------------------------------------------- statistics
    @property
    def visible(self) -> np.ndarray:
        """``(frames, markers)`` bool: the sample is present."""
        return ~np.isnan(self.positions).any(axis=2)

    @property
    def missing_fraction(self) -> float:
        """Missing samples of the labeled markers (ghost ``*N`` columns are not counted,
        unless every column is one, as in a raw unlabeled capture)."""
        vis = self.visible
        named = ~self.ghost_mask
        if named.any():
            vis = vis[:, named]
        if vis.size == 0:
            return 0.0
        return float(1.0 - vis.mean())

    def empty_columns(self) -> np.ndarray:
        """Indices of markers that are never visible."""
        return np.flatnonzero(~self.visible.any(axis=0))

    def gaps(self) -> list[tuple[int, int, int]]:
        """Runs of missing samples strictly inside each marker's visible span.

        Returns ``(marker, first_missing_frame, length)``; leading/trailing absence and
        never-visible markers are not gaps.
        """
        out: list[tuple[int, int, int]] = []
        vis = self.visible
        for m in range(self.n_markers):
            idx = np.flatnonzero(vis[:, m])
            if idx.size < 2:
                continue
            steps = np.diff(idx)
            for k in np.flatnonzero(steps > 1):
                out.append((m, int(idx[k] + 1), int(steps[k] - 1)))
        return out

    # ----------------------------------------------------------------- transformations
    def with_positions(self, positions: np.ndarray, **changes: object) -> Capture:
        return replace(self, positions=positions, **changes)  # type: ignore[arg-type]

    def select(self, columns: Sequence[int] | np.ndarray) -> Capture:
        cols = np.asarray(columns, dtype=np.intp)
        return replace(
            self,
            positions=self.positions[:, cols],
            labels=tuple(self.labels[i] for i in cols),
        )

    def without_absent_subjects(self) -> tuple[Capture, tuple[str, ...]]:
        """``(capture, names)``: the capture without the subjects none of whose markers is
        ever visible (a session's subject list holds someone not in this take), and their
        names. Nothing can be trained on or scored for such a subject, and a labeled start
        stopped at it ("no marker is seen in 3 or more of its labeled training frames")."""
        groups = subject_groups(self.labels, skip_ghosts=True)
        seen = np.asarray(self.visible.any(axis=0))
        absent = tuple(s for s, cols in groups.items() if s and not seen[cols].any())
        if not absent or len(absent) == len(groups):  # all absent: the callers' errors say so
            return self, ()
        keep = [i for i, x in enumerate(self.labels) if split_label(x)[0] not in absent]
        return self.select(keep), absent

    def frames(self, start: int = 0, stop: int | None = None, step: int = 1) -> Capture:
        """A frame range (``step`` > 1 decimates and divides the rate)."""
        if step < 1:
            raise ValueError(f"step must be >= 1, got {step}")
        return replace(
            self,
            positions=self.positions[start:stop:step],
            rate=self.rate / step,
        )

    def without_empty(self) -> Capture:
        """Drops markers that are never visible (e.g. CMU's empty duplicate ``RBAC-1``)."""
        empty = set(self.empty_columns().tolist())
        if not empty:
            return self
        keep = [i for i in range(self.n_markers) if i not in empty]
        dropped = ", ".join(self.labels[i] for i in sorted(empty))
        return replace(
            self.select(keep), notes=(*self.notes, f"dropped never-visible markers: {dropped}")
        )

    def with_subject(self, subject: str) -> Capture:
        """Every non-ghost label re-prefixed with ``subject:`` (any old prefix is replaced)."""
        if not subject or ":" in subject:
            raise ValueError(f"invalid subject name {subject!r}")
        labels = tuple(
            label if is_ghost(label) else f"{subject}:{split_label(label)[1]}"
            for label in self.labels
        )
        return replace(self, labels=labels)

    @staticmethod
    def concat_markers(captures: Iterable[Capture], source: str = "") -> Capture:
        """Side-by-side join of captures with the same rate and frame count."""
        caps = list(captures)
        if not caps:
            raise ValueError("nothing to join")
        rate, n = caps[0].rate, caps[0].n_frames
        for c in caps[1:]:
            if abs(c.rate - rate) > 1e-6 or c.n_frames != n:
                raise CaptureFormatError(
                    f"cannot join {c.source}: {c.n_frames} frames at {c.rate} Hz, "
                    f"expected {n} at {rate} Hz"
                )
        labels = tuple(label for c in caps for label in c.labels)
        if len(set(labels)) != len(labels):
            dup = sorted({x for x in labels if labels.count(x) > 1})
            raise CaptureFormatError(f"duplicate labels after join: {', '.join(dup[:5])}")
        return Capture(
            positions=np.concatenate([c.positions for c in caps], axis=1),
            labels=labels,
            rate=rate,
            source=source,
            notes=tuple(n for c in caps for n in c.notes),
        )


#: Twin markers named ``L*``/``R*``: enough of them and no other naming convention is tried.
MIN_CLASSIC_PAIRS = 3


_PREFIX = re.compile(r"^(left|right|l|r)([ _.\-]?)(.+)$", re.IGNORECASE)
_SUFFIX = re.compile(r"^(.+?)([ _.\-]?)(left|right|l|r)$", re.IGNORECASE)


def _side_key(token: str) -> tuple[str, str]:
    """``"L"`` -> ``("l", "upper")``: which side, and the spelling (so ``L`` pairs with ``R``,
    ``l`` with ``r``, ``Left`` with ``Right``)."""
    low = token.lower()
    side = low[0]
    form = "word" if len(low) > 1 else ("upper" if token.isupper() else "lower")
    return side, form


def side_pairs(names: Sequence[str]) -> list[tuple[int, int]]:
    """``(left, right)`` index pairs of twin markers.

    The classic convention first: ``L*`` / ``R*`` (``LSHO``/``RSHO``). When it finds fewer
    than ``MIN_CLASSIC_PAIRS`` pairs (a BTS take has ``LATT``/``RATT`` beside ``l knee``), every
    convention: a side token (``L``, ``R``, ``l``, ``r``, ``Left``, ``Right``) as
    prefix or suffix, with or without a separator (space, ``_``, ``.``, ``-``): ``L_IAS``,
    ``Shoulder_L``, ``R.Knee``, ``r knee``, ``ASISr``. Two names pair when everything but the
    side agrees (stem, separator, position and spelling of the side).
    """
    index = {n: i for i, n in enumerate(names)}
    classic = [
        (i, index["R" + n[1:]])
        for i, n in enumerate(names)
        if len(n) > 1 and n[0] == "L" and "R" + n[1:] in index
    ]
    if len(classic) >= MIN_CLASSIC_PAIRS:
        return classic
    keyed: dict[tuple[str, ...], dict[str, int]] = {}
    for i, n in enumerate(names):
        for kind, pattern in (("pre", _PREFIX), ("suf", _SUFFIX)):
            m = pattern.match(n)
            if m is None:
                continue
            token, sep, stem = (m[1], m[2], m[3]) if kind == "pre" else (m[3], m[2], m[1])
            side, form = _side_key(token)
            keyed.setdefault((kind, sep, stem, form), {}).setdefault(side, i)
    pairs = {(d["l"], d["r"]) for d in keyed.values() if "l" in d and "r" in d}
    return sorted(pairs)
