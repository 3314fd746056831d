"""Matching anonymous points to subject templates (steps 2-5 of labeling/boot.py): anchor
triangles per rigid body, body candidates by distance signature, 3D verification, the node
graph (numba), hypotheses grown per template, symmetric readings, completion of a subject from
free points. Everything here is private to :class:`~labeler_service.labeling.boot.Booter`."""

from __future__ import annotations

import contextlib
import contextvars
import functools
import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse.csgraph import minimum_spanning_tree
from scipy.spatial import cKDTree

from labeler_service._numba import njit
from labeler_service.capture import side_pairs
from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.geometry import rotation_angle
from labeler_service.labeling.kernels.boot_anchor import _anchor_predict, _join_triangles
from labeler_service.labeling.kernels.boot_grow import _grow as _grow_kernel
from labeler_service.labeling.kernels.boot_pairs import _constancy_counts
from labeler_service.labeling.kernels.boot_pairs import _pair_error as _pair_error_kernel
from labeler_service.labeling.kernels.boot_pairs import _swap_gains as _swap_gains_kernel
from labeler_service.labeling.kernels.stacked import _spread_labels
from labeler_service.labeling.kernels.track import _match_tracks, _track_history, _track_step
from labeler_service.labeling.templates import LabelerModel

#: A tolerance (``tol_mm + tol_sigma A + tol_relative D``) spans about this many standard
#: deviations of a pair of one trained body: the likelihood of a reading (:func:`_pair_nll`)
#: weighs its errors in standard deviations, not in tolerances (in tolerances, an arm read one
#: marker along its chain cost 1.6 more than the right reading among 600 on the still start
#: of the tennis take, and won on the loose pairs).
STRICT_SIGMAS = 4.0
#: A reading exchange (:func:`_exchange`, :func:`_swap_mirrors`) must lower the negative
#: log-likelihood by more than this (nats): ties and noise keep the reading the candidates gave.
EXCHANGE_MARGIN = 1.0
#: A symmetry of a segment is a reading the stream may need only when it turns the segment by
#: at least this (degrees): a half turn no joint makes (:func:`_plate_symmetries`).
HALF_TURN_DEG = 150.0
#: Segments of at most this many markers are searched for symmetries (:func:`_plate_symmetries`:
#: every permutation, 5! = 120 at most).
PLATE_MAX = 5
#: Rounds of exchanges and relocations (:func:`_local_search`) per hypothesis at most.
LOCAL_ROUNDS = 4
#: A placed pair exchanged along the window (:func:`_window_exchange`) must fit better in this
#: share of the frames that track both points, ...
WINDOW_EXCHANGE_SHARE = 0.8
#: ... by this many nats in the median (a true exchange on the real takes: thousands), ...
WINDOW_EXCHANGE_NATS = 10.0
#: ... at most this many exchanges per subject and extension.
WINDOW_EXCHANGE_ROUNDS = 3
#: An exchange of two markers of one segment neither of which is doubtful (inside a triangle,
#: :func:`_window_exchange`) must gain this many nats in the median: the dancer's wrist bar,
#: symmetric, gained 10-13 read either way round.
WINDOW_TRIANGLE_NATS = 50.0
#: Bodies are neighbours in the chain (:func:`_adjacent`) up to this multiple of a body's
#: steadiest pair deviation to any other body.
NEIGHBOUR = 1.5
#: Steadiest articulated pairs a segment joining through links must keep in range (_steady_links).
STEADY_LINKS = 3
#: A chirality quadruple (:func:`_handedness`) votes only when its tetrahedron is at least this
#: thick (cube root of ``|det|``, mm; trained ones are >= 20 mm): a flat one flips with noise.
CHIRAL_MIN_MM = 10.0
#: A hypothesis is refused when one local quadruple (one segment, or two beside a joint: it
#: cannot turn over without a mirror reading) is reversed, or more than this fraction of all its
#: voting quadruples: a wide one, steady in a short training segment, may still turn over in a
#: pose it never saw (a head, upper arm and hand of a hugging performer: 1 of 29 reversed on a
#: correct reading).
CHIRAL_REVERSED = 0.1
#: A twin pair (:func:`_twins`) is exchanged when at least this many of its witnesses vote
#: reversed ...
TWIN_MIN_VOTES = 2
#: ... and their evidence (summed ``|normalised volume|``) is more than this many times that
#: of those voting kept (a witness across a joint may flip in a pose the training never
#: showed: weak or split evidence keeps the reading)
TWIN_RATIO = 1.5
#: A twin witness whose normalised volume (:func:`_twin_votes`) is within this of zero abstains
TWIN_ABSTAIN = 0.05
#: nats by which a body candidate's reading of a superset of another candidate's points must
#: be more likely to drop that candidate (:func:`_undominated`): a likelihood ratio of e^2
DOMINATED_MARGIN = 2.0


# ---------------------------------------------------------------------------- templates
@dataclass
class _Body:
    markers: np.ndarray  # (k,) template marker indices
    shape: np.ndarray  # (k, 3) reference shape
    anchors: list[tuple[int, int, int]]  # positions into ``markers``


@dataclass
class _Template:
    index: int  # subject index in the model
    name: str
    offset: int  # first global marker index
    n: int
    D: np.ndarray
    A: np.ndarray
    tol: np.ndarray  # (m, m) in-body tolerance (inf where unknown)
    bound: np.ndarray  # (m, m) cross-body tolerance (inf where unknown)
    rigid: np.ndarray  # (m, m) pairs with A <= rigid_a_mm
    link: np.ndarray  # (m, m) articulated-pair tolerance (inf where unknown)
    #: (m, m) rigid pairs inside one trained body: only these must hold their distance; a
    #: pair rigid by ``A`` alone (an arm held still against the chest in the training frames)
    #: may change with the pose, so its mismatch is no evidence against a placement
    strict: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    #: (m, m) pairs inside one trained body, rigid or not (``strict`` is its rigid part): a
    #: marker's own evidence in the trilateration (_grow)
    same: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    #: (m, m) pairs inside a trained body whose every pair is rigid (one segment); a pair of
    #: ``strict`` outside every such body sits in a body the trainer completed across a joint
    #: (one of its pairs moved in training): see _stale_pairs
    whole: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    extent: float = 2000.0  # longest pair distance D (mm)
    r_max: float = 0.0  # longest anchor edge + tolerance (mm)
    segments: list[np.ndarray] = field(default_factory=list)  # see _segments
    #: (bodies, m) per body the markers of the bodies next to it in the chain (sharing a
    #: marker, or closer to it than the larger of the two bodies' sizes): see _adjacent
    near: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    bodies: list[_Body] = field(default_factory=list)
    body_of: list[list[int]] = field(default_factory=list)  # marker -> bodies
    #: mirror segments (left and right feet...): see _mirror_pairs
    mirrors: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    #: the mirror pairs whose markers are named as left and right twins (``LKNE``/``RKNE``,
    #: ``Ulna_L``/``Ulna_R``: :func:`~labeler_service.capture.side_pairs`), marker by marker
    sided: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    #: segments of 4+ markers whose trained distances permutations of them keep (a head plate
    #: turned half round): ``(markers, perms)``, see _plate_symmetries
    symmetric: list[tuple[np.ndarray, list[np.ndarray]]] = field(default_factory=list)
    #: per-pair constants of _nll (see _nll_tables)
    nll_scale: np.ndarray = field(default_factory=lambda: np.ones((0, 0)))
    nll_log: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    nll_gauss: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    nll_use: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    #: (q, 4) quadruples of positive trained signed volume (``SubjectTemplate.chirality``)
    chirality: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), dtype=np.int64))
    #: (q,) quadruples inside one body or two bodies sharing a marker (see _handedness)
    chiral_local: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    #: (w, 4) witness quadruples [i, j, a, b] of twin markers i, j
    #: (``SubjectTemplate.twin_witnesses``, see _twins)
    twins: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), dtype=np.int64))
    #: (m,) each marker's twin named on the other side (``LFAPA``/``RFAPA``:
    #: :func:`~labeler_service.capture.side_pairs`), -1 for none and for the markers of mirror
    #: segments (``mirrors``); see _twin_fits_better
    twin: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def _anchors(Dm: np.ndarray, Am: np.ndarray, body: list[int], count: int) -> list[tuple]:
    """Anchor triangles of a body: long, rigid, distinct edges (well-conditioned fits)."""
    k = len(body)
    scored = []
    for tri in itertools.combinations(range(k), 3):
        e = [(tri[0], tri[1]), (tri[0], tri[2]), (tri[1], tri[2])]
        d = np.array([Dm[body[a], body[b]] for a, b in e])
        a = np.array([Am[body[a], body[b]] for a, b in e])
        if not (np.isfinite(d).all() and np.isfinite(a).all()):
            continue
        ds = np.sort(d)
        distinct = min(ds[1] - ds[0], ds[2] - ds[1])
        scored.append((float(ds[0] + 0.5 * distinct - 3.0 * a.max()), tri))
    scored.sort(key=lambda s: -s[0])
    out: list[tuple] = []
    for _, tri in scored:
        if all(len(set(tri) & set(o)) < 3 for o in out):
            out.append(tri)
        if len(out) >= count:
            break
    return out


def _prepare(model: LabelerModel, config: BootConfig) -> list[_Template]:
    out = []
    offset = 0
    for s, subj in enumerate(model.subjects):
        Dm, Am = subj.D_array(), subj.A_array()
        m = len(subj.markers)
        tol = config.tol_mm + config.tol_sigma * Am + config.tol_relative * Dm
        bound = config.tol_mm + config.pair_sigma * Am + config.reach_relative * Dm
        tol = np.where(np.isfinite(tol), tol, np.inf)
        bound = np.where(np.isfinite(bound), bound, np.inf)
        # rigid: low deviation and close (far pairs can look rigid by accident in training,
        # head to knee while walking; the trainer's body rule prefers close pairs too)
        rigid = np.isfinite(Am) & (Am + config.rigid_weight * Dm <= config.rigid_a_mm)
        rigid &= np.isfinite(tol)
        np.fill_diagonal(rigid, False)
        link = config.tol_mm + config.link_sigma * Am + config.tol_relative * Dm
        link = np.where(np.isfinite(link), link, -1.0)
        same = np.zeros((m, m), dtype=bool)
        for body in subj.bodies:
            members = np.asarray(body, dtype=np.int64)
            same[np.ix_(members, members)] = True
        np.fill_diagonal(same, False)
        tpl = _Template(s, subj.name, offset, m, Dm, Am, tol, bound, rigid, link, same & rigid)
        tpl.same = same
        tpl.whole = np.zeros((m, m), dtype=bool)
        for body in subj.bodies:
            members = np.asarray(body, dtype=np.int64)
            inside = rigid[np.ix_(members, members)] | np.eye(members.size, dtype=bool)
            if inside.all():
                tpl.whole[np.ix_(members, members)] = True
        np.fill_diagonal(tpl.whole, False)
        tpl.body_of = [[] for _ in range(m)]
        for b, (body, shape) in enumerate(zip(subj.bodies, subj.shapes, strict=True)):
            if len(body) < 3:
                continue
            anchors = _anchors(Dm, Am, body, config.anchors_per_body)
            if not anchors:
                continue
            bi = len(tpl.bodies)
            tpl.bodies.append(_Body(np.asarray(body), np.asarray(shape, dtype=float), anchors))
            for i in body:
                tpl.body_of[i].append(bi)
            del b
        tpl.extent = float(np.nanmax(Dm)) if np.isfinite(Dm).any() else 2000.0
        tpl.chirality = np.asarray(subj.chirality, dtype=np.int64).reshape(-1, 4)
        tpl.chiral_local = _local_quads(tpl.chirality, subj.bodies)
        tpl.twins = np.asarray(subj.twin_witnesses, dtype=np.int64).reshape(-1, 4)
        tpl.segments = _segments(tpl)
        tpl.mirrors = _mirror_pairs(tpl)
        tpl.sided = _sided(tpl.mirrors, list(subj.markers))
        tpl.symmetric = _plate_symmetries(tpl)
        tpl.twin = np.full(tpl.n, -1, dtype=np.int64)
        for a, b in side_pairs(list(subj.markers)):
            tpl.twin[a], tpl.twin[b] = b, a
        for s1, s2 in tpl.mirrors:  # (their sides are the mirror segments' business)
            tpl.twin[s1] = tpl.twin[s2] = -1
        _nll_tables(tpl)
        tpl.near = _adjacent(tpl)
        for bd in tpl.bodies:
            for tri in bd.anchors:
                mk = bd.markers[list(tri)]
                for a, b in ((0, 1), (0, 2), (1, 2)):
                    tpl.r_max = max(tpl.r_max, float(Dm[mk[a], mk[b]] + tol[mk[a], mk[b]]))
        out.append(tpl)
        offset += m
    return out


# ---------------------------------------------------------------------------- geometry
def _kabsch_batch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Proper rotations ``R (C,3,3)`` and centroids mapping ``src (k,3)`` onto ``dst (C,k,3)``:
    ``dst ~ (src - cs) R^T + cd``."""
    cs = src.mean(axis=0)
    cd = dst.mean(axis=1)
    H = np.einsum("ki,ckj->cij", src - cs, dst - cd[:, None, :])
    U, _, Vt = np.linalg.svd(H)
    V = np.transpose(Vt, (0, 2, 1))
    d = np.sign(np.linalg.det(V @ np.transpose(U, (0, 2, 1))))
    d = np.where(d == 0, 1.0, d)
    V[:, :, 2] *= d[:, None]
    R = V @ np.transpose(U, (0, 2, 1))
    return R, cs, cd


class _Pairs:
    """Oriented point pairs sorted by distance (both orientations), for range queries."""

    def __init__(self, pts: np.ndarray, r_max: float) -> None:
        self.n = pts.shape[0]
        tree = cKDTree(pts)
        pr = tree.query_pairs(r_max, output_type="ndarray")
        if pr.size == 0:
            pr = np.zeros((0, 2), dtype=np.int64)
        d = np.linalg.norm(pts[pr[:, 0]] - pts[pr[:, 1]], axis=1)
        a = np.concatenate([pr[:, 0], pr[:, 1]])
        b = np.concatenate([pr[:, 1], pr[:, 0]])
        dd = np.concatenate([d, d])
        order = np.argsort(dd, kind="stable")
        self.a, self.b, self.d = a[order], b[order], dd[order]
        self.tree = tree
        self._pts = pts
        self._dist: np.ndarray | None = None

    @property
    def dist(self) -> np.ndarray:
        """``(n, n)`` distances of all point pairs, computed once (every template's node
        graph of a boot attempt reads the same points: :class:`_Graph`)."""
        if self._dist is None:
            p = np.ascontiguousarray(self._pts, dtype=np.float64)
            self._dist = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
        return self._dist

    def within(self, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        i0, i1 = np.searchsorted(self.d, [lo, hi])
        return self.a[i0:i1], self.b[i0:i1], self.d[i0:i1]


def _first_rows(rows: np.ndarray) -> np.ndarray:
    """Indices of the first occurrence of each distinct row of ``rows (C, k)``, the distinct
    rows in lexicographic order: ``np.unique(rows, axis=0, return_index=True)[1]`` (a stable
    lexsort, ~5x cheaper on the ~100-row arrays of a body search)."""
    if rows.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    ls = np.lexsort(rows.T[::-1])
    srt = rows[ls]
    new = np.ones(rows.shape[0], dtype=bool)
    new[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    return ls[new]


def _triangles(pairs: _Pairs, d: np.ndarray, t: np.ndarray, limit: int) -> np.ndarray:
    """Candidate point triples ``(C, 3)`` whose edges (01, 02, 12) match ``d +- t``."""
    a1, b1, d1 = pairs.within(d[0] - t[0], d[0] + t[0])
    if a1.size > limit:  # keep the closest distances
        keep = np.argsort(np.abs(d1 - d[0]), kind="stable")[:limit]
        a1, b1 = a1[keep], b1[keep]
    a2, b2, _ = pairs.within(d[1] - t[1], d[1] + t[1])
    a3, b3, _ = pairs.within(d[2] - t[2], d[2] + t[2])
    if a1.size == 0 or a2.size == 0 or a3.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    # join edge 01 with edge 02 on vertex 0; edge 12 must exist (:func:`_join_triangles`)
    o2 = np.argsort(a2, kind="stable")
    n = np.int64(pairs.n)
    keys3 = np.sort(a3.astype(np.int64) * n + b3)
    return _join_triangles(
        a1.astype(np.int64), b1.astype(np.int64), a2[o2].astype(np.int64),
        b2[o2].astype(np.int64), keys3, n,
    )  # fmt: skip


# ---------------------------------------------------------------------------- hypotheses
@njit
def _track_constancy(pp, hist, D, tol):
    """Per candidate row of ``pp (C, k)`` (point per body marker, -1 missing): how many of its
    pair distances along the tracks ``hist (N, W, 3)`` are off ``D +- tol`` (``bad``) out of
    how many were seen (both points tracked in that frame); each ordered pair counted."""
    C, k = pp.shape
    W = hist.shape[1]
    bad = np.zeros(C, dtype=np.int64)
    seen = np.zeros(C, dtype=np.int64)
    for c in range(C):
        nb = 0
        ns = 0
        for i in range(k):
            pi = pp[c, i]
            if pi < 0:
                continue
            for j in range(i + 1, k):
                pj = pp[c, j]
                if pj < 0:
                    continue
                dm = D[i, j]
                tl = tol[i, j]
                for w in range(W):
                    dx = hist[pi, w, 0] - hist[pj, w, 0]
                    dy = hist[pi, w, 1] - hist[pj, w, 1]
                    dz = hist[pi, w, 2] - hist[pj, w, 2]
                    d = np.sqrt(dx * dx + dy * dy + dz * dz)
                    if np.isfinite(d):
                        ns += 1
                        if abs(d - dm) > tl:
                            nb += 1
        bad[c] = 2 * nb
        seen[c] = 2 * ns
    return bad, seen


@dataclass
class _Candidate:
    markers: np.ndarray  # template marker indices
    points: np.ndarray  # point indices (same length)
    err: float  # RMS of predicted-to-point distance (mm)
    body: int = -1  # index into the template's bodies


def _body_candidates(
    tpl: _Template,
    body: _Body,
    pts: np.ndarray,
    hist: np.ndarray,
    pairs: _Pairs,
    config: BootConfig,
) -> list[_Candidate]:
    """Placements of one body: anchor triangles, Kabsch to the reference shape, nearest points
    to the predicted members, distance constancy along the tracks."""
    k = body.markers.shape[0]
    need = min(k, max(3, k - config.body_hidden))
    rows, errs = [], []
    for tri in body.anchors:
        mk = body.markers[list(tri)]
        e = [(0, 1), (0, 2), (1, 2)]
        d = np.array([tpl.D[mk[a], mk[b]] for a, b in e])
        t = np.array([tpl.tol[mk[a], mk[b]] for a, b in e])
        trip = _triangles(pairs, d, t, config.max_candidates)
        if trip.shape[0] == 0:
            continue
        pred = _anchor_predict(body.shape[list(tri)], body.shape, pts, trip)
        dist, near = pairs.tree.query(pred.reshape(-1, 3))
        dist = dist.reshape(trip.shape[0], k)
        near = near.reshape(trip.shape[0], k)
        hit = dist <= config.fit_mm
        hit[:, list(tri)] = True
        near[:, list(tri)] = trip
        keep = hit.sum(axis=1) >= need
        pp = np.where(hit, near, -1)[keep]
        dd = np.where(hit, dist, 0.0)[keep]
        srt = np.sort(pp, axis=1)
        dup = np.any((srt[:, 1:] == srt[:, :-1]) & (srt[:, 1:] >= 0), axis=1)
        rows.append(pp[~dup])
        errs.append(np.sqrt((dd[~dup] ** 2).sum(axis=1) / np.maximum((pp[~dup] >= 0).sum(1), 1)))
    if not rows:
        return []
    pp = np.concatenate(rows)
    err = np.concatenate(errs)
    order = np.argsort(err, kind="stable")
    sel = order[_first_rows(pp[order])]
    pp, err = pp[sel], err[sel]
    # distance constancy of the body's pairs along the tracks
    ok = pp >= 0
    Dm = np.ascontiguousarray(tpl.D[np.ix_(body.markers, body.markers)])
    tol = np.ascontiguousarray(tpl.tol[np.ix_(body.markers, body.markers)])
    bad, seen = _track_constancy(pp, hist, Dm, tol)
    steady = bad <= (1.0 - config.constancy) * np.maximum(seen, 1)
    out = []
    for c in np.flatnonzero(steady):
        v = ok[c]
        out.append(_Candidate(body.markers[v], pp[c, v], float(err[c])))
    return out


class _Memo:
    """The point pairs and body candidates of one local point set, computed once while a memo
    is open (:func:`memo`; :meth:`Booter.extend` opens one per subject it completes). A
    completion (:func:`_complete`) reads the free points within a subject's reach;
    :func:`_complete_weak` completes the same subject again with its weak markers or a loose
    segment released (:func:`_released`), most often on the same local points, and each of
    those recomputed the same pairs and the same candidates of every body not yet placed (10
    hugging performers, the two extensions of a catch-up: 72 completions, half their CPU in
    ``_candidates``, 396 body candidate searches of which 267 repeated one). Both are pure
    functions of the template, the local points and their tracks, so a reuse changes no label.
    Keyed by the template, the body and the local point indices into the arrays of the call
    that opened the memo (those arrays are not changed while it is open)."""

    def __init__(self) -> None:
        self.pairs: dict[tuple, _Pairs] = {}
        self.cands: dict[tuple, list[_Candidate]] = {}
        self.keep: list[tuple[np.ndarray, np.ndarray]] = []


_MEMO: contextvars.ContextVar[_Memo | None] = contextvars.ContextVar("boot_memo", default=None)


@contextlib.contextmanager
def memo() -> Iterator[None]:
    """Pairs and body candidates of the completions inside are computed once per local point
    set (:class:`_Memo`); open it around one call on one set of points and tracks."""
    token = _MEMO.set(_Memo())
    try:
        yield
    finally:
        _MEMO.reset(token)


def _local_pairs(
    tpl: _Template, pts: np.ndarray, hist: np.ndarray, local: np.ndarray
) -> tuple[_Pairs, tuple | None]:
    """``_Pairs`` of the points ``pts[local]`` (radius ``tpl.r_max``), from the memo when one
    is open; returns the memo key of the local set too (None: no memo)."""
    m = _MEMO.get()
    if m is None:
        return _Pairs(pts[local], tpl.r_max), None
    key = (tpl.offset, id(pts), id(hist), local.tobytes())
    pairs = m.pairs.get(key)
    if pairs is None:
        pairs = m.pairs[key] = _Pairs(pts[local], tpl.r_max)
        m.keep.append((pts, hist))  # (their ids stay theirs while the memo is open)
    return pairs, key


class _Graph:
    """Marker-to-point assignments (nodes) of one template and their pairwise relations:
    ``agree[a, b]``: a rigid pair (``A <= rigid_a_mm``) whose point distance matches ``D``;
    ``clash[a, b]``: one marker on two points, one point for two markers, a rigid pair whose
    distance does not match, or any pair farther apart than its reach; ``differ``: a pair rigid
    by ``A`` alone off its distance (no clash: counted against); ``link``: an articulated pair
    within its trained range, ``link_err`` its ``|d - D| / tolerance`` (0 elsewhere); ``art``:
    articulated pairs with a trained range (where links may be). ``support[a]``: how many nodes
    agree with ``a`` (the row sums of ``agree``).

    Rows are computed on demand (:meth:`rows`, numba): a hypothesis reads the rows of the nodes
    it chooses and of its seeds only, a small part of the square (~3,400 nodes per template in
    a 10-person hug, where the whole square cost 0.1-0.2 s per template and 160 MB). The arrays
    are allocated whole but untouched rows cost no memory. Every relation is symmetric."""

    def __init__(
        self,
        tpl: _Template,
        M: np.ndarray,
        P: np.ndarray,
        pts: np.ndarray,
        dist: np.ndarray | None = None,
    ) -> None:
        n = M.shape[0]
        self.M = M.astype(np.int64)
        self.P = P.astype(np.int64)
        self._tables = (tpl.D, tpl.tol, tpl.rigid, tpl.strict, tpl.bound, tpl.link)
        self.A = tpl.A  # trained deviations (the steadiest links: _steady_links)
        if dist is None:  # (``dist``: the points' distance table, shared by the templates)
            p = np.ascontiguousarray(pts, dtype=np.float64)
            dist = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
        self._dist = dist
        self.agree = np.empty((n, n), dtype=np.bool_)
        self.clash = np.empty((n, n), dtype=np.bool_)
        self.differ = np.empty((n, n), dtype=np.bool_)
        self.link = np.empty((n, n), dtype=np.bool_)
        self.link_err = np.empty((n, n))
        self.art = np.empty((n, n), dtype=np.bool_)
        self._done = np.zeros(n, dtype=np.bool_)
        self.support = np.zeros(n, dtype=np.int64)
        _agree_count(self.M, self.P, self._dist, tpl.D, tpl.tol, tpl.rigid, self.support)

    def rows(self, idx: np.ndarray | int) -> np.ndarray:
        """Computes the rows ``idx`` not computed yet; returns ``idx`` (an index array)."""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        _graph_rows(
            idx, self._done, self.M, self.P, self._dist, *self._tables,
            self.agree, self.clash, self.differ, self.link, self.link_err, self.art,
        )  # fmt: skip
        return idx


@njit
def _agree_count(M, P, dist, D, tol, rigid, out):
    """``out[a]``: nodes ``b`` agreeing with node ``a`` (:class:`_Graph`), without the square:
    only the nodes of ``a``'s rigid partner markers are looked at (nodes grouped by marker)."""
    n = M.shape[0]
    m = rigid.shape[0]
    order = np.argsort(M, kind="mergesort")
    start = np.zeros(m + 1, dtype=np.int64)
    for a in range(n):
        start[M[a] + 1] += 1
    for k in range(m):
        start[k + 1] += start[k]
    for a in range(n):
        ma, pa = M[a], P[a]
        c = 0
        for mb in range(m):
            if mb == ma or not rigid[ma, mb]:
                continue
            dm, tm = D[ma, mb], tol[ma, mb]
            for q in range(start[mb], start[mb + 1]):
                pb = P[order[q]]
                if pa != pb and abs(dist[pa, pb] - dm) <= tm:
                    c += 1
        out[a] = c


