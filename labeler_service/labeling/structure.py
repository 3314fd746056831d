"""Subject templates trained from labeled frames, sklearn style (the core of ``train
structure``, of ``evaluate --labeled-start model`` and of a service stream with
``labeled_start = "model"``).

``StructureTrainer(...).fit(captures)`` learns one
:class:`~labeler_service.labeling.templates.SubjectTemplate` per subject of in-memory
:class:`~labeler_service.capture.Capture` objects with the same code the online labeler uses on
its training window (:func:`labeler_service.labeling.training.train_subject`): D and A (Yu et al.
2007, Eq. 1-2), rigid bodies, reference shapes and per-marker motion noise, then what the boot
needs beyond them: chirality quadruples (:func:`chirality_quads`), handed reference shapes
(:func:`handed_shapes`) and twin witnesses (:func:`twin_witnesses`). Frames of several captures
are pooled per subject; the motion noise is learned per capture (it depends on the rate) and
averaged. The fitted template set is ``model_`` (a
:class:`~labeler_service.labeling.templates.LabelerModel`).

Reading files is not done here: :class:`offline.structure.StructureTrainer` (``train
structure``) adds it on top of this class.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np

from labeler_service.capture.model import Capture, split_label
from labeler_service.errors import LabelerError, ModelError
from labeler_service.labeling.kernels.chirality import volume_stats
from labeler_service.labeling.kernels.state import MAX_BODY
from labeler_service.labeling.templates import LabelerModel, reversed_in_shape
from labeler_service.labeling.training import motion_noise, train_subject

#: labeled frames a window model needs (:func:`window_model`; the default trainer's
#: ``min_pair_frames``: fewer give no pair statistics, so no rigid body)
WINDOW_MIN_FRAMES = 3

#: chirality quadruples (see :func:`chirality_quads`)
CHIRALITY_A_MM = 20.0  # every pair of a quadruple this steady (a segment, or two beside a joint)
CHIRALITY_MIN_MM = 20.0  # thick: cube root of |det| above this in 90 % of the frames
THICK_QUANTILE = 0.1  # ... the 10th percentile of the cube root over the frames seen
CHIRALITY_AGREE = 0.98  # one sign in this fraction of the frames
CHIRALITY_PER_MARKER = 3  # a marker is in at most this many quadruples
CHIRALITY_MAX = 64  # quadruples per subject
CHIRALITY_FRAMES = 400  # frames looked at (evenly spread)
CHIRALITY_POOL = 20000  # quadruples enumerated at most
HINGE_MAX_MARKERS = 8  # a body or hinge union larger than this adds no quadruples (C(8,4) = 70)

#: twin markers and their witnesses (see :func:`twin_witnesses`)
TWIN_Z = 1.5  # |D[i,k] - D[j,k]| <= TWIN_Z (A[i,k] + A[j,k]) for every body partner k
TWIN_SEPARATED = 0.9  # a chirality quadruple reversed by the exchange in this fraction separates
TWIN_AGREE = 0.99  # a witness keeps one sign in this fraction of the training frames
TWIN_MIN_FRAMES = 20  # ... seen in at least this many of them
TWIN_WITNESSES = 6  # witnesses per twin pair at most
TWIN_PER_MARKER = 2  # a third marker is in at most this many witnesses of one pair
TWIN_REACH = 0.5  # a witness's other markers within this fraction of the subject's extent


def _hinge_quads(bodies: Sequence[Sequence[int]]) -> set[tuple[int, int, int, int]]:
    """Quadruples inside one trained body or the union of two bodies that share at least two
    markers (a hinge: a foot and its ankle-knee body share the ankle and the fifth toe). Their
    sign holds in poses the training frames did not show unless the hinge folds flat, so they
    are kept even when a pair of them is not steady (knee to big toe across the ankle)."""
    sets = [frozenset(int(i) for i in b) for b in bodies]
    groups = {s for s in sets if len(s) >= 4}
    groups |= {a | b for i, a in enumerate(sets) for b in sets[i + 1 :] if len(a & b) >= 2}
    out: set[tuple[int, int, int, int]] = set()
    for g in groups:
        if len(g) <= HINGE_MAX_MARKERS:
            out.update(itertools.combinations(sorted(g), 4))
    return out


def chirality_quads(
    pos: np.ndarray,
    A: np.ndarray,
    bodies: Sequence[Sequence[int]] = (),
    steady_pool: bool = True,
) -> list[list[int]]:
    """Quadruples ``[a, b, c, d]`` of markers whose signed volume ``det(b - a, c - a, d - a)``
    is positive in the training frames ``pos (F, m, 3)``: every pair of the four steady
    (``A <= CHIRALITY_A_MM`` = 20 mm) while each of the four moved against some other marker
    (a pair of it over 20 mm: steadiness in frames where a marker kept still says nothing of
    other poses), the tetrahedron thick (cube root of ``|det|`` >= 20 mm in
    90 % of the frames where all four are seen, at least 10 such frames) and one sign in 98 %
    of them.
    Pair distances are the same for a subject and its mirror image; these volumes are not, and
    the boot uses them to refuse a subject read mirrored (left for right). Thickest first, each
    marker in at most ``CHIRALITY_PER_MARKER`` of them, at most ``CHIRALITY_MAX``.
    Quadruples of one body or two bodies on a hinge (:func:`_hinge_quads`) are also tried
    without the steadiness test and chosen before the others: a leg's knee, ankle and toes are
    not all steady to 20 mm, yet their volume keeps its sign, and without them a dancer's
    left foot read as the right one reverses no quadruple.
    ``steady_pool`` False: only those (no quadruple across bodies chosen for its steadiness;
    the window model's trainer, :func:`window_model`: in a labeled start's 0.4 s every pair
    is steady, and a head-knee-sternum-elbow quadruple turns over at the first serve)."""
    m = A.shape[0]
    steady = np.isfinite(A) & (A <= CHIRALITY_A_MM)
    np.fill_diagonal(steady, False)
    if steady_pool:
        # steadiness says "one rigid piece" only of markers the frames moved against some
        # partner (a marker steady to every other was merely still: a kneeling segment's trunk)
        moved = np.any(np.isfinite(A) & (A > CHIRALITY_A_MM), axis=1)
        steady &= moved[:, None] & moved[None, :]
    else:
        steady[:] = False
    quads: list[tuple[int, int, int, int]] = []
    for a in range(m):
        nb = np.flatnonzero(steady[a, a + 1 :]) + a + 1
        for bi, b in enumerate(nb.tolist()):
            nc = nb[bi + 1 :][steady[b, nb[bi + 1 :]]]
            for ci, c in enumerate(nc.tolist()):
                nd = nc[ci + 1 :][steady[c, nc[ci + 1 :]]]
                quads.extend([(a, b, c, d) for d in nd.tolist()])
                if len(quads) >= CHIRALITY_POOL:
                    break
            if len(quads) >= CHIRALITY_POOL:
                break
        if len(quads) >= CHIRALITY_POOL:
            break
    # (every pair must have a trained distance: ``load_model`` refuses a quadruple without)
    hinge = {
        h
        for h in _hinge_quads(bodies)
        if all(np.isfinite(A[i, j]) for i, j in itertools.combinations(h, 2))
    }
    quads = sorted(hinge) + [q for q in quads if q not in hinge]
    if not quads:
        return []
    q = np.asarray(quads, dtype=np.int64)
    n, pos_frac, thick = volume_stats(_spread_frames(pos), q, THICK_QUANTILE)
    sign = np.where(pos_frac >= 0.5, 1.0, -1.0)
    agree = np.maximum(pos_frac, 1.0 - pos_frac)
    ok = (n >= 10) & (agree >= CHIRALITY_AGREE) & (thick >= CHIRALITY_MIN_MM)
    out: list[list[int]] = []
    first = np.zeros(len(q), dtype=bool)
    first[: len(hinge)] = True  # (sorted(hinge) leads ``quads``)
    ok_k = np.flatnonzero(ok)
    order = ok_k[np.lexsort((-np.nan_to_num(thick[ok_k]), ~first[ok_k]))]  # hinge ones first
    use = [0] * m
    for (i0, i1, i2, i3), s in zip(q[order].tolist(), sign[order].tolist(), strict=True):
        if max(use[i0], use[i1], use[i2], use[i3]) >= CHIRALITY_PER_MARKER:
            continue
        out.append([i0, i1, i2, i3] if s > 0 else [i0, i1, i3, i2])
        for i in (i0, i1, i2, i3):
            use[i] += 1
        if len(out) >= CHIRALITY_MAX:
            break
    return out


def _spread_frames(pos: np.ndarray) -> np.ndarray:
    """At most ``CHIRALITY_FRAMES`` frames of ``pos (F, m, 3)``, evenly spread."""
    f = pos.shape[0]
    return np.asarray(pos[np.unique(np.linspace(0, f - 1, min(f, CHIRALITY_FRAMES)).astype(int))])


def _signed_volumes(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``det(p[b] - p[a], p[c] - p[a], p[d] - p[a])`` per frame of ``p (F, m, 3)`` and quadruple
    ``[a, b, c, d]`` of ``q (Q, 4)``: ``(F, Q)``, NaN where a marker is unseen."""
    a = p[:, q[:, 0]]
    # rows b - a, c - a, d - a (differences in p's dtype, as a (F, Q, 3, 3) stack would take
    # them); the triple product ``(b - a) . ((c - a) x (d - a))``, NaN where a marker is unseen
    u, v, w = ((p[:, q[:, k]] - a).astype(np.float64) for k in (1, 2, 3))
    return np.einsum("fqi,fqi->fq", u, np.cross(v, w))


