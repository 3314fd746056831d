"""Subject templates: the one versioned schema shared by the service and the offline trainer.

A template (seed 003, Sec. 3.1) holds, per subject:

- ``markers``: marker names (without the ``subject:`` prefix), in model order;
- ``D`` and ``A``: mean and standard deviation of every marker-pair distance (Eq. 1-2), mm,
  ``null`` where a pair was never seen together;
- ``bodies``: rigid bodies, each a list of 3-8 marker indices into ``markers``;
- ``shapes``: per body the reference shape, marker coordinates (mm) in a body frame (origin at
  the centroid, axes = principal axes), used by the Kabsch recovery and by
  :meth:`~labeler_service.labeling.labeler.Labeler.from_model` registration;
- ``motion_noise``: per marker the process noise of the constant-velocity Kalman filter
  (Eq. 3), as the variance of acceleration per axis, (mm/s^2)^2.

``save_model``/``load_model`` write and read JSON; every inconsistency raises
:class:`~labeler_service.errors.ModelError` with a message naming the subject and field.
"""

from __future__ import annotations

import errno
import json
import math
import os
import unicodedata
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from labeler_service.capture.io import os_reason, replace_file
from labeler_service.capture.model import MAX_RATE_HZ, MIN_RATE_HZ, is_ghost, join_label
from labeler_service.errors import ModelError

SCHEMA_VERSION: Literal[1] = 1

#: Ranges a human body allows (issue 12): a marker-pair distance ``D`` (off the diagonal) in mm,
#: and the motion noise ``q`` in (mm/s^2)^2 within 6 orders of magnitude of a typical trained
#: value (real takes at 60-250 Hz train 5e4 to 1.4e11).
PAIR_DISTANCE_MM = (1.0, 3000.0)
MOTION_NOISE_TYPICAL = 1.0e7
MOTION_NOISE_RANGE = (MOTION_NOISE_TYPICAL * 1e-6, MOTION_NOISE_TYPICAL * 1e6)
#: a subject whose most rigid bodies' links vary by more than this (the median of their
#: trained deviations ``A``, mm) was trained on labels that do not stay on their markers: the
#: real takes' models give 0.1-4.6 mm, labels shuffled every frame ~230 mm; its bodies would
#: match any points (a boot attempt with such a model ran for minutes)
LABELS_OFF_MM = 50.0


def body_link_spread(A: Any, bodies: Sequence[Sequence[int]]) -> float:
    """Median trained deviation ``A`` (mm; a matrix, ``None``/NaN = unknown) over the links
    inside ``bodies`` (0 without one)."""
    a = np.array([[np.nan if v is None else v for v in row] for row in A], dtype=float)
    vals = [a[i, j] for b in bodies for k, i in enumerate(b) for j in b[k + 1 :]]
    vals = [v for v in vals if np.isfinite(v)]
    return float(np.median(vals)) if vals else 0.0


#: Most chirality quadruples per subject (``train structure`` writes at most 64).
MAX_CHIRALITY = 1024
#: A chirality quadruple inside one body whose reference shape is at least this thick (cube
#: root of the signed volume, mm) must be positive there.
CHIRALITY_SHAPE_MM = 5.0
#: Largest model file read (a model of 20 subjects x 60 markers is about 3 MB).
MAX_MODEL_BYTES = 64 * 1024 * 1024


def reversed_in_shape(quad: list[int], body: list[int], shape: np.ndarray) -> bool:
    """Whether chirality quadruple ``quad`` (marker indices) lies inside ``body`` and its
    signed volume in the body's reference ``shape`` (rows in ``body``'s order) is negative, at
    least ``CHIRALITY_SHAPE_MM`` thick: the shape and the quadruple disagree on handedness."""
    row = {i: k for k, i in enumerate(body)}
    if not all(i in row for i in quad):
        return False
    p = np.asarray(shape, dtype=float)[[row[i] for i in quad]]
    det = float(np.linalg.det(p[1:] - p[0]))
    return det < 0 and float(np.cbrt(-det)) >= CHIRALITY_SHAPE_MM