@njit
def _graph_rows(
    rows, done, M, P, dist, D, tol, rigid, strict, bound, lt, agree, clash, differ, link,
    link_err, art,
):  # fmt: skip
    """The relations of :class:`_Graph` of the nodes ``rows`` to every node (rows ``done``
    already are skipped, then marked)."""
    n = M.shape[0]
    for k in range(rows.shape[0]):
        a = rows[k]
        if done[a]:
            continue
        done[a] = True
        ma, pa = M[a], P[a]
        for b in range(n):
            mb, pb = M[b], P[b]
            same_m = ma == mb
            same_p = pa == pb
            dab = D[ma, mb]
            dev = dist[pa, pb] - dab
            adev = abs(dev)
            known = np.isfinite(dab)
            rig = rigid[ma, mb]
            st = strict[ma, mb]
            other = not same_m and not same_p
            tl = tol[ma, mb]
            agree[a, b] = rig and other and adev <= tl
            differ[a, b] = rig and other and not st and adev > tl
            c = same_m != same_p
            if known and st and adev > tl:
                c = True
            if known and not st and dev > bound[ma, mb]:
                c = True
            clash[a, b] = c
            t = lt[ma, mb]
            ar = known and not rig and t > 0.0 and other
            art[a, b] = ar
            lk = ar and adev <= t
            link[a, b] = lk
            link_err[a, b] = adev / t if lk else 0.0


@njit(fastmath=False)
def _greedy_nodes(
    chosen, support, against, links, lerr, possible, blocked, min_support, done, M, P, dist,
    D, tol, rigid, strict, bound, lt, agree, clash, differ, link, link_err, art,
):  # fmt: skip
    """The node steps of :func:`_select` in one loop (in place): while the best unblocked node
    (most rigid agreements with the set, articulated links breaking ties) has at least
    ``min_support`` agreements, it joins and its row (:func:`_graph_rows`, computed here on
    demand) is added to the counts. Exactly the numpy steps it replaced (same scores, first
    maximum wins; no fastmath, so the division is not replaced by a reciprocal): a node step
    was ~8 numpy passes over ~3,400 nodes, ~40 steps per hypothesis."""
    n = M.shape[0]
    one = np.zeros(1, dtype=np.int64)
    nch = 0
    for i in range(n):
        if chosen[i]:
            nch += 1
    while True:
        denom = 1.0 + nch
        c = 0
        best = -np.inf
        for i in range(n):
            s = -1.0 if blocked[i] else support[i] + (links[i] - lerr[i]) / denom
            if s > best:
                best = s
                c = i
        if support[c] < min_support or blocked[c]:
            return
        chosen[c] = True
        nch += 1
        one[0] = c
        _graph_rows(
            one, done, M, P, dist, D, tol, rigid, strict, bound, lt, agree, clash, differ, link,
            link_err, art,
        )  # fmt: skip
        for i in range(n):
            support[i] += agree[c, i]
            against[i] += differ[c, i]
            links[i] += link[c, i]
            lerr[i] += link_err[c, i]
            possible[i] += art[c, i]
            blocked[i] |= clash[c, i]
        blocked[c] = True


@njit(fastmath=False)
def _body_scores(
    bodies, chosen, blocked, links, lerr, possible, support, against, near, M, refused,
    complete, link_fraction,
):  # fmt: skip
    """The body step's scores of :func:`_select` for every candidate row of ``bodies (C, 8)``
    (node indices, -1 padded) in one pass: ``(total, rsum, count, fb, bb)``, exactly the numpy
    arrays it replaced (``total``: soft link count of a segment free of clashes, beside a placed
    neighbour, not against most of its rigid pairs and linked enough, else -1; ``rsum``: its
    rigid agreements with the set plus shared nodes when spread over two or more markers, else
    0; ``count``: its links; ``fb``: free and beside; ``bb``: its new nodes). The float sums
    over a row of 8 are numpy's pairwise order (no fastmath), so ``argmax`` ties break the same.
    The numpy version was ~20 small array calls per step, ~2,000 steps per attempt of 10
    hugging performers."""
    C, K = bodies.shape
    N = chosen.shape[0]
    m = near.shape[1]
    placed = np.zeros(m, dtype=np.bool_)
    for i in range(N):
        if chosen[i]:
            placed[M[i]] = True
    need = 1 if complete else 2
    total = np.empty(C)
    rsum = np.zeros(C, dtype=np.int64)
    count = np.zeros(C, dtype=np.int64)
    fb = np.zeros(C, dtype=np.bool_)
    bb = np.zeros((C, K), dtype=np.bool_)
    v = np.zeros(K)
    for c in range(C):
        shared = 0
        anyb = False
        clash = False
        cnt = 0
        poss = 0
        sup = 0
        npos = 0
        dif = 0
        for k in range(K):
            b = bodies[c, k]
            j = b if b >= 0 else N + b
            on = b >= 0
            if complete:
                if on and chosen[j]:
                    shared += 1
                on = on and not chosen[j]
            bb[c, k] = on
            v[k] = lerr[j] * (1.0 if on else 0.0)
            if on:
                anyb = True
                clash = clash or blocked[j]
                cnt += links[j]
                poss += possible[j]
                sup += support[j]
                dif += against[j]
                if support[j] > 0:
                    npos += 1
        if K == 8:
            ls = ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7]))
        else:
            ls = 0.0
            for k in range(K):
                ls += v[k]
        free = anyb and not clash
        nb = 0
        for q in range(m):
            if near[c, q] and placed[q]:
                nb += 1
        beside = nb >= need
        count[c] = cnt
        fb[c] = free and beside
        frac = cnt / max(poss, 1)
        ok = free and beside and dif <= sup and not refused[c]
        total[c] = cnt - ls if ok and frac >= link_fraction else -1.0
        if free and npos >= 2:
            rsum[c] = sup + shared
    return total, rsum, count, fb, bb


def _select(
    g: _Graph,
    seed: np.ndarray,
    allowed: np.ndarray,
    bodies: np.ndarray,
    config: BootConfig,
    near: np.ndarray,
    complete: bool = False,
) -> np.ndarray:
    """Greedy consistent set. From the seed nodes, add the allowed node with the most rigid
    links that agree with the set (at least ``min_support``) and no clash; when none is left,
    add the whole body candidate (another segment) best linked to the set through articulated
    pairs within their trained range (at least ``min_links``), and go on."""
    chosen = np.zeros(g.M.size, dtype=bool)
    chosen[seed] = True
    g.rows(seed)
    support = g.agree[seed].sum(axis=0).astype(np.int64)
    against = g.differ[seed].sum(axis=0).astype(np.int64)
    links = g.link[seed].sum(axis=0).astype(np.int64)
    lerr = g.link_err[seed].sum(axis=0)
    possible = g.art[seed].sum(axis=0).astype(np.int64)
    blocked = g.clash[seed].any(axis=0) | chosen | ~allowed
    refused = np.zeros(bodies.shape[0], dtype=bool)  # candidates whose steadiest links fail
    while True:
        # rigid agreement first; among equals, the node more articulated pairs agree with
        # (breaks the near-symmetries of small segments: a wrist bar read either way); every
        # such node step in one numba loop
        _greedy_nodes(
            chosen, support, against, links, lerr, possible, blocked, config.min_support,
            g._done, g.M, g.P, g._dist, *g._tables,
            g.agree, g.clash, g.differ, g.link, g.link_err, g.art,
        )  # fmt: skip
        if bodies.shape[0] == 0:
            return np.flatnonzero(chosen)
        # completing a booted subject, a candidate may share placed markers (the same nodes:
        # a foot body on the placed ankle, whose heel, toe and metatarsal have no other rigid
        # partner placed): its new nodes (``bb``) are what it adds and is scored on, the shared
        # ones count as agreements with the set. A segment joins when most of its articulated
        # pairs to the set are in range (another performer's hand within reach of this one's
        # shoulder is not, of its hips neither; links counted softly, 1 - |d - D| / tolerance
        # each: a symmetric segment read either way, or the left foot read as the right one,
        # has as many links but farther from D), only next to a neighbour in the chain already
        # placed (two of its markers; one when completing: the neighbour's others may be
        # hidden), and not against most of its pairs rigid by A alone (a forearm read on a
        # shoulder and the head: in range of the hips, but off the trained arm-to-chest pairs).
        # A segment whose markers keep their rigid distances to the set (an elbow's to the
        # forearm's) joins first, however far its articulated pairs are from the trained
        # poses: at least ``min_support + 1`` agreements spread over two or more of its markers
        # (``rsum``). Every score in one kernel pass (:func:`_body_scores`).
        total, rsum, count, fb, bb = _body_scores(
            bodies, chosen, blocked, links, lerr, possible, support, against, near, g.M,
            refused, complete, config.link_fraction,
        )  # fmt: skip
        best = int(np.argmax(total))
        if rsum.max() > config.min_support:
            best = int(np.argmax(rsum))
        elif count[best] < config.min_links or total[best] < 0:
            rows = np.where(bb, bodies, -1)
            best = _beside_joint(g, chosen, rows, fb, near) if complete else -1
            if best < 0:
                return np.flatnonzero(chosen)
        elif not _steady_links(g, bodies[best][bb[best]], np.flatnonzero(chosen & near[best][g.M])):
            refused[best] = True
            continue
        b = bodies[best][bb[best]]
        chosen[b] = True
        g.rows(b)
        support += g.agree[b].sum(axis=0)
        against += g.differ[b].sum(axis=0)
        links += g.link[b].sum(axis=0)
        lerr += g.link_err[b].sum(axis=0)
        possible += g.art[b].sum(axis=0)
        blocked |= g.clash[b].any(axis=0)
        blocked[b] = True


def _steady_links(g: _Graph, nodes: np.ndarray, chosen: np.ndarray) -> bool:
    """A segment joining through articulated links: its ``STEADY_LINKS`` articulated pairs to
    the placed markers of its chain neighbours (``chosen``: :func:`_adjacent`) with the least
    trained deviation ``A`` must all be in range. Most pairs in range is not enough: a hugging
    partner's forearm where this performer's hidden upper arm should be is in range of most of
    the shoulder's and hips' pairs, not of the steadiest ones."""
    g.rows(nodes)
    art = g.art[np.ix_(nodes, chosen)]
    if not art.any():
        return True
    a = g.A[g.M[nodes][:, None], g.M[chosen][None, :]]
    a = np.where(art & np.isfinite(a), a, np.inf).ravel()
    steady = np.argsort(a, kind="stable")[:STEADY_LINKS]
    steady = steady[np.isfinite(a[steady])]
    return bool(np.all(g.link[np.ix_(nodes, chosen)].ravel()[steady]))


def _beside_joint(
    g: _Graph, chosen: np.ndarray, bodies: np.ndarray, rows: np.ndarray, near: np.ndarray
) -> int:
    """Completing a booted subject: the body candidate (among ``rows``) whose articulated pairs
    to the placed markers of its chain neighbours are all in range (four or more), best soft
    count first; -1 if none. An arm in a pose the model never saw is far from its trained
    distances to the rest of the body, not from the segment it hangs on."""
    ch = np.flatnonzero(chosen)
    best, best_val = -1, 0.0
    for r in np.flatnonzero(rows):
        nodes = bodies[r][bodies[r] >= 0]
        cn = ch[near[r][g.M[ch]]]
        if cn.size == 0:
            continue
        g.rows(nodes)
        art = g.art[np.ix_(nodes, cn)]
        n_art = int(art.sum())
        n_link = int(g.link[np.ix_(nodes, cn)].sum())
        if n_art < 4 or n_link < n_art:
            continue
        val = n_link - float(g.link_err[np.ix_(nodes, cn)].sum())
        if val > best_val:
            best, best_val = int(r), val
    return best


def _grow(
    tpl: _Template,
    assign: np.ndarray,
    taken: np.ndarray,
    pts: np.ndarray,
    tree: cKDTree,
    config: BootConfig,
) -> None:
    """Markers with no node yet: a free point that keeps the rigid distances (3 or more) to the
    markers placed, and clashes with none of them, joins (trilateration). With two rigid
    partners only, the point must be the only one that also keeps every articulated pair in
    its trained range.

    Own evidence first: a marker joins only when a marker of its own trained body is among
    those placed (``tpl.same``; rigid to it or not: a toe whose only rigid partner of its body
    is the other toe, hidden with it, has the ankle). A pair rigid by ``A`` alone may cross a
    joint that never moved in training (a model trained kneeling, the stream prone: the right
    heel read from the right thigh plate and the pelvis landed on the left thigh). Only when
    that leaves the subject under the boot gate (``min_fraction``) are the other rigid pairs
    let in: a pelvis of two triangles with one marker hidden has no body candidate, so none of
    its markers has a placed partner of its own bodies, and only the trunk can bring it in."""
    # one numba loop (kernels/boot_grow.py; ``tree`` is not needed there: the ball query is
    # a scan of the points; the numpy version is the twin tests/reference.py:grow)
    del tree
    p = np.ascontiguousarray(pts, dtype=np.float64)
    rest = (tpl.D, tpl.tol, tpl.bound, tpl.rigid, tpl.strict, tpl.link)
    _grow_kernel(assign, taken, p, *rest, tpl.same)
    if int((assign >= 0).sum()) < config.boot_markers(tpl.n):
        _grow_kernel(assign, taken, p, *rest, tpl.rigid)  # (every rigid partner is evidence)


def _articulate(
    tpl: _Template,
    assign: np.ndarray,
    taken: np.ndarray,
    pts: np.ndarray,
    hist: np.ndarray,
    tree: cKDTree,
    config: BootConfig,
) -> None:
    """Markers with no rigid evidence (fewer than two rigid partners placed: a Plug-in-Gait
    upper-arm or thigh wand, a heel whose only rigid partner is the ankle, a dance set's hip
    and knee markers): a free point joins when it keeps its distances to the marker's
    ``art_anchors`` steadiest placed partners (least trained ``A``, each at most ``art_a_mm``:
    markers of the same or the next segment) within their trained range (``tol`` for a rigid
    pair, ``D +- (tol_mm + link_sigma A + tol_relative D)`` otherwise), three or more of them,
    in ``constancy`` of the window's samples, no pair beyond its reach, and it is the *only*
    free point that does and no other marker claims it: evidence that is not unique is not
    taken (a ghost beside the elbow, another performer's knee within reach). Repeated while
    markers join (a thigh wand, then the knee's heel)."""
    w = hist.shape[1]
    for _ in range(3):
        have = np.flatnonzero(assign >= 0)
        if have.size < config.art_min_anchors:
            return
        fits: dict[int, list[int]] = {}
        for m in np.flatnonzero(assign < 0):
            a = tpl.A[m, have]
            ok_a = np.isfinite(a) & np.isfinite(tpl.D[m, have]) & (a <= config.art_a_mm)
            if ok_a.sum() < config.art_min_anchors:
                continue
            anc = have[ok_a][np.argsort(a[ok_a], kind="stable")][: config.art_anchors]
            tol = np.where(tpl.rigid[m, anc], tpl.tol[m, anc], tpl.link[m, anc])
            j = anc[0]
            near = np.asarray(
                tree.query_ball_point(pts[assign[j]], tpl.D[m, j] + tol[0]), dtype=np.int64
            )
            near = near[~taken[near]]
            if near.size == 0:
                continue
            d = np.linalg.norm(pts[near][:, None, :] - pts[assign[anc]][None, :, :], axis=2)
            ok = np.all(np.abs(d - tpl.D[m, anc]) <= tol, axis=1)
            # no pair to the rest of the subject beyond its reach
            dall = np.linalg.norm(pts[near][:, None, :] - pts[assign[have]][None, :, :], axis=2)
            ok &= ~np.any(dall - tpl.D[m, have] > tpl.bound[m, have], axis=1)
            for p in near[ok].tolist():
                # the distances hold along the tracks
                dh = np.linalg.norm(hist[p][None] - hist[assign[anc]], axis=2)  # (k, W)
                seen = np.isfinite(dh)
                held = seen & (np.abs(dh - tpl.D[m, anc][:, None]) <= tol[:, None])
                if seen.sum() >= w and held.sum() >= config.constancy * seen.sum():
                    fits.setdefault(int(m), []).append(int(p))
        # a marker with one fitting point that fits no other marker (the elbow's point fits the
        # forearm marker's loose ranges too, and the elbow's own: neither is taken)
        count: dict[int, int] = {}
        for ps in fits.values():
            for p in ps:
                count[p] = count.get(p, 0) + 1
        changed = False
        for marker, ps in fits.items():
            if len(ps) == 1 and count[ps[0]] == 1:
                assign[marker] = ps[0]
                taken[ps[0]] = True
                changed = True
        if not changed:
            return