def twin_pairs(
    pos: np.ndarray, D: np.ndarray, A: np.ndarray, bodies: Sequence[Sequence[int]], quads
) -> list[tuple[int, int]]:
    """Pairs of markers ``(i, j)`` of one body whose exchange the trained distances cannot
    tell and no chirality quadruple separates: every marker ``k`` sharing a body with ``i`` or
    ``j`` has ``|D[i,k] - D[j,k]| <= TWIN_Z (A[i,k] + A[j,k])`` (a forearm's radius and ulna
    markers, 81 mm apart, at 271.8 and 277.5 mm from the elbow, 143.4 and 143.1 from the
    finger), and no quadruple of ``quads`` containing ``i`` or ``j`` changes its sign in
    ``TWIN_SEPARATED`` of the training frames ``pos (F, m, 3)`` when the two are exchanged."""
    m = D.shape[0]
    partner = np.zeros((m, m), dtype=bool)
    for b in bodies:
        idx = np.asarray(b, dtype=np.int64)
        partner[np.ix_(idx, idx)] = True
    np.fill_diagonal(partner, False)
    q = np.asarray(quads, dtype=np.int64).reshape(-1, 4)
    p = _spread_frames(pos)
    out = []
    for i, j in itertools.combinations(range(m), 2):
        if not partner[i, j]:
            continue
        ks = np.flatnonzero(partner[i] | partner[j])
        ks = ks[(ks != i) & (ks != j)]
        d = np.abs(D[i, ks] - D[j, ks])
        a = A[i, ks] + A[j, ks]
        ok = np.isfinite(d) & np.isfinite(a)
        if not ok.any() or np.any(d[ok] > TWIN_Z * np.maximum(a[ok], 1.0)):
            continue
        mine = q[np.any((q == i) | (q == j), axis=1)]
        if mine.size:
            swapped = np.where(mine == i, -1, mine)
            swapped = np.where(mine == j, i, swapped)
            swapped = np.where(swapped == -1, j, swapped)
            before = _signed_volumes(p, mine)
            after = _signed_volumes(p, swapped)
            both = np.isfinite(before) & np.isfinite(after)
            flip = np.where(both, np.sign(before) != np.sign(after), False).sum(axis=0)
            if np.any(flip >= TWIN_SEPARATED * np.maximum(both.sum(axis=0), 1)):
                continue
        out.append((i, j))
    return out