class SubjectTemplate(BaseModel):
    """Structure and motion model of one subject (seed 003 Sec. 3.1)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    markers: list[str] = Field(min_length=1)
    D: list[list[float | None]]
    A: list[list[float | None]]
    bodies: list[list[int]] = Field(min_length=1)
    shapes: list[list[list[float]]]
    motion_noise: list[float]
    #: quadruples of markers (indices) whose signed volume det(b - a, c - a, d - a) was
    #: positive in the training frames (near-rigid and thick): the handedness pair distances
    #: cannot carry (a subject read mirrored keeps every distance); learned by
    #: ``train structure``, empty in models without it
    chirality: list[list[int]] = Field(default_factory=list)
    #: witness quadruples ``[i, j, a, b]`` of "twin" markers ``i, j`` (two markers of one body
    #: whose exchange no trained distance and no chirality quadruple can tell: a forearm's
    #: radius and ulna): ``det(j - i, a - i, b - i)`` kept a positive sign in the training
    #: frames, so exchanging ``i`` and ``j`` reverses it; the boot votes with them
    #: (``boot_match._twins``); learned by ``train structure``, empty in models without it
    twin_witnesses: list[list[int]] = Field(default_factory=list)

    @property
    def no_body(self) -> list[str]:
        """The markers in no rigid body, sorted (training saw them in fewer than 3 frames, or
        as a duplicate track): a labeler of this model never labels them."""
        inside = {i for b in self.bodies for i in b}
        return sorted(m for i, m in enumerate(self.markers) if i not in inside)

    @property
    def labels(self) -> tuple[str, ...]:
        """``subject:marker`` labels of the markers, in order (a subject ``""``, trained on
        labels without a prefix, gives the bare marker names back)."""
        return tuple(join_label(self.name, m) for m in self.markers)

    @model_validator(mode="after")
    def _check(self) -> SubjectTemplate:
        m = len(self.markers)
        where = f"subject {self.name!r}"
        # names that would not read back from a labeled capture (a hand-edited model)
        if ":" in self.name:
            raise ValueError(
                f"{where}: a subject name cannot hold ':' (labels are subject:marker; it would "
                f"read back as subject {self.name.partition(':')[0]!r})"
            )
        for mk in self.markers:
            if not mk.strip() or is_ghost(mk):
                raise ValueError(
                    f"{where}: marker name {mk!r} is empty or named like an unlabeled track (*N)"
                )
        for what, name in (("subject", self.name), *(("marker", mk) for mk in self.markers)):
            if any(unicodedata.category(c) == "Cc" for c in name):  # a newline, a tab, NUL
                raise ValueError(
                    f"{where}: {what} name {name!r} holds a control character (no capture file "
                    "or wire label can carry it back)"
                )
        if len(set(self.markers)) != m:
            raise ValueError(f"{where}: duplicate marker names")
        for key in ("D", "A"):
            mat = getattr(self, key)
            if len(mat) != m or any(len(row) != m for row in mat):
                raise ValueError(f"{where}: {key} must be {m}x{m}")
            if any(v is not None and not (math.isfinite(v) and v >= 0) for row in mat for v in row):
                raise ValueError(f"{where}: {key} has a negative or non-finite entry")
        lo, hi = PAIR_DISTANCE_MM
        for i in range(m):
            for j in range(m):
                d, a = self.D[i][j], self.A[i][j]
                if i == j or d is None:
                    continue
                if not lo <= d <= hi:
                    raise ValueError(
                        f"{where}: D[{i}][{j}] = {d:g} mm ({self.markers[i]}-{self.markers[j]}) "
                        f"is outside {lo:g}-{hi:g} mm"
                    )
                if a is not None and not a < d:
                    raise ValueError(
                        f"{where}: A[{i}][{j}] = {a:g} mm is not below the distance D = {d:g} mm"
                    )
        if len(self.motion_noise) != m:
            raise ValueError(f"{where}: motion_noise needs {m} values")
        if any(not (math.isfinite(q) and q > 0) for q in self.motion_noise):
            raise ValueError(f"{where}: motion_noise must be positive and finite")
        qlo, qhi = MOTION_NOISE_RANGE
        for i, q in enumerate(self.motion_noise):
            if not qlo <= q <= qhi:
                raise ValueError(
                    f"{where}: motion_noise[{i}] = {q:g} (mm/s^2)^2 ({self.markers[i]}) is outside "
                    f"{qlo:g}-{qhi:g}"
                )
        if len(self.chirality) > MAX_CHIRALITY:
            raise ValueError(
                f"{where}: {len(self.chirality)} chirality entries, more than {MAX_CHIRALITY}"
            )
        seen: dict[frozenset[int], list[int]] = {}
        for quad in self.chirality:
            if len(quad) != 4 or len(set(quad)) != 4 or any(not 0 <= i < m for i in quad):
                raise ValueError(
                    f"{where}: chirality entry {quad} must be 4 distinct marker indices"
                )
            first = seen.setdefault(frozenset(quad), quad)
            if first is not quad:
                raise ValueError(f"{where}: chirality entries {first} and {quad} repeat markers")
            for k, i in enumerate(quad):
                for j in quad[k + 1 :]:
                    if self.D[i][j] is None or self.A[i][j] is None:
                        raise ValueError(
                            f"{where}: chirality entry {quad}: {self.markers[i]}-"
                            f"{self.markers[j]} has no trained distance"
                        )
        if len(self.twin_witnesses) > MAX_CHIRALITY:
            raise ValueError(
                f"{where}: {len(self.twin_witnesses)} twin witnesses, more than {MAX_CHIRALITY}"
            )
        seen_w: set[tuple[int, ...]] = set()
        for quad in self.twin_witnesses:
            if len(quad) != 4 or len(set(quad)) != 4 or any(not 0 <= i < m for i in quad):
                raise ValueError(f"{where}: twin witness {quad} must be 4 distinct marker indices")
            wkey = (min(quad[:2]), max(quad[:2]), *sorted(quad[2:]))
            if wkey in seen_w:
                raise ValueError(f"{where}: twin witness {quad} repeats another")
            seen_w.add(wkey)
        if len(self.shapes) != len(self.bodies):
            raise ValueError(f"{where}: {len(self.bodies)} bodies but {len(self.shapes)} shapes")
        for b, (body, shape) in enumerate(zip(self.bodies, self.shapes, strict=True)):
            if not 1 <= len(body) <= 8:
                raise ValueError(f"{where}: body {b} has {len(body)} markers (1-8 allowed)")
            if len(set(body)) != len(body) or any(not 0 <= i < m for i in body):
                raise ValueError(f"{where}: body {b} has repeated or out-of-range indices")
            if len(shape) != len(body) or any(len(p) != 3 for p in shape):
                raise ValueError(f"{where}: shape of body {b} must be {len(body)}x3")
            if not np.all(np.isfinite(np.asarray(shape, dtype=float))):
                raise ValueError(f"{where}: shape of body {b} is not finite")
            self._check_chirality(b, body, np.asarray(shape, dtype=float))
        spread = body_link_spread(self.A, self.bodies)
        if spread > LABELS_OFF_MM:
            raise ValueError(
                f"{where}: the links inside its bodies vary by {spread:.0f} mm (median trained "
                f"deviation A, at most {LABELS_OFF_MM:g}): trained on labels that do not stay "
                "on their markers; train it again on a correctly labeled take"
            )
        return self

    def _check_chirality(self, b: int, body: list[int], shape: np.ndarray) -> None:
        """A chirality quadruple inside body ``b`` must have the sign of its reference shape
        (else the model is a mirror image, or edited: every reading would be refused)."""
        for quad in self.chirality:
            if reversed_in_shape(quad, body, shape):
                names = ", ".join(self.markers[i] for i in quad)
                raise ValueError(
                    f"subject {self.name!r}: chirality entry {quad} ({names}) is reversed "
                    f"against the reference shape of body {b} (a mirror-image model?)"
                )

    # numpy views (float64, NaN where unknown)
    def D_array(self) -> np.ndarray:
        return np.array([[np.nan if v is None else v for v in r] for r in self.D], dtype=float)

    def A_array(self) -> np.ndarray:
        return np.array([[np.nan if v is None else v for v in r] for r in self.A], dtype=float)


class LabelerModel(BaseModel):
    """A versioned set of subject templates (schema ``version: 1``)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    version: Literal[1] = SCHEMA_VERSION
    # the range every rate is held to (capture.model.rate_problem): 1e-6 Hz was accepted and
    # the stream then reported 0.0 Hz
    rate: float = Field(
        ge=MIN_RATE_HZ,
        le=MAX_RATE_HZ,
        allow_inf_nan=False,
        description="frame rate (Hz) of the training data",
    )
    subjects: list[SubjectTemplate] = Field(min_length=1)
    source: str = ""

    @model_validator(mode="after")
    def _unique(self) -> LabelerModel:
        names = [s.name for s in self.subjects]
        if len(set(names)) != len(names):
            raise ValueError("duplicate subject names")
        return self

    @property
    def marker_names(self) -> tuple[str, ...]:
        """``subject:marker`` labels in model order (subjects, then their markers)."""
        return tuple(label for s in self.subjects for label in s.labels)