def _constancy(
    tpl: _Template, assign: np.ndarray, hist: np.ndarray, config: BootConfig
) -> np.ndarray:
    """Drops markers whose rigid pair distances do not hold along the tracks."""
    for _ in range(3):
        have = np.flatnonzero(assign >= 0)
        if have.size < 2:
            return assign
        # per marker, its strict pairs' distances along the tracks seen and off D +- tol
        # (kernels/boot_pairs.py; its numpy twin is tests/reference.py:constancy_counts)
        sub = np.ix_(have, have)
        n_pair, n_bad = _constancy_counts(
            hist, assign[have], tpl.D[sub], tpl.tol[sub], tpl.strict[sub]
        )
        frac_bad = n_bad / np.maximum(n_pair, 1)
        worst = int(np.argmax(frac_bad))
        if frac_bad[worst] <= 1.0 - config.constancy:
            return assign
        drop = frac_bad > max(1.0 - config.constancy, 0.5 * frac_bad[worst])
        assign[have[drop]] = -1
    return assign


def _strict_partners(tpl: _Template, assign: np.ndarray) -> np.ndarray:
    """``(n,)`` per marker, how many placed markers a pair of one trained body ties it to."""
    placed = assign >= 0
    return (tpl.strict & placed[None, :]).sum(axis=1) * placed


def _orphans(tpl: _Template, assign: np.ndarray, had: np.ndarray, movable: np.ndarray) -> None:
    """Unplaces the ``movable`` markers (a completion's new ones) that had strict partners
    (``had``, :func:`_strict_partners` before :func:`_constancy`) and have none left: the body
    candidate that placed them was refuted and nothing else vouches for them. A model's wrist
    triangle read on the other wrist's points lost its radius and ulna to the check and kept
    its hand, alone on the other radius's point, for the labeler to grow the wrong side from
    (kneel from frame 900 through the service, boot results installed late)."""
    while True:
        lost = movable & (had > 0) & (assign >= 0) & (_strict_partners(tpl, assign) == 0)
        if not lost.any():
            return
        assign[lost] = -1


def _score(tpl: _Template, assign: np.ndarray, pts: np.ndarray) -> float:
    """Markers explained, less per marker the mean squared distance error of its rigid pairs
    (in tolerances) and of its articulated pairs (in link tolerances, capped at 1): a leg read
    as the other leg keeps its rigid distances but not its distances to the pelvis."""
    have = np.flatnonzero(assign >= 0)
    if have.size == 0:
        return 0.0
    p = pts[assign[have]]
    d = np.linalg.norm(p[:, None] - p[None, :], axis=2)
    Dm = tpl.D[np.ix_(have, have)]
    rigid = tpl.rigid[np.ix_(have, have)]
    strict = tpl.strict[np.ix_(have, have)]
    e = np.abs(d - Dm) / tpl.tol[np.ix_(have, have)]
    # pairs of one trained body uncapped; pairs rigid by A alone capped at 1 (pose-dependent)
    e = np.where(strict, e, np.minimum(e, 1.0))
    e = np.where(rigid & np.isfinite(e), e, 0.0)
    per = (e**2).sum(axis=1) / np.maximum(rigid.sum(axis=1), 1)
    lt = tpl.link[np.ix_(have, have)]
    art = ~rigid & (lt > 0) & np.isfinite(Dm)
    np.fill_diagonal(art, False)
    le = np.minimum(np.abs(d - Dm) / np.where(art, lt, 1.0), 1.0)
    le = np.where(art, le, 0.0)
    per_l = (le**2).sum(axis=1) / np.maximum(art.sum(axis=1), 1)
    return float(have.size - per.sum() - per_l.sum())


def _local_quads(quads: np.ndarray, bodies: list[list[int]]) -> np.ndarray:
    """Per quadruple: are its four markers inside one trained body, or two bodies sharing a
    marker (a segment, or two beside one joint)?"""
    sets = [set(b) for b in bodies]
    unions = sets + [a | b for i, a in enumerate(sets) for b in sets[i + 1 :] if a & b]
    return np.array([any(set(q.tolist()) <= u for u in unions) for q in quads], dtype=bool)


def _volumes(p: np.ndarray) -> np.ndarray:
    """Signed volumes ``det(p1 - p0, p2 - p0, p3 - p0)`` of quadruples ``p (..., 4, 3)``
    (coincident points give 0 or nan, without a warning)."""
    with np.errstate(all="ignore"):
        return np.linalg.det(p[..., 1:, :] - p[..., :1, :])


def _reversed_thick(det: np.ndarray) -> np.ndarray:
    """Quadruples whose signed volume ``det`` is reversed (negative; the trained sign is
    positive) and thick enough to vote (cube root of ``|det|`` >= ``CHIRAL_MIN_MM``)."""
    return (np.cbrt(np.abs(det)) >= CHIRAL_MIN_MM) & (det < 0)


def _handedness(tpl: _Template, assign: np.ndarray, pts: np.ndarray) -> tuple[int, int, int]:
    """Of the template's chirality quadruples with all four markers placed and a thick
    tetrahedron (cube root of ``|det|`` >= ``CHIRAL_MIN_MM``), how many keep the trained sign,
    how many are reversed, and how many of those are local (one segment or two beside a
    joint, :func:`_local_quads`): a subject read mirrored (left for right) keeps every pair
    distance but reverses these volumes."""
    q = tpl.chirality
    if q.shape[0] == 0:
        return 0, 0, 0
    placed = np.all(assign[q] >= 0, axis=1)
    q, local = q[placed], tpl.chiral_local[placed]
    if q.shape[0] == 0:
        return 0, 0, 0
    det = _volumes(pts[assign[q]])
    thick = np.cbrt(np.abs(det)) >= CHIRAL_MIN_MM
    rev = thick & (det < 0)
    return int(np.sum(thick & (det > 0))), int(rev.sum()), int(np.sum(rev & local))


def _twin_votes(
    tpl: _Template, assign: np.ndarray, hist: np.ndarray
) -> dict[tuple[int, int], list[float]]:
    """Per twin pair ``(i, j)`` with both markers placed: ``[kept, reversed, kept_weight,
    reversed_weight]``, how many of its witnesses with all four markers placed keep their
    trained sign and how many are reversed, and the sums of their ``|normalised volume|``
    (the evidence each gives). A witness is judged
    over the window (``hist (N, W, 3)``) by its normalised volume ``det / (|e1| |e2| |e3|)``
    (scale-free, in [-1, 1]) averaged over the frames where its tetrahedron is thick (cube root
    of ``|det|`` >= ``CHIRAL_MIN_MM``); within ``TWIN_ABSTAIN`` of zero it does not vote: a
    witness across a joint near the pose where it flips (measured on the synthetic arm: the
    two that flipped in an unseen pose were at -0.02 and -0.00, the four right ones at 0.12 to
    0.39) is no evidence either way."""
    w = tpl.twins
    out: dict[tuple[int, int], list[float]] = {}
    if w.shape[0] == 0:
        return out
    use = np.all(assign[w] >= 0, axis=1)
    if not use.any():
        return out
    w = w[use]
    p = hist[assign[w]]  # (q, 4, W, 3)
    e = np.transpose(p[:, 1:] - p[:, :1], (0, 2, 1, 3))  # (q, W, 3, 3)
    with np.errstate(all="ignore"):  # untracked frames, coincident points
        det = np.linalg.det(e)
        unit = det / np.prod(np.linalg.norm(e, axis=3), axis=2)
    thick = np.isfinite(unit) & (np.cbrt(np.abs(det)) >= CHIRAL_MIN_MM)
    n = thick.sum(axis=1)
    mean = np.where(thick, unit, 0.0).sum(axis=1) / np.maximum(n, 1)
    for (i, j), k, v in zip(w[:, :2].tolist(), n, mean, strict=True):
        votes = out.setdefault((i, j), [0, 0, 0.0, 0.0])
        if k and v > TWIN_ABSTAIN:
            votes[0] += 1
            votes[2] += float(v)
        elif k and v < -TWIN_ABSTAIN:
            votes[1] += 1
            votes[3] -= float(v)
    return out


def _twins(
    tpl: _Template,
    assign: np.ndarray,
    pts: np.ndarray,
    hist: np.ndarray,
    movable: np.ndarray | None = None,
) -> None:
    """Twin markers (two of one body whose exchange no trained distance and no chirality
    quadruple tells: a forearm's radius and ulna, ``SubjectTemplate.twin_witnesses``) placed
    the wrong way round are exchanged: when at least ``TWIN_MIN_VOTES`` of the pair's witness
    quadruples (:func:`_twin_votes`) are reversed over the window, their summed evidence is
    more than ``TWIN_RATIO`` times that of the kept ones, and the exchange does not cost the
    subject's distances more than ``EXCHANGE_MARGIN`` (:func:`_pair_error`: the witnesses
    decide only what distances cannot). ``movable``: markers that may be exchanged (both of
    a pair); default all."""
    for (i, j), (_, rev, w_kept, w_rev) in _twin_votes(tpl, assign, hist).items():
        if rev < TWIN_MIN_VOTES or not w_rev > TWIN_RATIO * w_kept:
            continue
        if movable is not None and not (movable[i] and movable[j]):
            continue
        mk = np.array([i, j], dtype=np.int64)
        base = assign.copy()
        base[mk] = -1
        now = _pair_error(tpl, mk, assign[mk], base, pts)
        then = _pair_error(tpl, mk, assign[mk[::-1]], base, pts)
        if then <= now + EXCHANGE_MARGIN:
            assign[i], assign[j] = assign[j], assign[i]


@dataclass
class _Hypothesis:
    template: int
    assign: np.ndarray  # (m,) point index per template marker, -1
    score: float
    rms: float = 0.0  # RMS of |d - D| over its rigid pairs (mm)


def _rms(tpl: _Template, assign: np.ndarray, pts: np.ndarray) -> float:
    """RMS distance error (mm) of a hypothesis over its rigid pairs: how well the template's
    body size and proportions fit (two performers of similar height differ here)."""
    have = np.flatnonzero(assign >= 0)
    p = pts[assign[have]]
    d = np.linalg.norm(p[:, None] - p[None, :], axis=2)
    rig = tpl.strict[np.ix_(have, have)]
    if not rig.any():
        return np.inf
    return float(np.sqrt(np.mean((d - tpl.D[np.ix_(have, have)])[rig] ** 2)))


@dataclass
class _Candidates:
    """Body candidates of one template as graph nodes (``rows``: node indices per candidate,
    -1 padded; ``cm``/``cp``: the same as markers and points)."""

    cands: list[_Candidate]
    g: _Graph
    seeds: list[np.ndarray]
    rows: np.ndarray
    cm: np.ndarray
    cp: np.ndarray
    near: np.ndarray  # (C, m) markers next to each candidate's body (_adjacent)