def twin_witnesses(
    pos: np.ndarray, D: np.ndarray, A: np.ndarray, bodies: Sequence[Sequence[int]], quads
) -> list[list[int]]:
    """Witness quadruples ``[i, j, a, b]`` of the twin pairs (:func:`twin_pairs`): ``a, b``
    any two other markers of the subject with the signed volume ``det(j - i, a - i, b - i)``
    positive in ``TWIN_AGREE`` of the training frames (at least ``TWIN_MIN_FRAMES`` seen) and
    thick (cube root of ``|det|`` >= ``CHIRALITY_MIN_MM`` in 90 % of them). Exchanging ``i``
    and ``j`` reverses every witness of the pair. The steadiest first (least largest trained
    deviation ``A`` among the quadruple's pairs: a quadruple over one segment keeps its sign in
    any pose, one across a joint may flip in a pose the training never showed), at most
    ``TWIN_WITNESSES`` per pair, a third marker in at most ``TWIN_PER_MARKER`` of them, and
    only markers within ``TWIN_REACH`` of the subject's extent (largest ``D``) of both twins,
    about a limb's length: a dancer's toe markers witnessed by her head and shoulders keep
    their sign only while her feet point the way they did in training, and all of them flip
    together when she turns a foot. The boot votes with them (``boot_match._twins``)."""
    m = D.shape[0]
    p = _spread_frames(pos)
    out: list[list[int]] = []
    extent = float(np.nanmax(D)) if np.isfinite(D).any() else 0.0
    for i, j in twin_pairs(pos, D, A, bodies, quads):
        near = np.fmax(D[i], D[j]) <= TWIN_REACH * extent  # (NaN: never seen together)
        rest = [k for k in range(m) if k not in (i, j) and near[k]]
        ab = np.array(list(itertools.combinations(rest, 2)), dtype=np.int64).reshape(-1, 2)
        if ab.size == 0:
            continue
        q = np.concatenate([np.full((ab.shape[0], 1), i), np.full((ab.shape[0], 1), j), ab], 1)
        n, pos_frac, thick = volume_stats(p, q, THICK_QUANTILE)
        agree = np.maximum(pos_frac, 1.0 - pos_frac)
        ok = (n >= TWIN_MIN_FRAMES) & (agree >= TWIN_AGREE) & (thick >= CHIRALITY_MIN_MM)
        if not ok.any():
            continue
        k = np.flatnonzero(ok)
        pairs = [(0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
        spread = np.max([A[q[k, u], q[k, v]] for u, v in pairs], axis=0)
        spread = np.where(np.isfinite(spread), spread, np.inf)
        use: dict[int, int] = {}
        chosen = 0
        for r in k[np.lexsort((-thick[k], spread))]:
            a, b = int(q[r, 2]), int(q[r, 3])
            if use.get(a, 0) >= TWIN_PER_MARKER or use.get(b, 0) >= TWIN_PER_MARKER:
                continue
            out.append([i, j, a, b] if pos_frac[r] >= 0.5 else [i, j, b, a])
            use[a] = use.get(a, 0) + 1
            use[b] = use.get(b, 0) + 1
            chosen += 1
            if chosen >= TWIN_WITNESSES:
                break
    return out


def handed_shapes(
    shapes: list[list[list[float]]], bodies: list[list[int]], quads: list[list[int]]
) -> list[list[list[float]]]:
    """``shapes`` with the handedness of the training frames: a body whose reference shape
    reverses a chirality quadruple inside it is mirrored. A body never seen whole in training
    gets its shape from its distances alone (multidimensional scaling), whose handedness is
    arbitrary; the quadruples come from the frames themselves, and a model whose shape and
    quadruples disagree would be refused at load."""
    out = []
    for body, shape in zip(bodies, shapes, strict=True):
        p = np.asarray(shape, dtype=float)
        if any(reversed_in_shape(quad, body, p) for quad in quads):
            p = p * np.array([1.0, 1.0, -1.0])
        out.append(p.tolist())
    return out


class StructureTrainer:
    """Learns subject templates from labeled captures.

    Parameters are those of the rigid-body rule (see :mod:`labeler_service.labeling.training`):
    ``tolerance_mm`` (largest ``A + distance_weight D`` inside a body), ``distance_weight``,
    ``min_size``/``max_size`` (markers per body, 1-8), ``min_pair_frames`` (samples needed for a
    pair's statistics) and ``all_seeds`` (every marker seeds a body: there is time for the
    richer, overlapping body set); ``glimpsed``: a marker seen in fewer than
    ``min_pair_frames`` frames joins a body of its nearest markers
    (:func:`~labeler_service.labeling.training.glimpse_bodies`; the window model's trainer);
    ``steady_pool``: chirality quadruples across bodies chosen for their steadiness
    (:func:`chirality_quads`; the window model's trainer goes without).
    """

    def __init__(
        self,
        tolerance_mm: float = 6.0,
        distance_weight: float = 0.02,
        min_size: int = 3,
        max_size: int = 6,
        min_pair_frames: int = 3,
        all_seeds: bool = True,
        glimpsed: bool = False,
        steady_pool: bool = True,
    ) -> None:
        self.tolerance_mm = tolerance_mm
        self.distance_weight = distance_weight
        self.min_size = min_size
        self.max_size = max_size
        self.min_pair_frames = min_pair_frames
        self.all_seeds = all_seeds
        self.glimpsed = glimpsed
        self.steady_pool = steady_pool

    def _check_rule(self) -> None:
        """Refuses rule values that make no body (``train structure``'s options named beside
        the parameters: a NaN weight made every marker a body of its own, and a negative one
        was blamed on the training frames' labels)."""
        tol, w = self.tolerance_mm, self.distance_weight
        if not (math.isfinite(tol) and tol > 0):
            raise ModelError(
                f"tolerance_mm (--tolerance-mm) must be a finite distance > 0 mm, got {tol}"
            )
        if not (math.isfinite(w) and w >= 0):
            raise ModelError(
                f"distance_weight (--distance-weight) must be a finite number >= 0, got {w}"
            )
        if not 1 <= self.min_size <= self.max_size <= MAX_BODY:
            raise ModelError(
                f"min_size and max_size (--min-size, --max-size) need 1 <= min <= max <= "
                f"{MAX_BODY} markers per body, got {self.min_size} and {self.max_size}"
            )
        if self.min_pair_frames < 1:
            raise ModelError(f"min_pair_frames must be >= 1, got {self.min_pair_frames}")

    def fit(self, captures: Sequence[Capture]) -> StructureTrainer:
        """Learns ``model_`` (one template per subject found in the captures)."""
        self._check_rule()
        caps = list(captures)
        if not caps:
            raise ModelError("train structure needs at least one capture")
        # subject -> marker names in order of first appearance
        subjects: dict[str, list[str]] = {}
        for cap in caps:
            for s in cap.subjects:
                names = subjects.setdefault(s, [])
                for i in cap.subject_columns(s):
                    marker = split_label(cap.labels[i])[1]
                    if marker not in names:
                        names.append(marker)
        if not subjects:
            raise ModelError("no labeled markers in the captures (only unlabeled *N tracks?)")
        templates = []
        for subject, markers in subjects.items():
            blocks, noises = [], []
            for cap in caps:
                cols = {split_label(cap.labels[i])[1]: i for i in cap.subject_columns(subject)}
                if not cols:
                    continue
                pos = np.full((cap.n_frames, len(markers), 3), np.nan, dtype=np.float32)
                for k, mk in enumerate(markers):
                    if mk in cols:
                        pos[:, k] = cap.positions[:, cols[mk]]
                blocks.append(pos)
                noises.append(motion_noise(pos, cap.rate))
            pos = np.concatenate(blocks)
            t = train_subject(
                subject or "subject",
                markers,
                pos,
                caps[0].rate,
                tolerance_mm=self.tolerance_mm,
                distance_weight=self.distance_weight,
                min_size=self.min_size,
                max_size=self.max_size,
                min_pair_frames=self.min_pair_frames,
                all_seeds=self.all_seeds,
                glimpsed=self.glimpsed,
            )
            # the pooled frames' motion noise is replaced: noise depends on the rate, so it is
            # learned per capture and averaged (positive and finite like each capture's)
            q = np.mean(noises, axis=0)
            quads = chirality_quads(pos, t.A_array(), t.bodies, self.steady_pool)
            shapes = handed_shapes(t.shapes, t.bodies, quads)
            witnesses = twin_witnesses(pos, t.D_array(), t.A_array(), t.bodies, quads)
            templates.append(
                t.model_copy(
                    update={
                        "motion_noise": [float(x) for x in q],
                        "chirality": quads,
                        "shapes": shapes,
                        "twin_witnesses": witnesses,
                    }
                )
            )
        rates = sorted({c.rate for c in caps})
        self.model_ = LabelerModel(
            rate=rates[0],
            subjects=templates,
            source=", ".join(c.source or "capture" for c in caps),
        )
        self.n_frames_ = int(sum(c.n_frames for c in caps))
        return self


def window_model(window: Capture) -> LabelerModel:
    """The subject templates of a labeled init window (``window``: its frames, true labels):
    what the labeled start through the model-based labeler boots from
    (:func:`~labeler_service.labeling.registry.make_window_labeler`; ``evaluate --labeled-start
    model``, a service stream with ``labeled_start = "model"``; the booter's relearn). The
    trainer of ``train structure``, without quadruples across bodies chosen for their
    steadiness (``steady_pool`` off): a window's few frames show every pair steady, and those
    quadruples turned over in the first stroke (tune24: a head-knee-sternum-elbow quadruple
    kept the tennis arm's free points from its markers for 1 s). A window of fewer frames than
    the trainer needs for a pair's statistics (``min_pair_frames``, 3) raises
    :class:`LabelerError`, as the labeler trained in place does."""
    trainer = StructureTrainer(glimpsed=True, steady_pool=False)
    if window.n_frames < max(WINDOW_MIN_FRAMES, trainer.min_pair_frames):
        raise LabelerError(
            f"the labeled start through a window model needs at least {WINDOW_MIN_FRAMES} "
            f"labeled init frames to train subject templates on (got {window.n_frames}): send "
            "more init frames (evaluate --init-frames, replay --init-frames)"
        )
    return trainer.fit([window]).model_