#: Two subjects whose trained pair distances differ by at most this (median over the pairs
#: both trained) with the same marker names have one template: a boot cannot tell them apart.
SAME_TEMPLATE_MM = 5.0


def same_templates(model: LabelerModel) -> list[tuple[str, str]]:
    """Pairs of the model's subjects with one template: the same marker names and pair
    distances within ``SAME_TEMPLATE_MM`` at the median (a take and its copy; one performer
    trained twice under two names). Such subjects keep their names only by continuity: which
    one a boot calls which is arbitrary (issue 11)."""
    out = []
    subjects = model.subjects
    for i, a in enumerate(subjects):
        for b in subjects[i + 1 :]:
            if list(a.markers) != list(b.markers):
                continue
            da, db = a.D_array(), b.D_array()
            both = np.isfinite(da) & np.isfinite(db)
            np.fill_diagonal(both, False)
            if both.any() and float(np.median(np.abs(da[both] - db[both]))) <= SAME_TEMPLATE_MM:
                out.append((a.name, b.name))
    return out


def _matrix(a: np.ndarray) -> list[list[float | None]]:
    return [[None if not np.isfinite(v) else round(float(v), 4) for v in row] for row in a]


def make_subject(
    name: str,
    markers: list[str],
    D: np.ndarray,
    A: np.ndarray,
    bodies: list[list[int]],
    shapes: list[np.ndarray],
    motion_noise: np.ndarray,
) -> SubjectTemplate:
    """Builds a validated template from numpy arrays (NaN -> ``null``)."""
    try:
        return SubjectTemplate(
            name=name,
            markers=list(markers),
            D=_matrix(np.asarray(D)),
            A=_matrix(np.asarray(A)),
            bodies=[[int(i) for i in b] for b in bodies],
            shapes=[np.round(np.asarray(s, dtype=float), 4).tolist() for s in shapes],
            motion_noise=[float(q) for q in np.asarray(motion_noise)],
        )
    except ValidationError as exc:
        raise ModelError(f"invalid template for subject {name!r}: {_first_error(exc)}") from exc