def _candidates(
    tpl: _Template,
    pts: np.ndarray,
    hist: np.ndarray,
    pairs: _Pairs,
    config: BootConfig,
    fixed: np.ndarray | None = None,
    key: tuple | None = None,
) -> _Candidates | None:
    """Every body candidate of ``tpl`` and their graph; ``fixed`` (a template assignment) adds
    its (marker, point) nodes (as a last candidate row of its own, not a body). ``key``: the
    local point set's key in the open memo (:func:`_local_pairs`), whose body candidates are
    then computed once."""
    cands: list[_Candidate] = []
    mem = _MEMO.get() if key is not None else None
    for bi, body in enumerate(tpl.bodies):
        if fixed is not None and np.all(fixed[body.markers] >= 0):
            # every marker placed: each node of its candidates is a fixed node or clashes with
            # one (a marker on two points), so none can join the completion (:func:`_select`);
            # skipped, they cost nothing (most bodies of a booted subject's extension)
            continue
        found = None if mem is None else mem.cands.get((bi, key))
        if found is None:
            found = _body_candidates(tpl, body, pts, hist, pairs, config)
            if mem is not None:
                mem.cands[(bi, key)] = found
        for c in found:
            c.body = bi  # (read only downstream: a memo's candidates are shared)
            cands.append(c)
    n = pts.shape[0]
    keys = [c.markers * n + c.points for c in cands]
    if fixed is not None:
        m = np.flatnonzero(fixed >= 0)
        keys.append(m * n + fixed[m])
    if not keys or not np.concatenate(keys).size:
        return None
    uniq, inv = np.unique(np.concatenate(keys), return_inverse=True)
    g = _Graph(tpl, uniq // n, uniq % n, pts, pairs.dist)
    bounds = np.cumsum([0] + [k.size for k in keys])
    seeds = [inv[bounds[i] : bounds[i + 1]] for i in range(len(keys))]
    rows = np.full((len(cands), 8), -1, dtype=np.int64)
    cm = np.zeros((len(cands), 8), dtype=np.int64)
    cp = np.full((len(cands), 8), -1, dtype=np.int64)
    for i, c in enumerate(cands):
        rows[i, : c.markers.size] = seeds[i]
        cm[i, : c.markers.size] = c.markers
        cp[i, : c.markers.size] = c.points
    near = tpl.near[[c.body for c in cands]] if cands else np.zeros((0, tpl.n), dtype=bool)
    return _Candidates(cands, g, seeds, rows, cm, cp, near)


def _hypotheses(
    tpl: _Template,
    pts: np.ndarray,
    hist: np.ndarray,
    pairs: _Pairs,
    config: BootConfig,
) -> list[_Hypothesis]:
    """Up to ``max_hypotheses`` disjoint subject hypotheses of one template."""
    cg = _candidates(tpl, pts, hist, pairs, config)
    if cg is None or not cg.cands:
        return []
    n = pts.shape[0]
    cands, g, seeds, padded, cm, cp = cg.cands, cg.g, cg.seeds, cg.rows, cg.cm, cg.cp
    # candidates another body explains better (:func:`_undominated`) neither seed nor join
    dominated = ~_undominated(tpl, cg, pts)
    padded = np.where(dominated[:, None], -1, padded)
    # seeds by support: rigid links of the rest of the graph that agree with the seed body
    support = np.array([g.support[s].sum() for s in seeds])
    order = np.argsort(-support, kind="stable")
    extent = float(np.nanmax(tpl.D)) if np.isfinite(tpl.D).any() else 2000.0
    need = config.boot_markers(tpl.n)
    out: list[_Hypothesis] = []
    claimed = np.zeros(n, dtype=bool)  # points of this template's accepted hypotheses
    used = np.zeros(len(cands), dtype=bool)
    node_pos = pts[g.P]
    tried = 0
    # candidates with the same point set: one body read through its symmetries (a plate of
    # four markers, a leg read as the other leg); each is grown and the best hypothesis kept
    groups: dict[tuple[int, ...], list[int]] = {}
    for i, c in enumerate(cands):
        groups.setdefault(tuple(sorted(c.points.tolist())), []).append(i)
    for ci in order:
        if len(out) >= config.max_hypotheses or tried >= config.max_seeds:
            break
        if used[ci] or dominated[ci] or np.any(claimed[cands[ci].points]):
            continue
        tried += 1
        best: _Hypothesis | None = None
        for cj in groups[tuple(sorted(cands[ci].points.tolist()))][: config.max_symmetries]:
            used[cj] = True
            if dominated[cj]:
                continue
            centre = pts[cands[cj].points].mean(axis=0)
            allowed = ~claimed[g.P] & (np.linalg.norm(node_pos - centre, axis=1) <= extent)
            nodes = _select(g, seeds[cj], allowed, padded, config, cg.near)
            assign = np.full(tpl.n, -1, dtype=np.int64)
            assign[g.M[nodes]] = g.P[nodes]
            h = _Hypothesis(tpl.index, assign, _score(tpl, assign, pts))
            if best is None or h.score > best.score:
                best = h
        if best is not None:
            # the best reading is completed (trilateration) and checked along the tracks
            assign = best.assign
            taken = claimed.copy()
            taken[assign[assign >= 0]] = True
            _grow(tpl, assign, taken, pts, pairs.tree, config)
            assign = _constancy(tpl, assign, hist, config)
            if int((assign >= 0).sum()) < need:
                continue
            # markers without rigid evidence, once the subject stands on its own rigid evidence
            taken = claimed.copy()
            taken[assign[assign >= 0]] = True
            _articulate(tpl, assign, taken, pts, hist, pairs.tree, config)
            _symmetries(tpl, assign, pts, cands, groups)
            _readings(tpl, assign, pts)
            _swap_mirrors(tpl, assign, pts)
            free = _local_search(tpl, assign, pts, claimed, pairs.tree)
            _free_readings(tpl, assign, pts, free, pairs.tree, hist)
            _twins(tpl, assign, pts, hist)
            kept, reversed_, local = _handedness(tpl, assign, pts)
            if local > 0 or reversed_ > CHIRAL_REVERSED * (kept + reversed_):
                # a mirror image (left read for right): every distance fits, the volumes
                # do not; its points stay free for the seeds that read it the right way
                continue
            # a mirror segment placed on one side with nothing to tell the side yet (a foot
            # whose knee is not placed) is not guessed: the extension reads it with the knee
            assign[_one_sided(tpl, assign)] = -1
            if int((assign >= 0).sum()) < need:
                continue
            best = _Hypothesis(tpl.index, assign, _score(tpl, assign, pts), _rms(tpl, assign, pts))
        if best is not None:
            # seeds inside this hypothesis need not be tried again
            used |= np.all((best.assign[cm] == cp) | (cp < 0), axis=1)
            claimed[best.assign[best.assign >= 0]] = True
            out.append(best)
    return out


def _nll(tpl: _Template, rows: np.ndarray, cols: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Negative log-likelihoods of point distances ``d`` for marker pairs ``(rows, cols)``
    (index arrays broadcast against ``d``; 0 where a pair carries no evidence): pairs of one
    trained body Gaussian in standard deviations (``STRICT_SIGMAS`` per tolerance), pairs rigid
    by ``A`` alone and articulated pairs Cauchy in their tolerance (link tolerance for
    articulated ones), each plus ``log`` of its tolerance, which makes readings with different
    markers comparable (a loose articulated pair is weak evidence, a tight rigid one strong).
    The per-pair constants are the template's ``nll_*`` tables (:func:`_nll_tables`)."""
    e = np.abs(d - tpl.D[rows, cols]) / tpl.nll_scale[rows, cols]
    cost = np.where(tpl.nll_gauss[rows, cols], 0.5 * (STRICT_SIGMAS * e) ** 2, np.log1p(e**2))
    cost += tpl.nll_log[rows, cols]
    return np.where(tpl.nll_use[rows, cols] & np.isfinite(cost), cost, 0.0)


def _nll_tables(tpl: _Template) -> None:
    """The per-pair constants of :func:`_nll`: ``nll_scale`` (the pair's tolerance: ``tol`` if
    rigid, the link tolerance if articulated), its log, ``nll_gauss`` (pairs of one trained
    body) and ``nll_use`` (pairs that carry evidence)."""
    art = ~tpl.rigid & (tpl.link > 0) & np.isfinite(tpl.D)
    scale = np.where(tpl.rigid, tpl.tol, np.where(art, tpl.link, 1.0))
    scale = np.where(np.isfinite(scale) & (scale > 0), scale, 1.0)
    tpl.nll_scale = scale
    tpl.nll_log = np.log(scale)
    tpl.nll_gauss = tpl.strict.copy()
    tpl.nll_use = (tpl.rigid | art) & np.isfinite(tpl.D)


def _pair_nll(
    tpl: _Template, ma: np.ndarray, pa: np.ndarray, mb: np.ndarray, pb: np.ndarray, pts: np.ndarray
) -> np.ndarray:
    """``(len(ma), len(mb))`` :func:`_nll` of markers ``ma`` on points ``pa`` against ``mb`` on
    ``pb``."""
    d = np.linalg.norm(pts[pa][:, None, :] - pts[pb][None, :, :], axis=2)
    return _nll(tpl, np.asarray(ma)[:, None], np.asarray(mb)[None, :], d)


def _pair_error(
    tpl: _Template, markers: np.ndarray, points: np.ndarray, assign: np.ndarray, pts: np.ndarray
) -> float:
    """Distance error of ``markers`` placed on ``points`` against the rest of ``assign`` and
    among themselves (:func:`_nll`): pairs of one trained body ``e^2 / 2`` with ``e`` in
    standard deviations (``STRICT_SIGMAS`` per tolerance); every
    other pair (rigid by ``A`` alone, articulated) robustly, ``log(1 + e^2)`` with ``e`` in its
    tolerance (link tolerance for articulated pairs): a pose the model never saw moves them by
    a few tolerances, a mirrored reading (a head plate turned round, a wrist bar read the wrong
    way) by many; a cap would make both look the same. Each pair adds ``log`` of its tolerance.
    The pairs among ``markers`` count too: two readings of the same points may be bodies of
    different tolerances (a wrist bar and its finger marker, or the loose body the trainer made
    of the forearm, wrist and elbow markers on the same three points: scored against the rest
    alone, the loose reading won and shifted a whole arm along its chain)."""
    # one numba loop over the pairs (kernels/boot_pairs.py; its numpy twin is
    # tests/reference.py:pair_error): ~3,600 calls per attempt on 10 hugging performers
    return float(
        _pair_error_kernel(
            tpl.D, tpl.nll_scale, tpl.nll_log, tpl.nll_gauss, tpl.nll_use,
            np.ascontiguousarray(markers, dtype=np.int64),
            np.ascontiguousarray(points, dtype=np.int64),
            np.ascontiguousarray(assign, dtype=np.int64),
            np.ascontiguousarray(pts, dtype=np.float64), STRICT_SIGMAS,
        )
    )  # fmt: skip


def _exchange(tpl: _Template, assign: np.ndarray, pts: np.ndarray, rounds: int = 8) -> None:
    """Pairs of placed markers exchange their points while that lowers the subject's negative
    log-likelihood (:func:`_pair_nll` over all its pairs) by more than ``EXCHANGE_MARGIN``: two
    markers the body candidates placed the wrong way round (a forearm's radius and ulna
    markers, a forefoot's first and fifth metatarsal heads, the ends of a loose body) where the
    rest of the subject tells them apart. The marker set and the point set stay the same; a
    swap changes only the pairs of the two markers with the others (the pair between them keeps
    its distance), so every exchange is scored at once from one ``(k, k, k)`` table.

    The score is not that difference exactly: the "before" side (``S[i, i] + S[q, q]``) also
    counts the pair i-q, twice, and takes the self term off twice, so a pair of markers that
    misfit each other is more willing to exchange. Measured against the exact difference
    (review of 2026-11-29): the exact one gave more wrong labels on the tune takes' ``rate`` and
    ``alone`` boot cells (49k -> 69k, subjects booted 36 -> 35) and the same on the holdout takes,
    so this one stays, named for what it is."""
    for _ in range(rounds):
        have = np.flatnonzero(assign >= 0)
        k = have.size
        if k < 3:
            return
        P = assign[have]
        E = _exchange_table(tpl, have, pts[P])  # i, q, j
        idx = np.arange(k)
        total = E.sum(axis=2)
        # S[i, q]: marker i on point q against every other marker j (j != i, q) on its point
        S = (
            total
            - E[idx[:, None], idx[None, :], idx[:, None]]
            - E[idx[:, None], idx[None, :], idx[None, :]]
        )
        delta = S + S.T - np.diag(S)[:, None] - np.diag(S)[None, :]
        np.fill_diagonal(delta, 0.0)
        i, q = np.unravel_index(int(np.argmin(delta)), delta.shape)
        if not delta[i, q] < -EXCHANGE_MARGIN:
            return
        assign[have[i]], assign[have[q]] = P[q], P[i]


def _relocate(
    tpl: _Template,
    assign: np.ndarray,
    pts: np.ndarray,
    free: np.ndarray,
    tree: cKDTree,
    rounds: int = 8,
) -> None:
    """A placed marker moves to a free point (``free``: points of no subject) while that lowers
    the subject's negative log-likelihood by more than ``EXCHANGE_MARGIN``: a limb read one
    marker along its chain (the elbow's label on the forearm marker, the forearm's on the wrist
    marker, the wrist's point left free) is undone one move at a time, each freeing the point
    the next marker belongs on. A marker is offered the free points within its steadiest placed
    partner's distance (``D + tol``), so the cost stays linear in the subject's markers."""
    for _ in range(rounds):
        have = np.flatnonzero(assign >= 0)
        if have.size < 3:
            return
        P = assign[have]
        rows, cand = [], []
        for i, m in enumerate(have):
            part = have[have != m]
            a = tpl.A[m, part]
            if not np.isfinite(a).any():
                continue
            j = part[int(np.nanargmin(a))]
            near = np.asarray(
                tree.query_ball_point(pts[assign[j]], tpl.D[m, j] + tpl.tol[m, j]), dtype=np.int64
            )
            near = near[free[near]]
            rows += [i] * near.size
            cand += near.tolist()
        if not rows:
            return
        r = np.asarray(rows, dtype=np.int64)
        c = np.asarray(cand, dtype=np.int64)
        # each marker against the others on their points, at its candidate and at its own point
        d_new = np.linalg.norm(pts[c][:, None, :] - pts[P][None, :, :], axis=2)
        d_old = np.linalg.norm(pts[P[r]][:, None, :] - pts[P][None, :, :], axis=2)
        mi, mj = have[r][:, None], have[None, :]
        others = r[:, None] != np.arange(have.size)[None, :]
        new = np.where(others, _nll(tpl, mi, mj, d_new), 0.0).sum(axis=1)
        old = np.where(others, _nll(tpl, mi, mj, d_old), 0.0).sum(axis=1)
        delta = new - old
        b = int(np.argmin(delta))
        if not delta[b] < -EXCHANGE_MARGIN:
            return
        free[P[r[b]]] = True
        free[c[b]] = False
        assign[have[r[b]]] = c[b]


def _local_search(
    tpl: _Template, assign: np.ndarray, pts: np.ndarray, claimed: np.ndarray, tree: cKDTree
) -> np.ndarray:
    """:func:`_exchange` then :func:`_relocate`, again until neither changes the reading (at
    most ``LOCAL_ROUNDS`` times); returns the points still free (not ``claimed``, not placed).
    One pass is not a fixed point: a relocation frees the point an exchange needed. A hugging
    performer's hand triangle (nearly equilateral: its own permutations fit) was read with its
    finger and fifth metacarpal markers exchanged after the relocation moved one of them, 23
    nats less likely than the truth by the wrist links, and kept for the whole take."""
    free = ~claimed
    for _ in range(LOCAL_ROUNDS):
        before = assign.copy()
        _exchange(tpl, assign, pts)
        free = ~claimed
        free[assign[assign >= 0]] = False
        _relocate(tpl, assign, pts, free, tree)
        if np.array_equal(before, assign):
            break
    return free


def _exchange_table(tpl: _Template, have: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """``E[i, q, j]``: :func:`_nll` of marker ``have[i]`` on point ``pos[q]`` against marker
    ``have[j]`` on ``pos[j]``, for every triple at once."""
    d = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=2)[None, :, :]  # (1, q, j)
    return _nll(tpl, have[:, None, None], have[None, None, :], d)


def _mirror_pairs(tpl: _Template) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pairs of disjoint segments (:func:`_segments`, or bodies) of the same size whose trained
    distances
    match under some marker bijection (left and right feet, forearms, thighs): ``(s1, s2)``
    with ``s2`` ordered so that ``s1[i]`` corresponds to ``s2[i]``."""
    out = []
    segs = list(tpl.segments)
    keys = {tuple(x.tolist()) for x in segs}
    for body in tpl.bodies:  # a body inside a larger segment on one side only (a knee's)
        if tuple(sorted(body.markers.tolist())) not in keys:
            segs.append(np.sort(body.markers))
            keys.add(tuple(segs[-1].tolist()))
    for a in range(len(segs)):
        for b in range(a + 1, len(segs)):
            s1, s2 = segs[a], segs[b]
            if s1.size != s2.size or s1.size > 5 or np.intersect1d(s1, s2).size:
                continue
            D1 = tpl.D[np.ix_(s1, s1)]
            t1 = tpl.tol[np.ix_(s1, s1)]
            for perm in itertools.permutations(range(s2.size)):
                s2p = s2[list(perm)]
                D2 = tpl.D[np.ix_(s2p, s2p)]
                ok = np.isfinite(D1) & np.isfinite(D2)
                if ok.sum() > s1.size and np.all(np.abs(D1 - D2)[ok] <= t1[ok]):
                    out.append((s1, s2p))
                    break
    return out


def _sided(
    mirrors: list[tuple[np.ndarray, np.ndarray]], names: list[str]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The pairs of ``mirrors`` whose markers correspond as named left and right twins: a
    shape match alone also pairs a shin plate with a head's markers."""
    twins = {frozenset(p) for p in side_pairs(names)}
    return [
        (s1, s2)
        for s1, s2 in mirrors
        if all(frozenset((int(a), int(b))) in twins for a, b in zip(s1, s2, strict=True))
    ]


def _mirror_exchange(assign: np.ndarray, s1: np.ndarray, s2: np.ndarray) -> tuple | None:
    """The exchange of mirror segments ``s1``/``s2`` in ``assign``: ``(union, placed, swapped,
    base, other)`` - their markers, those placed, the exchanged reading, the reading without
    them, and those placed in the exchanged one; None when fewer than three are placed."""
    union = np.concatenate([s1, s2])
    placed = union[assign[union] >= 0]
    if placed.size < 3:
        return None
    swapped = assign.copy()
    swapped[s1], swapped[s2] = assign[s2], assign[s1]
    base = assign.copy()
    base[union] = -1
    return union, placed, swapped, base, union[swapped[union] >= 0]


def _swap_mirrors(tpl: _Template, assign: np.ndarray, pts: np.ndarray) -> None:
    """Mirror segments (:func:`_mirror_pairs`) read on each other's points (a dancer's left
    foot placed as the right one and the right as the left: their own distances cannot tell)
    are exchanged when the exchange fits the rest of the subject better by more than
    ``EXCHANGE_MARGIN``; a segment placed on one side only moves to the other side's markers
    when those are free."""
    for s1, s2 in tpl.mirrors:
        ex = _mirror_exchange(assign, s1, s2)
        if ex is None:
            continue
        union, placed, swapped, base, other = ex
        now = _pair_error(tpl, placed, assign[placed], base, pts)
        then = _pair_error(tpl, other, swapped[other], base, pts)
        if then < now - EXCHANGE_MARGIN:
            assign[union] = swapped[union]


def _symmetries(
    tpl: _Template,
    assign: np.ndarray,
    pts: np.ndarray,
    cands: list[_Candidate],
    groups: dict[tuple[int, ...], list[int]],
) -> None:
    """Bodies read through a symmetry (a head's four markers, a wrist bar): among the body
    candidates on the same points (whose markers are free or theirs), keeps the reading whose
    distances to the rest of the subject fit best (its own distances cannot tell them apart)."""
    marker_of = {int(p): int(m) for m, p in enumerate(assign) if p >= 0}
    for key, idx in groups.items():
        if len(idx) < 2 or any(p not in marker_of for p in key):
            continue
        current = np.array([marker_of[p] for p in key])
        free = assign < 0
        free[current] = True
        readings = [cands[i] for i in idx if np.all(free[cands[i].markers])]
        if not readings:
            continue
        base = assign.copy()
        base[current] = -1
        now = _pair_error(tpl, current, assign[current], base, pts)
        errs = [_pair_error(tpl, c.markers, c.points, base, pts) for c in readings]
        if min(errs) >= now:
            continue
        best = readings[int(np.argmin(errs))]
        assign[current] = -1
        assign[best.markers] = best.points
        for m, p in zip(best.markers.tolist(), best.points.tolist(), strict=True):
            marker_of[p] = m


def _adjacent(tpl: _Template) -> np.ndarray:
    """``(bodies, m)``: per body the markers of its neighbours in the chain. Two bodies are
    neighbours when they share a marker, or when their steadiest pair of markers (least trained
    deviation ``A``: two markers beside one joint) is within ``NEIGHBOUR`` times the body's
    steadiest pair to any body it shares no marker with (a shin and its foot, a forearm and
    its hand, a thigh plate and a shank plate; not a pelvis and a foot, nor a hand and the chest
    it rested on in the training frames); then a minimum spanning tree over those deviations
    joins what is still apart, so the chain reaches every body. A segment joins a hypothesis
    through articulated pairs only next to a neighbour already placed (:func:`_select`):
    another performer's foot near this one's hips does not."""
    nb = len(tpl.bodies)
    out = np.zeros((nb, tpl.n), dtype=bool)
    steady = np.full((nb, nb), np.inf)
    share = np.zeros((nb, nb), dtype=bool)
    for i, bi in enumerate(tpl.bodies):
        for j, bj in enumerate(tpl.bodies):
            share[i, j] = i == j or np.intersect1d(bi.markers, bj.markers).size > 0
            cross = tpl.A[np.ix_(bi.markers, bj.markers)]
            if not share[i, j] and np.isfinite(cross).any():
                steady[i, j] = float(np.nanmin(cross))
    adj = share.copy()
    for i in range(nb):
        best = steady[i][np.isfinite(steady[i])]
        if best.size:
            adj[i] |= steady[i] <= NEIGHBOUR * float(best.min())
    adj |= adj.T
    if nb:
        # edges already there cost ~0, so the tree only adds the cheapest links between parts
        w = np.where(adj, 1e-9, np.where(np.isfinite(steady), steady + 1.0, 0.0))
        np.fill_diagonal(w, 0.0)  # 0: no edge for scipy
        tree = minimum_spanning_tree(w).toarray() > 0
        adj |= tree | tree.T
    np.fill_diagonal(adj, False)
    for i, bi in enumerate(tpl.bodies):
        for k in np.flatnonzero(adj[i]):
            out[i, tpl.bodies[k].markers] = True
        out[i, bi.markers] = False
    return out


def _segments(tpl: _Template) -> list[np.ndarray]:
    """Marker groups whose readings are checked by :func:`_readings`: each body with the
    bodies sharing two or more markers with it (a head split into 3-marker bodies is one
    group), at most ``6`` markers."""
    out: list[np.ndarray] = []
    seen: set[tuple[int, ...]] = set()
    for body in tpl.bodies:
        group = set(body.markers.tolist())
        for other in tpl.bodies:
            if len(group & set(other.markers.tolist())) >= 2:
                group |= set(other.markers.tolist())
        key = tuple(sorted(group))
        if len(key) <= 6 and key not in seen:
            seen.add(key)
            out.append(np.array(key, dtype=np.int64))
    return out


def _segment_readings(
    tpl: _Template, seg: np.ndarray, assign: np.ndarray, pts: np.ndarray
) -> tuple[np.ndarray, list[np.ndarray]]:
    """The placed markers of a segment and its other readings: injective maps of their points
    to the segment's markers (free or its own) that keep the distances of one trained body
    (depth-first, each point's marker checked against those already given). Two to four placed
    markers only: reading five- and six-marker segments again (a hand with its wrist bar) turned
    correct readings on the walk test stream (0.90 -> 0.89 correct)."""
    placed = seg[assign[seg] >= 0]
    if placed.size < 2 or placed.size > 4:
        return placed, []
    points = assign[placed]
    options = np.concatenate([placed, seg[assign[seg] < 0]])
    d = np.linalg.norm(pts[points][:, None] - pts[points][None, :], axis=2)
    oo = np.ix_(options, options)
    strict, D, tol = tpl.strict[oo], tpl.D[oo], tpl.tol[oo]
    # point k on option marker m and point j on option marker c keep the pair (m, c)
    fits = {
        (k, j): ~strict | (np.abs(d[k, j] - D) <= tol) for k in range(placed.size) for j in range(k)
    }
    maps = _injective_maps(placed.size, options.size, fits) or []
    return placed, [mk for mk in (options[m] for m in maps) if not np.array_equal(mk, placed)]


def _injective_maps(
    k: int, n: int, fits: dict[tuple[int, int], np.ndarray], limit: int | None = None
) -> list[np.ndarray] | None:
    """Every injective map of items ``0..k-1`` to options ``0..n-1`` (depth-first, options in
    order) such that for each pair ``(a, b)``, ``b < a``, in ``fits`` item ``a``'s option ``i``
    and item ``b``'s option ``j`` have ``fits[a, b][i, j]``: the readings of a segment that
    keep one trained body's distances (:func:`_segment_readings` maps points to markers,
    :func:`_maps_onto` markers to points). ``None`` when there are more than ``limit``."""
    maps: list[np.ndarray] = []
    chosen: list[int] = []

    def place(a: int) -> None:
        if limit is not None and len(maps) > limit:
            return
        if a == k:
            maps.append(np.array(chosen, dtype=np.int64))
            return
        ok = np.ones(n, dtype=bool)
        ok[chosen] = False
        for b, c in enumerate(chosen):
            f = fits.get((a, b))
            if f is not None:
                ok &= f[:, c]
        for i in np.flatnonzero(ok).tolist():
            chosen.append(i)
            place(a + 1)
            chosen.pop()

    place(0)
    return None if limit is not None and len(maps) > limit else maps


def _readings(
    tpl: _Template, assign: np.ndarray, pts: np.ndarray, movable: np.ndarray | None = None
) -> None:
    """Every segment's points are read again: among the injective maps of its placed points to
    the segment's markers (free or its own) that keep the rigid distances, the map whose
    distances to the rest of the subject fit best is kept. A symmetric segment (a head's four
    markers with one hidden, a wrist bar) may have been placed mirrored by a body candidate
    that saw only part of it; its own distances cannot tell, the rest of the body can. Two
    adjacent segments (closer to each other than their own size: a wrist bar and the hand)
    are then read again together: a whole forearm and hand placed mirrored fit worse flipped
    one segment at a time than as they are. ``movable``: markers that may be read again (a
    segment with another placed marker is left as it is); default all."""
    ok = np.ones(tpl.n, dtype=bool) if movable is None else movable
    segs = [seg for seg in tpl.segments if np.all(ok[seg[assign[seg] >= 0]])]
    for seg in segs:
        placed, options = _segment_readings(tpl, seg, assign, pts)
        if not options:
            continue
        _reread(tpl, placed, options, assign, pts)
    reads = [(seg, *_segment_readings(tpl, seg, assign, pts)) for seg in segs]
    reads = [r for r in reads if r[2]]
    for i in range(len(reads)):
        for j in range(i + 1, len(reads)):
            (s1, p1, o1), (s2, p2, o2) = reads[i], reads[j]
            size = max(np.nanmax(tpl.D[np.ix_(s1, s1)]), np.nanmax(tpl.D[np.ix_(s2, s2)]))
            if not np.nanmin(tpl.D[np.ix_(s1, s2)]) <= size:
                continue
            if np.intersect1d(s1, s2).size:
                continue  # segments sharing a marker read together: hug 5 0.48 -> 0.34 correct
            placed = np.concatenate([p1, p2])
            if np.any(assign[placed] < 0):
                continue  # changed by an earlier joint reading
            joint = [  # one of the two may keep its reading
                mk
                for m1 in [p1, *o1]
                for m2 in [p2, *o2]
                if not (m1 is p1 and m2 is p2)
                and np.unique(mk := np.concatenate([m1, m2])).size == mk.size
            ]
            _reread(tpl, placed, joint, assign, pts)


def _reread(
    tpl: _Template, placed: np.ndarray, options: list, assign: np.ndarray, pts: np.ndarray
) -> None:
    """Moves the points of markers ``placed`` to the reading among ``options`` (marker arrays
    of the same length) whose distances to the rest of ``assign`` fit best, if one fits better
    than the current reading (:func:`_pair_error`)."""
    points = assign[placed]
    base = assign.copy()
    base[placed] = -1
    best, best_err = None, _pair_error(tpl, placed, points, base, pts)
    for mk in options:
        err = _pair_error(tpl, mk, points, base, pts)
        if err < best_err:
            best, best_err = mk, err
    if best is not None:
        assign[placed] = -1
        assign[best] = points


def _complete(
    tpl: _Template,
    assign: np.ndarray,
    pts: np.ndarray,
    hist: np.ndarray,
    taken: np.ndarray,
    config: BootConfig,
    reread: bool = False,
    exchange: bool = False,
    partial: bool = False,
) -> np.ndarray:
    """Adds markers to a placed subject ``assign`` from free points near it: body candidates
    (other segments, linked through articulated pairs) and trilateration. Markers already
    placed stay; new ones must pass the distance constancy along the tracks, keep a strict
    partner when they had one (:func:`_orphans`) and have no other free point fit their
    placed strict partners as well (:func:`_ambiguous`). With ``reread``,
    a completion refused for a reversed chirality quadruple may read the new markers'
    segments again, moving placed markers (:func:`_chiral_reread`); with ``exchange`` as
    well, when that finds nothing, two placed markers of the reversed quadruples may exchange
    their points on the window's evidence (:func:`_chiral_exchange`). With ``partial`` (and
    no ``reread``), a completion refused that way keeps the new markers of the segments that
    reverse nothing (:func:`_without_reversed`) instead of none."""
    have = np.flatnonzero(assign >= 0)
    if have.size == 0:
        return assign
    centre = pts[assign[have]].mean(axis=0)
    own = np.zeros(pts.shape[0], dtype=bool)
    own[assign[have]] = True
    local = np.flatnonzero((np.linalg.norm(pts - centre, axis=1) <= tpl.extent) & (~taken | own))
    if local.size < 3:
        return assign
    back = np.full(pts.shape[0], -1, dtype=np.int64)
    back[local] = np.arange(local.size)
    lp, lh = pts[local], hist[local]
    fixed = np.where(assign >= 0, back[np.maximum(assign, 0)], -1)
    pairs, key = _local_pairs(tpl, pts, hist, local)
    cg = _candidates(tpl, lp, lh, pairs, config, fixed, key)
    out = assign.copy()
    if cg is not None:
        keep = _undominated(tpl, cg, lp)
        nodes = _select(
            cg.g,
            cg.seeds[-1],
            np.ones(cg.g.M.size, dtype=bool),
            cg.rows[keep],
            config,
            cg.near[keep],
            True,
        )
        la = np.full(tpl.n, -1, dtype=np.int64)
        la[cg.g.M[nodes]] = cg.g.P[nodes]
    else:
        la = fixed.copy()
    ltaken = np.zeros(local.size, dtype=bool)
    ltaken[la[la >= 0]] = True
    ltree = cKDTree(lp)
    _grow(tpl, la, ltaken, lp, ltree, config)
    la[fixed >= 0] = fixed[fixed >= 0]
    ltaken[la[la >= 0]] = True
    _articulate(tpl, la, ltaken, lp, lh, ltree, config)
    had = _strict_partners(tpl, la)
    checked = _constancy(tpl, la.copy(), lh, config)
    fresh = (fixed < 0) & (la >= 0) & (checked == la)
    la = np.where(fresh | (fixed >= 0), la, -1)
    _orphans(tpl, la, had, fresh)
    fresh = (fixed < 0) & (la >= 0)
    # the new markers' segments read again (a hidden forearm and hand that appear mirrored)
    _readings(tpl, la, lp, movable=fresh)
    _twins(tpl, la, lp, lh, movable=fresh)
    fresh = (fixed < 0) & (la >= 0)
    out[fresh] = local[la[fresh]]
    # one point per marker and one marker per point
    pts_used = out[out >= 0]
    if np.unique(pts_used).size != pts_used.size:
        return assign
    # no thick chirality quadruple with a new marker reversed (a leg completed mirrored), and
    # a new mirror segment with nothing to tell its side yet is not guessed (:func:`_one_sided`)
    _drop_one_sided(tpl, assign, out)
    out[_twin_fits_better(tpl, assign, out, hist)] = -1
    # (after the side tests: a segment read whole on one side is judged whole)
    out[_ambiguous(tpl, la, lh, fresh & (out >= 0), config)] = -1
    new = np.flatnonzero(out != assign)
    if new.size and _fill_reversed(tpl, assign, pts, new[None], out[new][None])[0]:
        if not reread:
            return _without_reversed(tpl, assign, out, pts) if partial else assign
        got = _chiral_reread(tpl, assign, out, new, pts)
        if got is assign and exchange:
            got = _chiral_exchange(tpl, assign, out, new, pts, hist)
        return got
    return out


def _ambiguous(
    tpl: _Template, la: np.ndarray, lh: np.ndarray, fresh: np.ndarray, config: BootConfig
) -> np.ndarray:
    """``(n,)`` bool: the new markers (``fresh``) of reading ``la`` whose placed strict
    partners another unused point (``lh (L, W, 3)``, the local tracks) fits as well: each of
    those pairs within its tolerance in a ``config.constancy`` share of the frames both are
    tracked. Nothing tells which of the two points the marker is on. A forearm plate's two
    distal markers placed, the radius went on the plate's proximal point, 73 and 55 mm from
    them against 83 +- 10 and 52 +- 17 trained, as well as on its own; the labeler then grew
    the wrist onto the plate (kneel from frame 900, boot results 5-80 frames late)."""
    out = np.zeros(tpl.n, dtype=bool)
    placed = la >= 0
    unused = np.ones(lh.shape[0], dtype=bool)
    unused[la[placed]] = False
    alt = np.flatnonzero(unused)
    if alt.size == 0:
        return out
    for m in np.flatnonzero(fresh):
        partners = np.flatnonzero(tpl.strict[m] & placed)
        if partners.size == 0:
            continue
        # (A, P, W) distances from each unused point to each partner's point along the window
        d = np.linalg.norm(lh[alt][:, None] - lh[la[partners]][None], axis=3)
        seen = np.isfinite(d)
        off = np.abs(d - tpl.D[m, partners][None, :, None])
        within = seen & (off <= tpl.tol[m, partners][None, :, None])
        share = within.sum(axis=2) / np.maximum(seen.sum(axis=2), 1)
        fits = np.all((share >= config.constancy) & seen.any(axis=2), axis=1)
        out[m] = bool(fits.any())
    return out


def _undominated(tpl: _Template, cg: _Candidates, pts: np.ndarray) -> np.ndarray:
    """``(C,)`` bool: the body candidates of ``cg`` that no candidate of another body explains
    better. Candidate ``c`` is dominated by a candidate ``o`` of another body on a strict
    superset of its points when ``o``'s reading of all its points (:func:`_nll` of its pairs)
    is more likely, by ``DOMINATED_MARGIN``, than ``c``'s reading of its own points with each
    pair that only ``o`` explains taken as unrelated to the body (a distance anywhere up to
    the size of ``o``'s body, ``log`` of that size each). A loose body of three markers (a
    wrist, ulna and hand triangle, an acromion with two upper-arm markers: trained
    tolerances of 10-20 mm) fits three points of a rigid plate of another segment; the plate
    fits all four of them within a millimetre, and the fourth point's three distances are
    what a chance placement would not hold. Without it, the kneeling performer booted from a
    model of other frames had both wrist triangles read on the upper-arm plates (and the arms
    unlabeled) for the whole take, through the service as offline."""
    cands = cg.cands
    keep = np.ones(len(cands), dtype=bool)
    if len(cands) < 2:
        return keep
    holding: dict[int, set[int]] = {}
    for i, c in enumerate(cands):
        for p in c.points.tolist():
            holding.setdefault(p, set()).add(i)
    own: dict[int, float] = {}
    size: dict[int, float] = {}
    alone = np.full(tpl.n, -1, dtype=np.int64)  # (a reading's own pairs only: _pair_error)

    def cost(c: _Candidate) -> float:
        return _pair_error(tpl, c.markers, c.points, alone, pts)

    def log_size(body: int) -> float:
        if body not in size:
            bm = tpl.bodies[body].markers
            d = tpl.D[np.ix_(bm, bm)]
            size[body] = float(np.log(max(float(np.max(d[np.isfinite(d)], initial=1.0)), 1.0)))
        return size[body]

    for i, c in enumerate(cands):
        ni = c.points.size
        for j in set.intersection(*(holding[p] for p in c.points.tolist())):
            o = cands[j]
            if o.body == c.body or o.points.size <= ni:
                continue
            if i not in own:
                own[i] = cost(c)
            if j not in own:
                own[j] = cost(o)
            extra = o.points.size * (o.points.size - 1) // 2 - ni * (ni - 1) // 2
            if own[i] + extra * log_size(o.body) - own[j] > DOMINATED_MARGIN:
                keep[i] = False
                break
    return keep


def _without_reversed(
    tpl: _Template, assign: np.ndarray, out: np.ndarray, pts: np.ndarray
) -> np.ndarray:
    """A completion ``out`` of ``assign`` that reverses a thick chirality quadruple, without
    the new markers of the segments (:func:`_segments`; a marker in none alone) holding a new
    marker of a reversed quadruple, until none is reversed: the mirrored part of a completion
    is refused, the rest of it (another limb) kept. Without the refusal being per segment,
    one arm completed onto a partner's point refused the whole completion, and with it the
    subject's own foot that a hugging partner's boot had taken as its other foot (a mirror
    image, three markers: no handedness): :meth:`Booter._reclaim` never saw it, and the two
    performers' feet stayed exchanged for the rest of the take (hug5 reboot, 8 s)."""
    out = out.copy()
    q = tpl.chirality
    for _ in range(tpl.n):
        fresh = (out >= 0) & (out != assign)
        new = np.flatnonzero(fresh)
        if new.size == 0:
            break
        bad_q = q[_reversed_quads(q, out, fresh, pts)]
        if bad_q.shape[0] == 0:
            break
        bad = np.intersect1d(bad_q.ravel(), new)
        drop = set(bad.tolist())
        for seg in tpl.segments:
            if np.isin(seg, bad).any():
                drop.update(np.intersect1d(seg, new).tolist())
        idx = np.fromiter(drop, dtype=np.int64)
        out[idx] = assign[idx]
    # (a mirror segment whose side the dropped markers told is not guessed: _one_sided)
    _drop_one_sided(tpl, assign, out)
    return out


def _twin_fits_better(
    tpl: _Template, assign: np.ndarray, out: np.ndarray, hist: np.ndarray
) -> np.ndarray:
    """The markers new in ``out`` (not placed in ``assign``) that do not fit their point
    better than their named twin on the other side (``tpl.twin``), placed in neither, would
    against the markers ``assign`` placed: by ``EXCHANGE_MARGIN`` (:func:`_evidence`) in the
    median of the window frames (``hist (N, W, 3)``) that track that point and every placed
    marker. Side needs evidence for it, not only none against it: a left forearm marker
    placed by its articulated ranges alone on the right ulna's point (its twin fitted there
    no better: neither is that point's marker) was taken by the labeler's re-acquisition of
    the left forearm body, which then read the whole right forearm plate as the left one.
    A forearm plate outside every trained body has no mirror segment (:func:`_mirror_pairs`):
    on a kneeling performer whose left arm was not yet placed, the completion put a left
    forearm marker on the right forearm's point, next to the placed right upper arm (its twin
    fits there: 2-3 tolerances better), and the left plate was then read onto the right one
    for the whole take, the performer booted and online. Such a marker waits for its side's
    evidence instead. Markers of mirror segments are left to the segments' own tests
    (``tpl.twin`` is -1 for them): a single marker of a foot judged alone against a body in a
    pose the model never saw favoured the other foot, and a foot read on a hand at boot kept
    it (the release that puts the foot back was refused)."""
    new = np.flatnonzero((out >= 0) & (assign < 0))
    if new.size == 0 or tpl.twin.size == 0:
        return new[:0]
    tw = tpl.twin[new]
    new = new[(tw >= 0) & (out[np.maximum(tw, 0)] < 0)]
    if new.size == 0:
        return new
    have = np.flatnonzero(assign >= 0)
    seen = np.all(np.isfinite(hist[assign[have], :, 0]), axis=0)
    drop = []
    for m in new.tolist():
        t = int(tpl.twin[m])
        p = int(out[m])
        frames = np.flatnonzero(seen & np.isfinite(hist[p, :, 0]))
        if frames.size == 0:
            continue
        own, alt = assign.copy(), assign.copy()
        own[m] = alt[t] = p
        mk, tk, pp = np.array([m]), np.array([t]), np.array([p])
        gain = [
            _evidence(tpl, mk, pp, own, hist[:, f]) - _evidence(tpl, tk, pp, alt, hist[:, f])
            for f in frames
        ]
        if np.median(gain) > -EXCHANGE_MARGIN:
            drop.append(m)
    return np.asarray(drop, dtype=np.int64)


def _changed_reversed(tpl: _Template, assign: np.ndarray, out: np.ndarray, pts: np.ndarray) -> bool:
    """Does the reading ``out`` of ``assign`` reverse a thick chirality quadruple holding a
    marker it places on another point (:func:`_fill_reversed`)?"""
    changed = np.flatnonzero((out >= 0) & (out != assign))
    if changed.size == 0:
        return False
    base = out.copy()
    base[changed] = -1
    return bool(_fill_reversed(tpl, base, pts, changed[None], out[changed][None])[0])


def _held(tpl: _Template, out: np.ndarray, m: int, old: np.ndarray, pts: np.ndarray) -> int:
    """How many pairs of one trained body (``strict``) tie marker ``m`` of ``out`` to the
    markers ``old`` placed before, within their tolerance."""
    o = np.flatnonzero(old & (out >= 0) & tpl.strict[m])
    o = o[o != m]
    if out[m] < 0 or o.size == 0:
        return 0
    d = np.linalg.norm(pts[out[o]] - pts[out[m]], axis=1)
    return int(np.count_nonzero(np.abs(d - tpl.D[m, o]) <= tpl.tol[m, o]))


def _chiral_reread(
    tpl: _Template, assign: np.ndarray, out: np.ndarray, new: np.ndarray, pts: np.ndarray
) -> np.ndarray:
    """A completion ``out`` of ``assign`` refused because a new marker reverses a thick
    chirality quadruple (:func:`_complete`) says, when the new marker is where it should be,
    that the markers placed beside it are a mirror reading: a plate of four markers symmetric
    about the body's plane (a pelvis, ASIS and PSIS left and right) booted with one marker
    hidden is three markers with no handedness, read left for right as well as right; every
    distance fits, and the fourth marker, when it shows, can only join mirrored too. So each
    segment (:func:`_segments`) holding a new marker and an old one is read again on its
    points (:func:`_segment_readings`: the maps that keep the distances of one trained body);
    the reading that reverses no thick quadruple with a marker it moves, keeps every new
    marker placed and fits the rest of the subject within ``EXCHANGE_MARGIN`` of the refused
    one (a mirror keeps every distance), is taken, the lowest :func:`_pair_error` first. Only
    when each new marker of the segment is tied to the markers placed before by more than
    ``WEAK_SUPPORT`` pairs of one trained body (:func:`_held`): the new marker is then where
    the old reading says, and the side is what is wrong; a new marker tied by one pair may be
    on the wrong point itself (a hand marker on its neighbour's in the labeled start of
    tune11: reading the wrist segment again there moved four right labels). Returns
    ``assign`` when none is found (nothing placed, nothing moved)."""
    old = assign >= 0
    for seg in tpl.segments:
        if not np.isin(new, seg).any() or not np.any(old[seg]):
            continue
        mine = new[np.isin(new, seg)]
        if any(_held(tpl, out, int(m), old, pts) <= WEAK_SUPPORT for m in mine):
            # a new marker weakly tied to the placed ones may itself be on the wrong point
            # (a hand marker on its neighbour's, tune11 labeled start): not a mirror
            continue
        placed, options = _segment_readings(tpl, seg, out, pts)
        if not options:
            continue
        points = out[placed]
        base = out.copy()
        base[placed] = -1
        now = _pair_error(tpl, placed, points, base, pts)
        best, best_err = None, math.inf
        for mk in options:
            err = _pair_error(tpl, mk, points, base, pts)
            if err > now + EXCHANGE_MARGIN or err >= best_err:
                continue
            alt = base.copy()
            alt[mk] = points
            if np.any(alt[new] < 0) or _changed_reversed(tpl, assign, alt, pts):
                continue
            best, best_err = alt, err
        if best is not None:
            return best
    return assign


def _chiral_exchange(
    tpl: _Template,
    assign: np.ndarray,
    out: np.ndarray,
    new: np.ndarray,
    pts: np.ndarray,
    hist: np.ndarray,
) -> np.ndarray:
    """A completion ``out`` of ``assign`` refused because its new markers ``new`` reverse a
    thick chirality quadruple, and not a mirror of their segment (:func:`_chiral_reread`: the
    new markers are tied to the placed ones by ``WEAK_SUPPORT`` pairs or fewer), may say that
    two markers placed before, in a reversed quadruple, sit on each other's points: a hand
    triangle nearly isosceles (the tennis model's ``RFIN RWRA RWRB``, ``D`` 102.7 and 99.6 mm)
    booted with its finger and outer wrist exchanged keeps every distance among the placed
    markers, and the forearm and elbow markers, the only evidence, are refused at every
    extension because their quadruple with the hand is reversed. Each placed marker ``a`` of
    a reversed quadruple and each placed marker ``b`` in one trained body with it
    (``strict``; the other member of the exchange need not be in the quadruple) are exchanged
    in the completion when, over the window frames that track both points (at least half the
    window, ``hist (N, W, 3)``):

    - with the completion's markers placed, the exchange lowers the subject's :func:`_nll` of
      the two markers' pairs by more than ``EXCHANGE_MARGIN`` in ``WINDOW_EXCHANGE_SHARE`` of
      the frames and by ``WINDOW_EXCHANGE_NATS`` in the median (the new markers tell);
    - without them (``assign`` alone) it neither costs more than ``EXCHANGE_MARGIN`` nor gains
      more than ``WINDOW_EXCHANGE_NATS`` in the median: the markers placed before cannot tell
      the two readings apart (a reading they hold is not overturned by markers added from
      free points, and one they contradict is :func:`_window_exchange`'s);
    - with the exchange, no thick chirality quadruple with a new or moved marker is reversed,
      and neither moved marker is doubtful in the last frame (:func:`_still_doubtful`).

    The best such exchange (largest median gain) is taken. Returns ``out`` with it, or
    ``assign`` (nothing placed, nothing moved)."""
    q = tpl.chirality
    if q.shape[0] == 0:
        return assign
    fresh = np.zeros(tpl.n, dtype=bool)
    fresh[new] = True
    use = np.all(out[q] >= 0, axis=1) & np.any(fresh[q], axis=1)
    if not use.any():
        return assign
    qu = q[use]
    rev = qu[_reversed_thick(_volumes(pts[out[qu]]))]
    olds = np.unique(rev[~fresh[rev]])
    placed = (assign >= 0) & ~fresh
    pairs = sorted(
        {
            (min(a, b), max(a, b))
            for a in olds.tolist()
            for b in np.flatnonzero(placed & tpl.strict[a]).tolist()
            if b != a
        }
    )
    w = hist.shape[1]
    best, best_gain = assign, -math.inf
    for a, b in pairs:
        alt = out.copy()
        alt[a], alt[b] = out[b], out[a]
        moved = np.concatenate([new, [a, b]])
        base = alt.copy()
        base[moved] = -1
        if _fill_reversed(tpl, base, pts, moved[None], alt[moved][None])[0]:
            continue
        both = np.isfinite(hist[out[a], :, 0]) & np.isfinite(hist[out[b], :, 0])
        if int(both.sum()) < max(2, w // 2):
            continue
        with_new = _window_swap_gain(tpl, out, a, b, hist)[both]
        if np.mean(with_new > EXCHANGE_MARGIN) < WINDOW_EXCHANGE_SHARE:
            continue
        gain = float(np.median(with_new))
        if gain <= WINDOW_EXCHANGE_NATS or gain <= best_gain:
            continue
        alone = float(np.median(_window_swap_gain(tpl, assign, a, b, hist)[both]))
        if not -EXCHANGE_MARGIN <= alone <= WINDOW_EXCHANGE_NATS:
            continue
        if _still_doubtful(tpl, alt, hist, a, b):
            continue
        best, best_gain = alt, gain
    return best


def _window_swap_gain(
    tpl: _Template, assign: np.ndarray, a: int, b: int, hist: np.ndarray
) -> np.ndarray:
    """``(W,)`` per window frame: how much lower the :func:`_nll` of the pairs of placed
    markers ``a`` and ``b`` with the other placed markers of ``assign`` is with their points
    exchanged (the pair between them keeps its distance; an untracked point's pairs count 0)."""
    rest = np.flatnonzero(assign >= 0)
    rest = rest[(rest != a) & (rest != b)]
    H = hist[assign[rest]]  # (r, W, 3)
    pa, pb = hist[assign[a]], hist[assign[b]]  # (W, 3)
    da = np.linalg.norm(H - pa[None], axis=2)  # (r, W)
    db = np.linalg.norm(H - pb[None], axis=2)
    r, ma, mb = rest[:, None], np.array([a]), np.array([b])
    now = _nll(tpl, ma, r, da) + _nll(tpl, mb, r, db)
    swap = _nll(tpl, ma, r, db) + _nll(tpl, mb, r, da)
    return (now - swap).sum(axis=0)


#: Rounds of :func:`_complete_weak` (each releases the weak markers the last one left).
WEAK_ROUNDS = 3


def _complete_weak(
    tpl: _Template,
    assign: np.ndarray,
    pts: np.ndarray,
    hist: np.ndarray,
    taken: np.ndarray,
    config: BootConfig,
    exchange: bool = False,
) -> np.ndarray:
    """:func:`_complete` (``exchange``: see there), then up to ``WEAK_ROUNDS`` re-readings
    with the weakly placed markers (:func:`_weak_markers`) released: the completion without
    them is kept when it
    places more of the subject's markers and the released markers it puts on other points fit
    the markers placed in both readings better there (:func:`_pair_error`, by
    ``EXCHANGE_MARGIN``). A limb or plate read on another
    limb's points at boot (the kneeling performer's right ankle, heel and toe triangle on its
    left hand and forearm, a shank marker on a toe) holds its points and clashes with every
    candidate of the segments next to it, which then stay unlabeled for the whole take;
    released, those segments join on their rigid evidence and the released markers are
    placed again where the completion finds them. Then each loose segment (:func:`_loose_part`:
    nothing rigid ties it to the rest, a hugging partner's hand read as this performer's) is
    released alone, under the same test with each reading judged against its own rest
    (:func:`_evidence`). Markers may move: the caller carries the moves."""
    grown = _complete(tpl, assign, pts, hist, taken, config, reread=True, exchange=exchange)
    for _ in range(WEAK_ROUNDS):
        if np.all(grown >= 0):
            break
        weak = _weak_markers(tpl, grown, np.flatnonzero(grown < 0), pts)
        if weak.size == 0:
            break
        alt = _released(tpl, grown, weak, pts, hist, taken, config)
        if np.count_nonzero(alt >= 0) <= np.count_nonzero(grown >= 0):
            break
        # released markers placed on other points must fit the markers placed in both
        # readings better there (:func:`_pair_error`, by ``EXCHANGE_MARGIN``): the dancer's
        # back hip markers (no rigid partner in that model) came back exchanged otherwise
        moved = weak[(alt[weak] >= 0) & (alt[weak] != grown[weak])]
        if moved.size:
            both = (alt >= 0) & (grown >= 0)
            now = _pair_error(tpl, moved, grown[moved], np.where(both, grown, -1), pts)
            new = _pair_error(tpl, moved, alt[moved], np.where(both, alt, -1), pts)
            if new > now - EXCHANGE_MARGIN:
                break
        grown = alt
    # whole segments that nothing rigid ties to the rest of the subject, released one at a
    # time (:func:`_loose_part`), under the same test
    for seg in tpl.segments if config.release_loose else ():
        if np.all(grown >= 0):
            break
        part = _loose_part(tpl, seg, grown, pts)
        if part.size == 0:
            continue
        alt = _released(tpl, grown, part, pts, hist, taken, config)
        # more markers placed, the released ones among them (the segment may be right: a
        # pelvis plate let go for markers placed elsewhere is not undone by the next rounds)
        if np.count_nonzero(alt >= 0) <= np.count_nonzero(grown >= 0) or np.any(alt[part] < 0):
            continue
        # released markers placed on other points must fit better there, each reading
        # against the rest of it (:func:`_evidence`): the segments the release let in are
        # what tells a partner's hand from this performer's own, at the end of its forearm
        moved = part[(alt[part] >= 0) & (alt[part] != grown[part])]
        if np.isin(alt[moved], grown[part]).any():
            # the segment read again on its own points (a head plate turned round) is the
            # readings' business (:func:`_readings`), not the release's: against each
            # reading's own rest, the completion's added markers would decide it
            continue
        if moved.size:
            now = _evidence(tpl, moved, grown[moved], grown, pts)
            new = _evidence(tpl, moved, alt[moved], alt, pts)
            if new > now - EXCHANGE_MARGIN:
                continue
        grown = alt
    return grown


def _released(
    tpl: _Template,
    grown: np.ndarray,
    released: np.ndarray,
    pts: np.ndarray,
    hist: np.ndarray,
    taken: np.ndarray,
    config: BootConfig,
) -> np.ndarray:
    """:func:`_complete` of ``grown`` with the markers ``released`` unplaced and their points
    free again (the re-reading :func:`_complete_weak` tests)."""
    base = grown.copy()
    base[released] = -1
    free = taken.copy()
    free[grown[released]] = False
    return _complete(tpl, base, pts, hist, free, config)


def _evidence(
    tpl: _Template, markers: np.ndarray, points: np.ndarray, assign: np.ndarray, pts: np.ndarray
) -> float:
    """:func:`_pair_error` of ``markers`` on ``points`` (against the rest of ``assign`` and
    among themselves) as a log-likelihood ratio: less the same pairs' negative log-likelihood
    were the points unrelated to the subject (a pair distance uniform over the template's
    ``extent``: ``log extent`` each). Each pair's ``_nll`` is a density in mm, so the plain sum
    grows with the number of pairs, right or wrong: two subjects reading the same points are
    compared on different pair counts, and the one with fewer markers placed looked better (a
    hugging partner's arm taken from a performer with 41 markers placed, whose 7 rigid pairs to
    it held, by one with 32 and none: 1,213 against 1,370 nats; as ratios -227 against -565)."""
    have = np.flatnonzero(assign >= 0)
    rest = have[~np.isin(have, markers)]
    mk = np.asarray(markers, dtype=np.int64)
    use = tpl.nll_use & np.isfinite(tpl.D)
    n_pairs = int(np.triu(use[np.ix_(mk, mk)], 1).sum() + use[np.ix_(mk, rest)].sum())
    return _pair_error(tpl, mk, points, assign, pts) - n_pairs * float(np.log(tpl.extent))


def _tied(
    tpl: _Template, markers: np.ndarray, points: np.ndarray, assign: np.ndarray, pts: np.ndarray
) -> int:
    """How many pairs of one trained body (``strict``) tie ``markers`` on ``points`` to the
    markers placed by ``assign`` outside them, within their tolerance: the rigid evidence that
    the points belong to *this* subject. Pairs among ``markers`` are left out: any reading of
    the same limb has them (as many as the template's bodies over those markers: a model's loose
    body of forearm, wrist and hand markers gives a partner's forearm read as this subject's
    hand a dozen)."""
    mk = np.asarray(markers, dtype=np.int64)
    have = np.flatnonzero(assign >= 0)
    rest = have[~np.isin(have, mk)]
    if mk.size == 0 or rest.size == 0:
        return 0
    d = np.linalg.norm(pts[points][:, None] - pts[assign[rest]][None], axis=2)
    ok = tpl.strict[np.ix_(mk, rest)] & (
        np.abs(d - tpl.D[np.ix_(mk, rest)]) <= tpl.tol[np.ix_(mk, rest)]
    )
    return int(ok.sum())


def _loose_part(tpl: _Template, seg: np.ndarray, assign: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """The placed markers of segment ``seg`` (:func:`_segments`) when the segment is *loose*:
    at most ``WEAK_SUPPORT`` pairs of one trained body tie them to the rest of the subject
    (:func:`_tied`) and two or more markers of the segment's bodies or of their chain
    neighbours (``tpl.near``) are still unplaced; else an empty array. A hugging partner's
    hand joined through articulated links where this performer's hand should be, with the
    forearm and upper arm between left out, holds its three points by its own rigid pairs (no
    marker of it is weak, :func:`_weak_markers`) and clashes with every candidate of this
    performer's own forearm; nothing rigid ties it to the shoulder."""
    part = seg[assign[seg] >= 0]
    if part.size == 0:
        return part
    # the segments between it and the trunk unplaced: two or more markers (a marker hidden
    # next to a plate rightly placed is the common case, and each release costs a completion)
    around = np.zeros(tpl.n, dtype=bool)
    for b in {b for m in seg for b in tpl.body_of[m]}:
        around[tpl.bodies[b].markers] = True
        around |= tpl.near[b]
    if np.count_nonzero(around & (assign < 0)) < 2:
        return part[:0]
    if _tied(tpl, part, assign[part], assign, pts) > WEAK_SUPPORT:
        return part[:0]
    return part


def warmup_kernels() -> None:
    """Compiles (or loads from cache) the boot's numba kernels on a tiny input."""
    M = np.zeros(2, dtype=np.int64)
    m = np.zeros((1, 1))
    rigid = np.zeros((1, 1), dtype=np.bool_)
    dist = np.zeros((1, 1))
    _agree_count(M, M, dist, m, m, rigid, np.zeros(2, dtype=np.int64))
    _track_constancy(
        np.zeros((1, 2), dtype=np.int64), np.zeros((1, 2, 3)), np.zeros((2, 2)), np.ones((2, 2))
    )
    out_b = np.zeros((2, 2), dtype=np.bool_)
    _graph_rows(
        M, np.zeros(2, dtype=np.bool_), M, M, dist, m, m, rigid, rigid.copy(), m, m,
        out_b, out_b.copy(), out_b.copy(), out_b.copy(), np.zeros((2, 2)), out_b.copy(),
    )  # fmt: skip
    # the kernels of kernels/boot_*.py and the point tracker's (every frame of a booting stream)
    z, ones = np.zeros(2, dtype=np.int64), np.ones(2, dtype=np.bool_)
    _greedy_nodes(
        ~ones, z.copy(), z.copy(), z.copy(), np.zeros(2), z.copy(), ones.copy(), 2, ~ones, M, M,
        dist, m, m, rigid, rigid.copy(), m, m, out_b, out_b.copy(), out_b.copy(), out_b.copy(),
        np.zeros((2, 2)), out_b.copy(),
    )  # fmt: skip
    _body_scores(
        np.array([[0, 1, -1, -1, -1, -1, -1, -1]]), ~ones, ~ones, z.copy(), np.zeros(2),
        z.copy(), z.copy(), z.copy(), np.ones((1, 2), dtype=np.bool_), M, ~ones[:1], True, 0.5,
    )  # fmt: skip
    p3 = np.zeros((2, 3))
    _pair_error_kernel(m, m, m, rigid, rigid, z[:1], z[:1], z[:1], p3, STRICT_SIGMAS)
    _grow_kernel(z[:1] - 1, ~ones, p3, m, m, m, rigid, rigid, m, rigid)
    _constancy_counts(np.zeros((2, 2, 3)), z.copy(), np.zeros((2, 2)), np.ones((2, 2)), ~out_b)
    _swap_gains_kernel(m, m, m, rigid, rigid, z, z[:1], z[1:], p3, STRICT_SIGMAS)
    _match_tracks(p3, p3 + 1.0, np.ones(2))
    _track_step(
        p3, p3 + 1.0, p3.copy(), ones.copy(), z.copy(), np.zeros(2), 1.0, 0.0, 1.0, 1.0, 0, 1.0,
        300.0,
    )  # fmt: skip
    _track_history(z, p3, z.copy(), np.array([0, 2]), np.full((2, 1, 3), np.nan))
    # the body search's anchor triangles (:func:`_triangles`, :func:`_body_candidates`)
    _join_triangles(z.copy(), z + 1, z.copy(), z + 1, np.array([3]), np.int64(2))
    _anchor_predict(np.eye(3), np.eye(3), np.eye(3), np.zeros((1, 3), dtype=np.int64))
    # a booting labeler's installs (kernels/stacked.py; the other one warms with the inner
    # labeler's install: BootingLabeler.warmup)
    _spread_labels(z[:1], z[:1], z.copy(), z - 1, np.array([0, 2]), 2)


# ---------------------------------------------------------------------------- joint fill
#: nats: the best joint assignment of a subject's leftover markers must beat every other by
#: this, and by ``EXCHANGE_MARGIN`` per leftover marker (:func:`_fill`)
FILL_MARGIN = 3.0
#: most joint assignments :func:`_fill` enumerates (it does nothing beyond)
FILL_MAX_MAPS = 60000
#: A segment read again onto free points (:func:`_free_readings`) must lower the negative
#: log-likelihood by more than this (nats): a move to points no marker held is a new reading,
#: not an exchange, and must beat the one the candidates gave clearly (the fill's 3 nats).
FREE_READ_NATS = 3.0
#: ... and is not tried when more maps than this keep the segment's distances (a crowd).
FREE_READ_MAX_MAPS = 2000


def _maps_onto(
    tpl: _Template, placed: np.ndarray, pool: np.ndarray, pts: np.ndarray
) -> list[np.ndarray] | None:
    """Injective maps of markers ``placed`` to points of ``pool`` that keep the distances of
    one trained body (depth-first, each marker checked against those already given); ``None``
    when there are more than ``FREE_READ_MAX_MAPS``."""
    D, tol, strict = tpl.D, tpl.tol, tpl.strict
    d = np.linalg.norm(pts[pool][:, None] - pts[pool][None, :], axis=2)
    # marker a on pool point i and marker b on pool point j keep the pair's trained distance;
    # only pairs of one trained body (``strict``) are checked
    fits = {
        (a, b): np.abs(d - D[placed[a], placed[b]]) <= tol[placed[a], placed[b]]
        for a in range(placed.size)
        for b in range(a)
        if strict[placed[a], placed[b]]
    }
    maps = _injective_maps(placed.size, pool.size, fits, FREE_READ_MAX_MAPS)
    return None if maps is None else [pool[m] for m in maps]


def _gain_along(
    tpl: _Template,
    placed: np.ndarray,
    old: np.ndarray,
    new: np.ndarray,
    base: np.ndarray,
    hist: np.ndarray,
) -> float | None:
    """The median over the window's samples of how much better markers ``placed`` fit on
    points ``new`` than on ``old`` (:func:`_pair_error` against the rest of ``base``), over the
    samples that track every point of both readings (at least half the window); ``None`` when
    fewer."""
    both = np.concatenate([old, new])
    ok = np.all(np.isfinite(hist[both, :, 0]), axis=0)
    if ok.sum() < max(1, hist.shape[1] // 2):
        return None
    gains = [
        _pair_error(tpl, placed, old, base, hist[:, f])
        - _pair_error(tpl, placed, new, base, hist[:, f])
        for f in np.flatnonzero(ok)
    ]
    return float(np.median(gains))


def _free_readings(
    tpl: _Template,
    assign: np.ndarray,
    pts: np.ndarray,
    free: np.ndarray,
    tree: cKDTree,
    hist: np.ndarray | None = None,
    min_placed: int = 3,
    doubtful: np.ndarray | None = None,
) -> None:
    """Every segment (``min_placed`` to four placed markers; three by default: two points keep one
    distance, which a plate's two diagonals share) is read again over its own points and the
    free points within its reach: the injective map of its placed markers to those points that
    keeps the distances of one trained body and fits the rest of the subject best
    (:func:`_pair_error`) replaces the current one when it is better by ``FREE_READ_NATS`` and
    reverses no thick chirality quadruple with a marker it moves. A model that lacks a marker (a
    ROM take that never showed it) leaves that marker's point free, and a plate read mirrored
    onto it (a pelvis's right ASIS on the left ASIS's point, the PSIS exchanged) keeps every
    distance of the plate; :func:`_readings` permutes the placed points only and cannot reach
    the true point, which the mirror left free. With the window's tracks ``hist (N, W, 3)`` the
    move must also fit better by ``FREE_READ_NATS`` in the median over the window frames that
    track every point of both readings (at least half the window, :func:`_gain_along`): a
    reading that fits one frame only is a coincidence. With ``doubtful`` (``(n,)`` bool, markers
    whose pairs are off: :func:`_doubtful`) a segment is read again only when no doubtful marker
    lies outside it: the move is judged against the rest of the subject, and a rest in doubt is
    no reference. ``free`` is updated."""
    D = tpl.D
    for seg in tpl.segments:
        placed = seg[assign[seg] >= 0]
        if placed.size < min_placed or placed.size > 4:
            continue
        if doubtful is not None and doubtful.sum() > doubtful[seg].sum():
            continue  # the rest the move is judged against is itself in doubt
        own = assign[placed]
        sub = D[np.ix_(seg, seg)]
        size = float(np.where(np.isfinite(sub), sub, 0.0).max())
        centre = pts[own].mean(axis=0)
        near = np.asarray(tree.query_ball_point(centre, size + 20.0), dtype=np.int64)
        near = near[free[near]]
        if near.size == 0:
            continue
        pool = np.concatenate([own, near])
        maps = _maps_onto(tpl, placed, pool, pts)
        if maps is None:
            continue
        base = assign.copy()
        base[placed] = -1
        best, best_err = None, _pair_error(tpl, placed, own, base, pts) - FREE_READ_NATS
        for mp in maps:
            if np.all(np.isin(mp, own)):
                continue  # a permutation of its own points: :func:`_readings`' business
            err = _pair_error(tpl, placed, mp, base, pts)
            if err < best_err:
                best, best_err = mp, err
        if best is None:
            continue
        out = assign.copy()
        out[placed] = best
        if _changed_reversed(tpl, assign, out, pts):
            continue
        if hist is not None:  # the window must agree (a coincidence of one frame: tune22 quarter)
            along = _gain_along(tpl, placed, own, best, base, hist)
            if along is None or along <= FREE_READ_NATS:
                continue
        free[own] = True
        free[best] = False
        assign[placed] = best


#: The fill judges chirality (:func:`_fill_reversed`) on this many of its cheapest maps.
FILL_CHIRAL_TOP = 256


def _fill_reversed(
    tpl: _Template,
    assign: np.ndarray,
    pts: np.ndarray,
    marks: np.ndarray,
    points: np.ndarray,
    stale: np.ndarray | None = None,
) -> np.ndarray:
    """Per map (``marks``, ``points``: ``(K, k)`` markers and their points): does it reverse a
    thick chirality quadruple (cube root of ``|det|`` >= ``CHIRAL_MIN_MM``) with all four
    markers placed and at least one of them new? ``stale (m, m)``: pairs the stream
    contradicts (:func:`_stale_pairs`); a quadruple holding one does not count."""
    q = tpl.chirality
    K = marks.shape[0]
    if stale is not None and q.shape[0]:
        q = q[~_quads_holding(q, stale)]
    if q.shape[0] == 0 or K == 0:
        return np.zeros(K, dtype=bool)
    out = np.broadcast_to(assign, (K, tpl.n)).copy()
    rows = np.arange(K)[:, None]
    out[rows, marks] = points
    new = np.zeros((K, tpl.n), dtype=bool)
    new[rows, marks] = True
    return np.any(_reversed_quads(q, out, new, pts), axis=1)


def _reversed_quads(q: np.ndarray, out: np.ndarray, new: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``(..., Q)``: the quadruples of ``q (Q, 4)`` with all four markers placed in ``out
    (..., m)``, one of them ``new (..., m)``, whose thick tetrahedron is reversed."""
    oq = out[..., q]  # (..., Q, 4)
    use = np.all(oq >= 0, axis=-1) & np.any(new[..., q], axis=-1)
    det = _volumes(pts[np.where(oq >= 0, oq, 0)])
    return use & _reversed_thick(det)


def _quads_holding(q: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Per quadruple of ``q (Q, 4)``: does one of its six pairs hold in ``pairs (m, m)``?"""
    out = np.zeros(q.shape[0], dtype=bool)
    for a, b in itertools.combinations(range(4), 2):
        out |= pairs[q[:, a], q[:, b]]
    return out


def _stale_pairs(
    tpl: _Template, miss: np.ndarray, have: np.ndarray, dp: np.ndarray, dc: np.ndarray
) -> np.ndarray:
    """``(m, m)`` rigid pairs of a trained body that was not rigid as a whole (``strict`` and
    not ``whole``), of a leftover marker (``miss``) with a placed one (``have``) or with
    another leftover marker, that the stream contradicts: no candidate point (``dp (nc, h)``:
    its distances to the placed markers), or no two distinct candidates (``dc (nc, nc)``),
    are at the pair's trained distance within ``tol``. Whatever the map, such a body is not
    rigid in this segment: the trainer completed it across a joint (one of its pairs moved)
    and the training segment never moved the joint between the other two (the broad jumper's
    ``[R.Shoulder, Sternum, R.Elbow]``, trained on a landing with the arms held:
    ``Sternum-R.Elbow`` ``A`` 11.7 mm; in the take-off ``R.Shoulder-R.Elbow`` is 21-86 mm
    off, ``tol`` 14). A pair that a wholly rigid body holds is one segment: contradicted, it
    says a marker is placed on the wrong point (the two-player copy's hand read with its
    finger and wrist markers exchanged at boot, ``RFRM-RWRB`` 234 mm for 131), and a pair across
    bodies off its distance is a pose; neither is listed."""
    out = np.zeros((tpl.n, tpl.n), dtype=bool)
    nc = dc.shape[0]
    if nc == 0 or miss.size == 0:
        return out
    loose = tpl.strict & ~tpl.whole
    D, tol = tpl.D[np.ix_(miss, have)], tpl.tol[np.ix_(miss, have)]
    fit = np.abs(dp[None] - D[:, None, :]) <= tol[:, None, :]  # (nu, nc, h)
    out[np.ix_(miss, have)] = loose[np.ix_(miss, have)] & ~fit.any(axis=1)
    if nc >= 2:
        D2, tol2 = tpl.D[np.ix_(miss, miss)], tpl.tol[np.ix_(miss, miss)]
        two = ~np.eye(nc, dtype=bool)
        fit2 = np.abs(dc[None, None] - D2[:, :, None, None]) <= tol2[:, :, None, None]
        out[np.ix_(miss, miss)] = loose[np.ix_(miss, miss)] & ~(fit2 & two).any(axis=(2, 3))
    out |= out.T
    return out


@functools.lru_cache(maxsize=64)
def _fill_maps(nu: int, nc: int) -> tuple[np.ndarray, np.ndarray]:
    """Every injective map between ``nu`` markers and ``nc`` points that places
    ``min(nu, nc)`` of them: ``(maps, k)`` marker and point positions per slot."""
    k = min(nu, nc)
    if nc >= nu:
        pt = np.array(list(itertools.permutations(range(nc), k)), dtype=np.int64).reshape(-1, k)
        mk = np.broadcast_to(np.arange(k), pt.shape)
    else:
        mk = np.array(list(itertools.permutations(range(nu), k)), dtype=np.int64).reshape(-1, k)
        pt = np.broadcast_to(np.arange(k), mk.shape)
    mk, pt = np.ascontiguousarray(mk), np.ascontiguousarray(pt)
    mk.flags.writeable = False  # (cached)
    pt.flags.writeable = False
    return mk, pt


def _drop_one_sided(tpl: _Template, assign: np.ndarray, out: np.ndarray) -> None:
    """Unplaces in ``out`` the markers new to it (not placed in ``assign``) that
    :func:`_one_sided` leaves unguessed."""
    loose = _one_sided(tpl, out)
    out[loose[assign[loose] < 0]] = -1


def _one_sided(tpl: _Template, assign: np.ndarray) -> np.ndarray:
    """Markers of mirror segments (:func:`_mirror_pairs`) placed whole on one side while no
    marker of the other side is placed and no thick-trained chirality quadruple has all four
    markers placed and one of them in the segment (nothing has told which side it is), while
    a local quadruple over it (:func:`_local_quads`: its leg's knee, ankle and toes) still
    lacks a marker (its knee), which will tell the side once placed."""
    q = tpl.chirality
    if q.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    covered = np.zeros(tpl.n, dtype=bool)
    covered[q[np.all(assign[q] >= 0, axis=1)].ravel()] = True
    pending = np.zeros(tpl.n, dtype=bool)  # in a local quadruple still lacking a marker
    pending[q[np.any(assign[q] < 0, axis=1) & tpl.chiral_local].ravel()] = True
    out = []
    for s1, s2 in tpl.mirrors:
        for a, b in ((s1, s2), (s2, s1)):
            if (
                np.all(assign[a] >= 0)
                and np.all(assign[b] < 0)
                and not covered[a].any()
                and pending[a].any()
            ):
                out.append(a)
    return np.unique(np.concatenate(out)) if out else np.zeros(0, dtype=np.int64)


def _fill(
    tpl: _Template,
    assign: np.ndarray,
    pts: np.ndarray,
    hist: np.ndarray,
    free: np.ndarray,
    others: np.ndarray,
    config: BootConfig,
    claimed: np.ndarray | None = None,
    exchange: bool = False,
) -> np.ndarray:
    """Places a booted subject's leftover markers on its leftover persistent tracks, judged
    jointly. A model trained on a segment that never exercised a joint (the broad jump's
    landing: arms down) has its distances from the arms to the rest off in every other pose
    and spurious rigid bodies across the arms, so no pair rule of the extension or of
    :meth:`Booter.acquire` accepts them, while the stream's own evidence (which leftover point
    is which leftover marker) is clear.

    ``free (N,)``: points that may be taken (free, tracked at least ``fill_min_age_s``: a ghost
    lives a few frames); ``others (K, 3)``: points labeled for other subjects. Candidates are
    the free points within the subject's extent, tracked over the whole window, whose nearest
    labeled point is this subject's; there must be no more of them than leftover markers (a
    surplus is points no leftover marker explains: a model that lacks some of the subject's
    markers, another performer) and at least two of each (a single pairing has no
    alternative to beat). Every injective map of the leftover markers to the candidates is
    scored by the negative log-likelihood of its distances, Cauchy in the pair's tolerance
    (``tol`` for a pair of one trained body, the articulated ``link`` otherwise), to the placed
    markers and among the map's own markers: robust to a minority of violated pairs, and the
    terms every map shares (a raised arm far from the trained hips) cancel between maps. The
    best map is taken only when it beats every other by ``FILL_MARGIN`` nats and by
    ``EXCHANGE_MARGIN`` per leftover marker, plus ``log comb(nu, nc)`` when fewer points
    (``nc``) than markers (``nu``) are left (a map then also chooses which markers are seen:
    the best of 10 choices of 2 arm markers out of 5 won by 5.5 nats, wrongly), and only if
    - each new marker has most of its pairs to its ``art_anchors`` steadiest placed partners
      (least ``A``: its own and the next segments) within reach (``D + bound``: a pose brings
      them closer, rarely much farther) and keeps its steadiest partner's distance within
      twice its tolerance along the window (the point moves with this subject);
    - no new marker would fit better (:func:`_pair_error`, by ``EXCHANGE_MARGIN``) with its
      point exchanged with a placed marker's: a placed marker on the wrong point (a dancer's
      fifth toe on the big toe's point) leaves its own point over, and filling it would lock
      the error in;
    - no thick chirality quadruple with a new marker is reversed (a subject booted with its
      legs mirrored is not completed mirrored), except quadruples holding a pair the stream
      contradicts of a body not rigid as a whole in training (:func:`_stale_pairs`: a body
      learned across a joint the training segment never moved).
    When the best map is not unique, the markers every map within the margin puts on one
    point are placed, if a pair of one trained body holds there and the best map passes
    the checks above as a whole (:func:`_fill_checks`); the others wait.
    Otherwise nothing is placed. When that places nothing and ``claimed (N,)`` is given (free
    points within reach of another active subject's leftover markers, :func:`_reach`), the
    free points nearer another subject's labeled points that no other subject claims and one
    of this subject's leftover markers reaches join the candidates, and the joint map is
    tried again with the same rules. Returns the new assignment (a copy when changed)."""
    n = tpl.n
    have = np.flatnonzero(assign >= 0)
    if have.size < config.boot_markers(n) or have.size == n:
        return assign
    miss = np.flatnonzero(assign < 0)
    miss = miss[np.isfinite(tpl.D[np.ix_(miss, have)]).any(axis=1)]
    if miss.size < 2:
        return assign
    placed = pts[assign[have]]
    centre = placed.mean(axis=0)
    cand = np.flatnonzero(free & (np.linalg.norm(pts - centre, axis=1) <= tpl.extent))
    cand = cand[np.isfinite(hist[cand, :, 0]).all(axis=1)]
    far = cand[:0]
    if cand.size and others.shape[0]:
        d_own = cKDTree(placed).query(pts[cand])[0]
        nearer = d_own < cKDTree(others).query(pts[cand])[0]
        far, cand = cand[~nearer], cand[nearer]
    out = _fill_jointly(tpl, assign, assign, miss, cand, pts, hist, config, exchange)
    if out is not None:
        return out
    # Points nearer another subject's labeled points that no other subject can still claim
    # (``claimed``: within reach of another active subject's leftover markers) and that one of
    # this subject's leftover markers reaches: a whole segment left over (a kneeling
    # performer's forearm and hand, a jumper's raised arms over a partner) lies farther from
    # its own placed markers than from a partner's, and the nearest-point rule above refused
    # every one of its points while the partner, complete there, has no marker to put on them.
    if claimed is not None and far.size:
        extra = far[~claimed[far] & _reach(tpl, assign, pts, far, config)]
        if extra.size:
            wide = np.sort(np.concatenate([cand, extra]))
            out = _fill_jointly(tpl, assign, assign, miss, wide, pts, hist, config, exchange)
            if out is not None:
                return out
    # Re-read with the weakly placed markers (:func:`_weak_markers`): an arm read one marker
    # along its chain at boot leaves the true points of its first markers free, and the plain
    # fill refuses them (a placed marker fits their points better); the weak markers and their
    # points then join the leftover ones and the joint map may move them.
    weak = _weak_markers(tpl, assign, miss, pts)
    if weak.size == 0 or cand.size == 0:
        return assign
    base = assign.copy()
    base[weak] = -1
    out = _fill_jointly(
        tpl,
        assign,
        base,
        np.concatenate([miss, weak]),
        np.concatenate([cand, assign[weak]]),
        pts,
        hist,
        config,
        exchange,
    )
    return assign if out is None else out


def _reach(
    tpl: _Template, assign: np.ndarray, pts: np.ndarray, idx: np.ndarray, config: BootConfig
) -> np.ndarray:
    """``(len(idx),)``: the points ``idx`` some leftover marker of the subject (unplaced in
    ``assign``) could be on, by the reach test of :func:`_fill_checks`: most of its distances
    to its ``art_anchors`` steadiest placed partners within ``D + bound``."""
    out = np.zeros(idx.size, dtype=bool)
    have = np.flatnonzero(assign >= 0)
    if have.size == 0 or idx.size == 0:
        return out
    d_all = np.linalg.norm(pts[idx][:, None] - pts[assign[have]][None], axis=2)  # (k, h)
    for m in np.flatnonzero(assign < 0):
        known = np.flatnonzero(np.isfinite(tpl.D[m, have]))
        if known.size == 0:
            continue
        mine = known[np.argsort(tpl.A[m, have[known]], kind="stable")[: config.art_anchors]]
        lim = tpl.D[m, have[mine]] + tpl.bound[m, have[mine]]
        out |= 2 * (d_all[:, mine] > lim).sum(axis=1) <= mine.size
    return out


#: A placed marker with at most this many pairs of one trained body placed at their distance
#: (``strict``, within ``tol``) has weak rigid evidence for its point (:func:`_weak_markers`).
WEAK_SUPPORT = 1


def _weak_markers(
    tpl: _Template, assign: np.ndarray, miss: np.ndarray, pts: np.ndarray
) -> np.ndarray:
    """Placed markers that share a trained body with a leftover marker (``miss``) and have at
    most ``WEAK_SUPPORT`` of their pairs of one trained body placed at their distance: the
    rigid evidence the joint resolution of :meth:`Booter.run` weighs a contested point by.
    A chain read one marker along (the tennis server's upper arm on the elbow's point, the
    elbow on the forearm's) keeps each such marker with one or no rigid partner in place.
    Support from weak markers does not count (repeated until nothing changes)."""
    have = np.flatnonzero(assign >= 0)
    if have.size < 2 or miss.size == 0:
        return np.zeros(0, dtype=np.int64)
    share = np.zeros(tpl.n, dtype=bool)
    for m in miss:
        for b in tpl.body_of[m]:
            share[tpl.bodies[b].markers] = True
    ok = _support_pairs(tpl, assign, pts)
    # support from weak markers does not count: a triangle read on another limb's points
    # holds its three distances to itself (its two weakest make the third weak too)
    weak = np.zeros(have.size, dtype=bool)
    while True:
        grown = share[have] & (ok[:, ~weak].sum(axis=1) <= WEAK_SUPPORT)
        if np.array_equal(grown, weak):
            return have[weak]
        weak = grown


def _support_pairs(tpl: _Template, assign: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``(h, h)`` over the placed markers of ``assign`` (in index order): pairs of one trained
    body (``strict``) placed within their tolerance."""
    have = np.flatnonzero(assign >= 0)
    p = pts[assign[have]]
    d = np.linalg.norm(p[:, None] - p[None, :], axis=2)
    return tpl.strict[np.ix_(have, have)] & (
        np.abs(d - tpl.D[np.ix_(have, have)]) <= tpl.tol[np.ix_(have, have)]
    )


def _fill_jointly(
    tpl: _Template,
    assign: np.ndarray,
    base: np.ndarray,
    miss: np.ndarray,
    cand: np.ndarray,
    pts: np.ndarray,
    hist: np.ndarray,
    config: BootConfig,
    exchange: bool = False,
) -> np.ndarray | None:
    """The joint map of :func:`_fill`: markers ``miss`` (unplaced in ``base``, which is
    ``assign`` less the markers re-read) onto points ``cand``. Returns the new assignment, or
    None when it is not unique or a check refuses it. A unique cheapest map that reverses a
    thick chirality quadruple is read again (:func:`_chiral_reread`), and with ``exchange``,
    when that finds nothing, may exchange two placed markers of the reversed quadruples
    (:func:`_chiral_exchange`)."""
    have = np.flatnonzero(base >= 0)
    placed = pts[base[have]]
    nu, nc = miss.size, cand.size
    if nc < 2 or nc > nu or math.perm(nu, nc) > FILL_MAX_MAPS:
        return None
    scale = np.where(tpl.strict, tpl.tol, tpl.link)
    dp = np.linalg.norm(pts[cand][:, None] - placed[None], axis=2)  # (nc, h)
    dc = np.linalg.norm(pts[cand][:, None] - pts[cand][None], axis=2)
    # bodies no candidate keeps rigid (a model trained in another pose): their quadruples
    # do not vote on chirality
    stale = _stale_pairs(tpl, miss, have, dp, dc)
    known = np.isfinite(tpl.D) & (scale > 0)

    def cost(ma: np.ndarray, mb: np.ndarray, d: np.ndarray) -> np.ndarray:
        e = (d - tpl.D[ma, mb]) / np.where(known[ma, mb], scale[ma, mb], 1.0)
        return np.where(known[ma, mb], np.log1p(e * e), 0.0)

    # unary: (nu, nc) to the placed markers; pairwise: (nu, nu, nc, nc) among the map's own
    unary = cost(miss[:, None, None], have[None, None, :], dp[None]).sum(axis=2)
    pair = cost(miss[:, None, None, None], miss[None, :, None, None], dc[None, None])
    mk, pt = _fill_maps(nu, nc)
    total = unary[mk, pt].sum(axis=1)
    k = mk.shape[1]
    for a in range(k):
        for b in range(a + 1, k):
            total += pair[mk[:, a], mk[:, b], pt[:, a], pt[:, b]]
    # with fewer points than markers a map also chooses which markers are seen: the best of
    # comb(nu, nc) such choices beats the others by chance more often (a Bonferroni term)
    margin = max(FILL_MARGIN, EXCHANGE_MARGIN * nu) + math.log(math.comb(nu, nc))
    # a map that reverses a thick chirality quadruple with a new marker is no reading (a
    # mirror image fits every distance): it does not make the winner ambiguous; when the
    # cheapest map is one, nothing is placed (the next-best, taken then, read a head's
    # diagonal markers crossed in tune14)
    top = np.argsort(total, kind="stable")[:FILL_CHIRAL_TOP]
    ok = ~_fill_reversed(tpl, base, pts, miss[mk[top]], cand[pt[top]], stale)
    if not ok[0]:
        # the cheapest map reversed, and unique: its segments read again (a plate placed
        # mirrored leaves its own fourth marker only the mirror point, :func:`_chiral_reread`)
        if top.size > 1 and total[top[1]] <= total[top[0]] + margin:
            return None
        out = base.copy()
        marks = miss[mk[top[0]]]
        out[marks] = cand[pt[top[0]]]
        got = _chiral_reread(tpl, base, out, marks, pts)
        if got is base and exchange:
            got = _chiral_exchange(tpl, base, out, marks, pts, hist)
        if np.array_equal(got, base) or not _fill_checks(
            tpl, assign, got, have, pts, hist, stale, config
        ):
            return None
        return got
    best = int(top[np.argmax(ok)])
    if top.size < total.size and total[top[-1]] <= total[best] + margin:
        return None  # rivals beyond the maps judged: wait for more evidence
    near = top[ok & (total[top] <= total[best] + margin)]
    out = base.copy()
    out[miss[mk[best]]] = cand[pt[best]]
    if near.size > 1 and not config.fill_agreement:
        return None
    if near.size > 1:
        # the cheapest map must pass the checks as a whole (a reading wrong somewhere makes
        # its rivals' agreement suspect: a performer read with its arms mixed agreed on a
        # right forearm marker on the left wrist's point, tune00)
        if np.array_equal(out, assign) or not _fill_checks(
            tpl, assign, out, have, pts, hist, stale, config
        ):
            return None
        # not unique: the markers every rival map puts on one point are placed when a pair
        # of one trained body holds there (rigid evidence; with fewer points than markers
        # every map places every point, a point of a marker the model lacks too), the others
        # wait for the next extension (a marker re-read, ``assign`` placed, keeps its point)
        got = np.full((near.size, nu), -1, dtype=np.int64)
        got[np.arange(near.size)[:, None], mk[near]] = cand[pt[near]]
        agree = np.all(got == got[:1], axis=0) & (got[0] >= 0)
        out = base.copy()
        out[miss[agree]] = got[0, agree]
        held = np.flatnonzero(out >= 0)
        d = np.linalg.norm(pts[np.maximum(got[0], 0)][:, None] - pts[out[held]][None], axis=2)
        fits = tpl.strict[np.ix_(miss, held)] & (
            np.abs(d - tpl.D[np.ix_(miss, held)]) <= tpl.tol[np.ix_(miss, held)]
        )
        agree &= fits.any(axis=1)
        if not agree.any():
            return None
        out = base.copy()
        out[miss[agree]] = got[0, agree]
        rest = miss[~agree]
        out[rest] = assign[rest]
        used = out[out >= 0]
        if np.unique(used).size != used.size:
            return None
    if np.array_equal(out, assign):
        return None
    return out if _fill_checks(tpl, assign, out, have, pts, hist, stale, config) else None


def _fill_checks(
    tpl: _Template,
    assign: np.ndarray,
    out: np.ndarray,
    have: np.ndarray,
    pts: np.ndarray,
    hist: np.ndarray,
    stale: np.ndarray,
    config: BootConfig,
) -> bool:
    """The checks of :func:`_fill` on a reading ``out`` of ``assign`` (``have``: the markers
    placed before the map): reach and steadiest partner of each new marker, no exchange with
    a placed marker, no thick chirality quadruple reversed (quadruples holding a ``stale``
    pair do not count)."""
    n = tpl.n
    fresh = np.flatnonzero((out >= 0) & (out != assign))
    for m in fresh:
        mine = np.flatnonzero((out >= 0) & (np.arange(n) != m) & np.isfinite(tpl.D[m]))
        mine = mine[np.argsort(tpl.A[m, mine], kind="stable")[: config.art_anchors]]
        d = np.linalg.norm(pts[out[mine]] - pts[out[m]], axis=1)
        if 2 * int(np.count_nonzero(d > tpl.D[m, mine] + tpl.bound[m, mine])) > mine.size:
            return False
        j = mine[np.argmin(tpl.A[m, mine])]
        track = np.linalg.norm(hist[out[m]] - hist[out[j]], axis=1)
        track = track[np.isfinite(track)]
        if track.size == 0 or float(track.max() - track.min()) > 2.0 * tpl.tol[m, j]:
            return False
    # a new marker and a placed one exchanging their points (:func:`_pair_error` of the two
    # against the rest, from one (k, k, k) table as in :func:`_exchange`; the pair between
    # them keeps its distance)
    allm = np.flatnonzero(out >= 0)
    E = _exchange_table(tpl, allm, pts[out[allm]])
    T = E.sum(axis=2)
    i = np.searchsorted(allm, fresh)[:, None]
    j = np.searchsorted(allm, have)[None, :]
    now = T[i, i] - E[i, i, i] - E[i, i, j] + T[j, j] - E[j, j, j] - E[j, j, i]
    swap = T[i, j] - E[i, j, i] - E[i, j, j] + T[j, i] - E[j, i, j] - E[j, i, i]
    if np.any(swap < now - EXCHANGE_MARGIN):
        return False
    q = tpl.chirality
    q = q[~_quads_holding(q, stale)]
    if q.shape[0]:
        new = np.zeros(n, dtype=bool)
        new[fresh] = True
        use = np.all(out[q] >= 0, axis=1) & np.any(new[q], axis=1)
        if use.any() and np.any(_reversed_thick(_volumes(pts[out[q[use]]]))):
            return False
    return True


def _window_exchange(
    tpl: _Template,
    assign: np.ndarray,
    hist: np.ndarray,
    others: np.ndarray | None = None,
    contact_mm: float = 0.0,
) -> np.ndarray:
    """Subject ``tpl``'s reading ``assign`` with pairs of its placed markers exchanged where
    their *tracks* fit the template better the other way round along the window (``hist (N,
    W, 3)``, the tracks of the current points): a booted subject read with two markers on each
    other's points (a wrist bar's ulna marker on the hand's point and the hand's on the ulna's,
    a pelvis read left for right) keeps that reading for the rest of the take, since the
    labeler then tracks both points well. A placed marker is *doubtful* when two or more of its
    pairs of one trained body (``strict``) are off their tolerance in the last frame, more
    than are within it; a doubtful marker ``i`` and another placed marker ``q`` exchange when
    the exchange lowers the subject's :func:`_nll` over all its pairs with the two markers
    (the pair between them keeps its distance) by more than ``EXCHANGE_MARGIN`` in
    ``WINDOW_EXCHANGE_SHARE`` of the window frames that track both points (at least half the
    window), by ``WINDOW_EXCHANGE_NATS`` in the median, and reverses no thick chirality
    quadruple, and neither is doubtful after it (:func:`_still_doubtful`).

    Two markers of one segment exchanged inside it (``a``, ``b`` of a triangle ``a b c``: the
    pair between them keeps its distance, each has one pair off, neither is doubtful) are
    judged by the same evidence when one of them has a pair of one trained body off in the
    last frame (a *suspect*) and both sit in one trained body whose every pair is rigid
    (``whole``: not a body the trainer completed across a joint, the broad jumper's elbow and
    wrist), by ``WINDOW_TRIANGLE_NATS`` in the median, and exchanged only when the exchange
    leaves both wholly consistent with their bodies along the window
    (:func:`_window_consistent`): a reading the model contradicts either way does not pass; and
    not while a point of their segment is within ``contact_mm`` of ``others`` (other subjects'
    labeled points, last frame), as :func:`_window_mirrors`. A doubtful marker's exchange is
    taken first. Returns ``assign`` itself when nothing
    changes, else a new reading."""
    out = assign
    for _ in range(WINDOW_EXCHANGE_ROUNDS):
        have = np.flatnonzero(out >= 0)
        k = have.size
        if k < 3:
            return out
        H = np.transpose(hist[out[have]], (1, 0, 2))  # (W, k, 3)
        w = H.shape[0]
        bad, good = _strict_off(tpl, have, H[-1])
        doubtful = _doubtful_counts(bad, good)
        suspect = bad >= 1
        if not suspect.any():
            return out
        dd = np.linalg.norm(H[:, :, None] - H[:, None, :], axis=3)  # (W, q, j)
        N = _nll(tpl, have[:, None], have[None, :], dd)  # every marker on its point, vs j
        seen = np.isfinite(H[:, :, 0])  # (W, k)
        whole = tpl.whole[np.ix_(have, have)]
        best = {True: (0.0, -1, -1), False: (0.0, -1, -1)}  # doubtful i / suspect i
        for i in np.flatnonzero(suspect):
            X = _nll(tpl, have[i], have[None, :], dd)  # i on point q, vs j
            Y = _nll(tpl, have[:, None], have[None, :], dd[:, i][:, None, :])  # q on i's point
            keep = np.ones((k, k), dtype=bool)
            keep[:, i] = False
            keep[np.arange(k), np.arange(k)] = False
            delta = ((X + Y - N[:, i][:, None, :] - N) * keep).sum(axis=2)  # (W, q)
            both = seen & seen[:, i][:, None]
            n = both.sum(axis=0)
            share = (both & (delta < -EXCHANGE_MARGIN)).sum(axis=0) / np.maximum(n, 1)
            med = np.full(k, np.inf)  # no frame tracks both points: no evidence
            cols = n > 0  # (nanmedian of an all-NaN column warns on the user's console)
            med[cols] = np.nanmedian(np.where(both[:, cols], delta[:, cols], np.nan), axis=0)
            ok = (n >= max(2, w // 2)) & (share >= WINDOW_EXCHANGE_SHARE)
            ok &= med < -WINDOW_EXCHANGE_NATS
            ok[i] = False
            if not doubtful[i]:  # (a doubtful q is judged as i of its own)
                ok &= whole[i] & ~doubtful & (med < -WINDOW_TRIANGLE_NATS)
            if not ok.any():
                continue
            q = int(np.flatnonzero(ok)[np.argmin(med[ok])])
            if med[q] < best[bool(doubtful[i])][0]:
                best[bool(doubtful[i])] = (float(med[q]), int(have[i]), int(have[q]))
        new = None
        for doubt in (True, False):  # a doubtful marker's exchange first
            _, a, b = best[doubt]
            if a < 0:
                continue
            new = out.copy()
            new[a], new[b] = out[b], out[a]
            if _changed_reversed(tpl, out, new, hist[:, -1]) or (
                _still_doubtful(tpl, new, hist, a, b)
                if doubt
                else _in_contact(tpl, new, hist, a, b, others, contact_mm)
                or not _window_consistent(tpl, new, hist, a, b)
            ):
                new = None
                continue
            break
        if new is None:
            return out
        out = new
    return out


#: Evidence for an exchange of two placed markers kept across extensions
#: (:func:`_ledger_exchange`): a pair is exchanged once its sum of per-extension gains, less
#: ``EXCHANGE_MARGIN`` each, exceeds this (nats; the bar a triangle exchange must clear in one
#: window) ...
LEDGER_NATS = WINDOW_TRIANGLE_NATS
#: ... and the exchange fit better by ``EXCHANGE_MARGIN`` in ``WINDOW_EXCHANGE_SHARE`` of its
#: calls, at least this many.
LEDGER_CALLS = 3


@dataclass
class _Ledger:
    """Per subject, the evidence :func:`_ledger_exchange` keeps across extensions for
    exchanging two placed markers: per marker pair ``(n, n)`` the sum of gains less the margin,
    the calls in which the exchange fit better, the calls; per marker the age of its point's
    track at the last call (-1: unplaced or not known)."""

    total: np.ndarray
    better: np.ndarray
    calls: np.ndarray
    age: np.ndarray

    @classmethod
    def of(cls, n: int) -> _Ledger:
        return cls(np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n)), np.full(n, -1.0))

    def clear(self, markers: np.ndarray) -> None:
        """Forgets the evidence of every pair with one of ``markers`` (a new reading)."""
        for t in (self.total, self.better, self.calls):
            t[markers] = 0.0
            t[:, markers] = 0.0


#: Two track ages advanced by the same time agree to this (seconds; under a frame period).
AGE_TOL_S = 1e-3


def _new_tracks(before: np.ndarray, now: np.ndarray) -> np.ndarray:
    """Per marker, is its point on another track than at the last call? ``before``/``now``:
    the age of each marker's point's track then and now (-1: unplaced). Every track that
    lasted has aged by the same time, the median over the markers placed both times; a marker
    whose age moved otherwise is on a new track or has moved onto an older one (a re-reading,
    a fill). An elapsed time below zero (a new take, a tracker restarted) renews them all."""
    both = (before >= 0) & (now >= 0)
    out = np.zeros(now.shape[0], dtype=bool)
    if not both.any():
        return out
    step = now[both] - before[both]
    elapsed = float(np.median(step))
    out[both] = (elapsed < 0) | (np.abs(step - elapsed) > AGE_TOL_S)
    return out


def _ledger_exchange(
    tpl: _Template,
    assign: np.ndarray,
    hist: np.ndarray,
    ledger: _Ledger,
    others: np.ndarray | None = None,
    contact_mm: float = 0.0,
    age: np.ndarray | None = None,
) -> np.ndarray:
    """Subject ``tpl``'s reading ``assign`` with one pair of its placed markers exchanged when
    the evidence for the exchange since the two markers' current readings began, summed over
    extensions in ``ledger`` (updated in place), clears ``LEDGER_NATS``.
    :func:`_window_exchange` judges one window (0.1 s) and only markers with a pair of one
    trained body off: a fast wrist bar whose two markers hold each other's points (a tennis
    serve played backward: ``RWRA`` and ``RWRB`` 99 mm apart, the wrist moving 100-180 mm a
    frame) keeps every such pair within its tolerance (the exchange costs each 12-15 mm of
    19-28), and a window tracks both points in one or two frames, so the swap lasted the rest
    of the take (631 frames). Read by the truth, the exchanged reading fits that take's model
    worse in every frame, by 6.4 nats in the median: evidence a window cannot hold but the
    extensions together do.

    Per extension and pair ``(a, b)`` of placed markers of one trained body (``same``: markers
    of different bodies on each other's points break their bodies' strict pairs, which
    :func:`_window_exchange` sees) whose points the last frame tracks, how much lower the
    :func:`_nll` of their pairs with the other placed markers is with their points exchanged
    (``kernels/boot_pairs.py:_swap_gains``) is added to the pair's sum less
    ``EXCHANGE_MARGIN``. The sum runs from the start of the reading: a marker unplaced,
    exchanged, or whose point is on another track than at the last call (``age (N,)``,
    seconds each point's track has lived: :func:`_new_tracks`) clears its pairs (the caller
    clears the markers the other re-checks moved). Not a running window: a model trained in
    other poses may prefer the exchanged reading for a while (the dancer's wrist bar,
    ``Radius_L``/``Ulna_L``, by 12.7 nats a frame for a second, read right by the truth); the
    calls since the reading began, most of them for it as it is, tell that apart from a
    reading wrong since it began. The pair with the largest sum
    over ``LEDGER_NATS`` whose exchange fit better in ``WINDOW_EXCHANGE_SHARE`` of at least
    ``LEDGER_CALLS`` calls is exchanged when the exchange reverses no thick chirality
    quadruple, leaves each of the two consistent with its segment along the window
    (:func:`_window_consistent`: the broad jumper's arm, a reading the model contradicts
    either way, was exchanged wrong for 150 frames without it) and neither doubtful, and no
    point of their segment is within ``contact_mm`` of ``others`` (:func:`_window_exchange`'s
    guards). Returns ``assign`` itself when nothing changes, else a new reading."""
    gone = assign < 0
    if age is not None:
        now_age = np.full(tpl.n, -1.0)
        now_age[~gone] = np.asarray(age, dtype=np.float64)[assign[~gone]]
        ledger.clear(np.flatnonzero(gone | _new_tracks(ledger.age, now_age)))
        ledger.age = now_age
    else:
        ledger.clear(np.flatnonzero(gone))
    have = np.flatnonzero(~gone)
    if have.size < 3:
        return assign
    ia, ib = np.triu_indices(have.size, 1)
    a, b = have[ia], have[ib]
    pair = tpl.same[a, b]
    a, b, ia, ib = a[pair], b[pair], ia[pair], ib[pair]
    if a.size == 0:
        return assign
    gain = _swap_gains_kernel(
        tpl.D, tpl.nll_scale, tpl.nll_log, tpl.nll_gauss, tpl.nll_use, have, ia, ib,
        np.ascontiguousarray(hist[assign[have], -1], dtype=np.float64), STRICT_SIGMAS,
    )  # fmt: skip
    rows = np.flatnonzero(np.isfinite(gain))
    if rows.size == 0:
        return assign
    a, b, g = a[rows], b[rows], gain[rows]
    ledger.total[a, b] += g - EXCHANGE_MARGIN
    ledger.better[a, b] += g > EXCHANGE_MARGIN
    ledger.calls[a, b] += 1.0
    total, calls = ledger.total[a, b], ledger.calls[a, b]
    ok = (total > LEDGER_NATS) & (calls >= LEDGER_CALLS)
    ok &= ledger.better[a, b] >= WINDOW_EXCHANGE_SHARE * calls
    if not ok.any():
        return assign
    top = int(np.flatnonzero(ok)[np.argmax(total[ok])])
    x, y = int(a[top]), int(b[top])
    new = assign.copy()
    new[x], new[y] = assign[y], assign[x]
    if (
        _changed_reversed(tpl, assign, new, hist[:, -1])
        or _still_doubtful(tpl, new, hist, x, y)
        or _in_contact(tpl, new, hist, x, y, others, contact_mm)
        or not _window_consistent(tpl, new, hist, x, y)
    ):
        return assign
    ledger.clear(np.array([x, y]))
    return new


def _strict_off(tpl: _Template, have: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per placed marker ``have[i]`` on ``pos[i]``: how many of its pairs of one trained body
    (``strict``) to the other placed markers are off their tolerance, and how many within it
    (a marker whose point is untracked has neither)."""
    d = np.linalg.norm(pos[:, None] - pos[None, :], axis=2)
    hh = np.ix_(have, have)
    strict = tpl.strict[hh]
    with np.errstate(invalid="ignore"):
        off = np.abs(d - tpl.D[hh]) > tpl.tol[hh]
    seen = np.isfinite(pos[:, 0])
    bad = (strict & off).sum(axis=1) * seen
    good = (strict & ~off & np.isfinite(d)).sum(axis=1)
    return bad, good


def _in_contact(
    tpl: _Template,
    new: np.ndarray,
    hist: np.ndarray,
    a: int,
    b: int,
    others: np.ndarray | None,
    contact_mm: float,
) -> bool:
    """Is a placed point of the segment of ``a`` and ``b`` (``whole``) within ``contact_mm`` of
    ``others`` in the last frame? In contact a partner's points confound the evidence (the 10
    hugging performers lost a boot to a triangle exchange without this)."""
    seg = np.flatnonzero((new >= 0) & (tpl.whole[a] | tpl.whole[b]))
    seg = np.union1d(seg, [a, b])
    return _touches(hist[new[seg], -1], others, contact_mm)


def _touches(points: np.ndarray, others: np.ndarray | None, contact_mm: float) -> bool:
    """Is one of ``points`` within ``contact_mm`` of ``others`` (other subjects' labeled
    points; untracked points, NaN, are never near)? ``contact_mm`` 0: everywhere (any other
    subject labeled), as ``BootConfig.verify_contact_mm`` says."""
    if others is None or others.shape[0] == 0:
        return False
    if contact_mm <= 0:
        return True
    with np.errstate(invalid="ignore"):
        near = np.linalg.norm(points[:, None] - others[None], axis=2)
    return bool(np.any(near < contact_mm))


def _window_consistent(tpl: _Template, new: np.ndarray, hist: np.ndarray, a: int, b: int) -> bool:
    """After exchanging ``a`` and ``b`` (reading ``new``), does each keep every pair of one
    trained body (``strict``) to the placed markers within its tolerance in
    ``WINDOW_EXCHANGE_SHARE`` of the window frames that track both points? An exchange inside
    a triangle that leaves a pair off only makes a reading the model contradicts either way
    less wrong."""
    have = np.flatnonzero(new >= 0)
    two = np.isin(have, [a, b])
    seg = two | tpl.whole[a, have] | tpl.whole[b, have]
    P = hist[new[have]]  # (k, W, 3)
    both = np.all(np.isfinite(P[two, :, 0]), axis=0)
    if not both.any():
        return False
    ok = 0
    for t in np.flatnonzero(both):
        bad, good = _strict_off(tpl, have, P[:, t])
        ok += not bad[seg].any() and bool(np.all(good[two] >= 2))
    return ok >= WINDOW_EXCHANGE_SHARE * both.sum()


def _doubtful(tpl: _Template, have: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Per placed marker ``have[i]`` on ``pos[i]`` (last frame): two or more of its pairs of
    one trained body (``strict``) to the other placed markers off their tolerance, more than
    within it (a marker whose point is untracked in that frame is never doubtful)."""
    return _doubtful_counts(*_strict_off(tpl, have, pos))


def _doubtful_counts(bad: np.ndarray, good: np.ndarray) -> np.ndarray:
    """Doubtful from :func:`_strict_off`'s counts: two or more pairs off, more than within."""
    return (bad >= 2) & (bad > good)


def _still_doubtful(tpl: _Template, new: np.ndarray, hist: np.ndarray, a: int, b: int) -> bool:
    """After exchanging ``a`` and ``b`` (reading ``new``), is either still doubtful in the last
    frame (:func:`_doubtful`)? An exchange that only makes a reading less wrong (a model whose
    arm pairs the stream contradicts either way) is no evidence for it."""
    have = np.flatnonzero(new >= 0)
    return bool(_doubtful(tpl, have, hist[new[have], -1])[np.isin(have, [a, b])].any())


def _plate_symmetries(tpl: _Template) -> list[tuple[np.ndarray, list[np.ndarray]]]:
    """``(markers, perms)`` per segment (:func:`_segments`: a head plate the trainer split into
    two triangles is one) of 4 to ``PLATE_MAX`` markers that has any: the permutations that
    move every marker, keep every trained distance among them within its tolerance and turn it
    by at least ``HALF_TURN_DEG`` (the rotation of its shape, embedded from the trained
    distances, onto the permuted shape): the segment's points read with ``markers[k]`` on the
    point of ``markers[perm[k]]`` fit it as well, in a pose no joint reaches (a rectangular
    head plate turned half round; turned over, it also reverses its chirality, which
    :func:`_window_symmetries` refuses). A quarter turn of a square plate is left out: a
    dancer's head yawed 90 degrees read its square plate a quarter round better than right,
    and the reading was taken (its four markers wrong for 245 frames, tune23 ``rate``)."""
    out: list[tuple[np.ndarray, list[np.ndarray]]] = []
    for mk in tpl.segments:
        if not 4 <= mk.size <= PLATE_MAX or not np.all(np.isfinite(tpl.D[np.ix_(mk, mk)])):
            continue
        D = tpl.D[np.ix_(mk, mk)]
        tol = tpl.tol[np.ix_(mk, mk)]
        shape = _embed(D)
        perms = []
        for perm in itertools.permutations(range(mk.size)):
            q = np.asarray(perm)
            if np.any(q == np.arange(mk.size)):
                continue  # (a marker on the axis: a forearm turned about itself, its wrist bar)
            if not np.all(np.abs(D - D[np.ix_(q, q)]) <= tol):
                continue
            R = _kabsch_batch(shape, shape[q][None])[0][0]
            if np.degrees(rotation_angle(R)) >= HALF_TURN_DEG:
                perms.append(q)
        if perms:
            out.append((mk, perms))
    return out


def _embed(D: np.ndarray) -> np.ndarray:
    """``(k, 3)`` points whose distances are ``D (k, k)`` as nearly as three dimensions allow
    (classical multidimensional scaling; mirror-image arbitrary)."""
    k = D.shape[0]
    J = np.eye(k) - 1.0 / k
    B = -0.5 * J @ (D**2) @ J
    w, V = np.linalg.eigh(B)
    top = np.argsort(w)[::-1][:3]
    return V[:, top] * np.sqrt(np.maximum(w[top], 0.0))


def _window_symmetries(tpl: _Template, assign: np.ndarray, hist: np.ndarray) -> np.ndarray:
    """Subject ``tpl``'s reading ``assign`` with a symmetric segment (:func:`_plate_symmetries`)
    read the other way round where the rest of the subject says so along the window (``hist
    (N, W, 3)``), judged as :func:`_window_mirrors` judges a mirror: by more than
    ``EXCHANGE_MARGIN`` in ``WINDOW_EXCHANGE_SHARE`` of the frames that track its points (at
    least half the window), by ``WINDOW_EXCHANGE_NATS`` in the median, reversing no thick
    chirality quadruple; the best such reading of a segment is taken. Its own distances cannot
    tell: a hugging performer's head plate booted turned half round (front markers on the back
    ones' points) stayed so for the whole 10 s of ``bench latency --start boot``, and neither
    the pair exchange (no pair of the plate is off) nor the re-verification's left-right
    exchanges (front and back differ too) could read it back. Unlike a mirror's exchange, not
    refused in contact with other performers: that head was within 72-139 mm of a partner's
    points throughout, and a half turn is no pose to be fooled by (simulated hugs of 5 and 10
    performers and a pile of 4: the same labels with the contact rule and without).
    Returns ``assign`` itself when nothing changes, else a new reading."""
    out = assign
    w = hist.shape[1]
    for mk, perms in tpl.symmetric:
        if np.any(out[mk] < 0):
            continue
        frames = np.flatnonzero(np.all(np.isfinite(hist[out[mk], :, 0]), axis=0))
        base = out.copy()
        base[mk] = -1
        if frames.size < max(2, w // 2) or not np.any(base >= 0):
            continue
        now = np.array([_pair_error(tpl, mk, out[mk], base, hist[:, f]) for f in frames])
        best, best_gain = None, WINDOW_EXCHANGE_NATS
        for perm in perms:  # (the best reading of the segment, not the first better one)
            turned = out.copy()
            turned[mk] = out[mk[perm]]
            gain = now - np.array(
                [_pair_error(tpl, mk, turned[mk], base, hist[:, f]) for f in frames]
            )
            if _window_wins(tpl, out, turned, gain, hist, best_gain):
                best, best_gain = turned, float(np.median(gain))
        if best is not None:
            out = best
    return out


def _window_mirrors(
    tpl: _Template,
    assign: np.ndarray,
    hist: np.ndarray,
    others: np.ndarray | None = None,
    contact_mm: float = 0.0,
) -> np.ndarray:
    """Subject ``tpl``'s reading ``assign`` with mirror segments (:func:`_mirror_pairs`) read
    on each other's points exchanged (:func:`_swap_mirrors`' exchange), judged along the window
    (``hist (N, W, 3)``, the tracks of the current points) as :func:`_window_exchange` judges
    a pair: a segment's own distances cannot tell left from right, and a boot that read a
    performer's arms in a near-symmetric pose keeps the mirror while the labeler tracks both.
    The exchange must fit the rest of the subject better by more than ``EXCHANGE_MARGIN`` in
    ``WINDOW_EXCHANGE_SHARE`` of the window frames that track every point of the two segments
    (at least half the window), by ``WINDOW_EXCHANGE_NATS`` in the median, and reverse no thick
    chirality quadruple. Only mirror pairs named as left and right twins (``tpl.sided``) are
    looked at, and not while a point of the two segments is within ``contact_mm`` of
    ``others`` (other subjects' labeled points, last frame): in contact the rest of the subject
    is no steady reference (a 5-person simulated hug lost 2.8 points of its labels to such
    exchanges). Returns ``assign`` itself when nothing changes, else a new reading."""
    out = assign
    w = hist.shape[1]
    for s1, s2 in tpl.sided:
        ex = _mirror_exchange(out, s1, s2)
        if ex is None:
            continue
        _, placed, swapped, base, other = ex
        if _touches(hist[out[placed], -1], others, contact_mm):
            continue
        tracked = np.all(np.isfinite(hist[out[placed], :, 0]), axis=0)
        frames = np.flatnonzero(tracked)
        if frames.size < max(2, w // 2):
            continue
        gain = np.array(
            [
                _pair_error(tpl, placed, out[placed], base, hist[:, f])
                - _pair_error(tpl, other, swapped[other], base, hist[:, f])
                for f in frames
            ]
        )
        if _window_wins(tpl, out, swapped, gain, hist):
            out = swapped
    return out


def _window_wins(
    tpl: _Template,
    out: np.ndarray,
    new: np.ndarray,
    gain: np.ndarray,
    hist: np.ndarray,
    nats: float = WINDOW_EXCHANGE_NATS,
) -> bool:
    """The window's verdict for reading ``new`` instead of ``out`` (mirrors, symmetries):
    ``gain`` (nats per tracked frame) above ``EXCHANGE_MARGIN`` in ``WINDOW_EXCHANGE_SHARE`` of
    the frames and above ``nats`` in the median, and no thick chirality quadruple reversed."""
    return bool(
        np.mean(gain > EXCHANGE_MARGIN) >= WINDOW_EXCHANGE_SHARE
        and np.median(gain) > nats
        and not _changed_reversed(tpl, out, new, hist[:, -1])
    )