def _first_error(exc: ValidationError, raw: object = None) -> str:
    """The first error as ``location: message``; with the ``raw`` model, a location in a
    subject also names it (``subjects.0 ('P1').chirality.0.3: ...``)."""
    err = exc.errors()[0]
    where = [str(x) for x in err.get("loc", ())]
    msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")  # pydantic's, not ours
    if len(where) >= 2 and where[0] == "subjects" and isinstance(raw, dict):
        subjects = raw.get("subjects")
        k = int(where[1]) if where[1].isdigit() else -1
        if isinstance(subjects, list) and 0 <= k < len(subjects):
            name = subjects[k].get("name") if isinstance(subjects[k], dict) else None
            if isinstance(name, str) and f"subject {name!r}" not in msg:
                where[1] = f"{where[1]} ({name[:64]!r})"
    loc = ".".join(where)
    return f"{loc}: {msg}" if loc else msg


def save_model(model: LabelerModel, path: str | Path) -> None:
    """Writes ``model`` as JSON, creating parent folders.

    The JSON goes to a temporary file next to the target, is synced and renamed over it, so
    the model file is either complete or untouched: an interrupted run (Ctrl-C, a full disk)
    never leaves half a model, and a service (re)starting meanwhile reads the old or the new
    model, never a truncated one. A symbolic link is followed (the file it points to is
    replaced)."""
    p = Path(path)
    text = model.model_dump_json(indent=1).encode("utf-8")
    target = Path(os.path.realpath(p))
    try:
        if target.is_dir():
            raise IsADirectoryError(errno.EISDIR, "Is a directory")
        target.parent.mkdir(parents=True, exist_ok=True)
        replace_file(target, lambda tmp: tmp.write_bytes(text))
    except OSError as exc:
        raise ModelError(f"{p}: cannot write model: {os_reason(exc)}") from exc


#: what a model file is, said with every "this file is no model" error
MODEL_IS = (
    "a subject model is the JSON file `mocap-labeler train structure TAKE... --out MODEL.json` "
    "writes"
)


def _not_a_model(p: Path, why: str) -> ModelError:
    """The error for a file that is no model at all: why, what a model is, and, for a capture
    given in its place (``--model take.c3d``), that it is one."""
    if p.suffix.lower() in (".c3d", ".trc", ".npz"):
        return ModelError(
            f"{p}: named as a capture, not a subject model ({why}); a model is trained on a "
            f"labeled capture: mocap-labeler train structure {p} --out MODEL.json"
        )
    return ModelError(f"{p}: {why}: not a subject model; {MODEL_IS}")


def load_model(path: str | Path) -> LabelerModel:
    """Reads and validates a JSON model; raises :class:`ModelError` naming the problem."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_MODEL_BYTES:
            raise _not_a_model(p, f"{size} bytes, larger than a model can be ({MAX_MODEL_BYTES})")
        raw = json.loads(p.read_bytes().decode("utf-8"))
    except OSError as exc:
        raise ModelError(f"{p}: cannot read model: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise _not_a_model(p, f"not UTF-8 text (byte {exc.start})") from exc
    except json.JSONDecodeError as exc:
        raise _not_a_model(p, f"not JSON: {exc}") from exc
    except RecursionError as exc:
        raise _not_a_model(p, "JSON nested too deeply") from exc
    if not isinstance(raw, dict):
        raise _not_a_model(p, "not a JSON object")
    if "version" not in raw:
        raise _not_a_model(p, "no 'version' key")
    if "subjects" not in raw:  # another JSON of ours (a shoulder skeleton, a report)
        kind = raw.get("format")
        raise _not_a_model(p, f"a {kind!r} file" if isinstance(kind, str) else "no 'subjects'")
    if raw.get("version") != SCHEMA_VERSION:
        raise ModelError(
            f"{p}: unsupported model version {raw.get('version')!r} (expected {SCHEMA_VERSION}; "
            "a model from another release of mocap-labeler: train it again with this one)"
        )
    try:
        return LabelerModel.model_validate(raw)
    except ValidationError as exc:
        raise ModelError(f"{p}: invalid model: {_first_error(exc, raw)}") from exc
    except RecursionError as exc:
        raise ModelError(f"{p}: not a model: nested too deeply") from exc
