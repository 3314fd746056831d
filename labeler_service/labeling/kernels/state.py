"""The online labeler's state as named structures (struct of arrays), and their builders.

The per-frame entry :func:`.step._process_frame` takes one frame (points, ``dt``, ring slot,
frame number) and five structures, each a :class:`typing.NamedTuple` of arrays that numba
passes as one argument and reads by field name (``tracks.x``, not ``t[3]``):

============  ==========================================================  ==========
structure     holds                                                        rows
============  ==========================================================  ==========
``Tracks``    per-marker motion state (Kalman filter, Eq. 3-4) and the     M markers
              bookkeeping of each track (age, rejections, last state)
``Bodies``    the structure model: rigid bodies, ``D``, ``A`` (Eq. 1-2,    B bodies
              Eq. 5) and their sliding window
``Recovery``  per-marker recovery set and its reference snapshot          M markers
              (Sec. 3.3)
``Scratch``   buffers rewritten every frame (gate candidates, the         M, N
              assignment, Algorithm 1 and Kabsch work space)
``Params``    every setting (:mod:`.params`, built from ``LabelerConfig``)  scalars
============  ==========================================================  ==========

The arrays are allocated once, by the ``new_*`` builders below, and updated in place by the
kernels: no allocation per frame. Each structure is also the argument of the smaller kernels
that need most of it (``_fit_bodies(bodies, ...)``, ``_verify(..., tracks, recovery, scratch,
params)``); leaf kernels that a plain-numpy twin checks (Kalman, gate, Kabsch) keep plain arrays.
**A helper called per marker, per member or per candidate takes the arrays it reads, never a
structure**: numba passes a structure as every one of its fields, 100-400 ns a call (the lost
markers' placement, ``.unseen._wanted``, cost 0.3 ms of a 1.25 ms frame at 10 performers that
way; :func:`.unseen._want` gathers such arrays once per frame).

**Adding state touches one place**: a field in the NamedTuple and its allocation in the
builder next to it (the Labeler and the tests build structures only through the builders);
numba compiles for the new type on first use, and every kernel that receives the structure can
read the field. Where future state goes is said in each docstring. (A new *nested* structure
also needs its name back in :func:`.step._process_frame_fields`, as ``Scratch.fit`` has.)

Sentinels of the assignment (``Scratch.assigned``, ``owner``) and marker states are named
module constants (numba reads module-level ints as compile-time constants): ``UNDECIDED``,
``NONE`` here, ``MISSING``/``OBSERVED``/``RECOVERED`` from
:class:`~labeler_service.labeling.frame.MarkerState`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

MAX_BODY = 8  # markers per rigid body and per recovery set (the marker itself and 7 neighbours)
UNDECIDED = -2  # ``assigned[m]``: not decided yet by Algorithm 1 (searched again)
NONE = -1  # ``assigned[m]``: no point (missing); ``owner[j]``: no marker (unlabeled point)
MAX_CAND = 12  # candidate points of one template fit (:mod:`.repair`)


class Tracks(NamedTuple):
    """Per-marker state, ``M`` rows in the labeler's marker order.

    - ``x (M, 6)``: Kalman state ``[x, y, z, vx, vy, vz]`` mm, mm/s (Eq. 3-4); a NaN row is a
      marker never seen (its first observation starts the track, :func:`.kalman._start_or_update`).
    - ``P (M, 3)``: the covariance, as the 2x2 block ``(p_pp, p_pv, p_vv)`` of ``P2 (x) I3``
      (exact for isotropic ``Q``, ``R``; :mod:`.kalman`).
    - ``q (M,)``: white-acceleration variance per axis (``Q`` of Eq. 3), learned per marker from
      the training window (1e6 for a marker without one).
    - ``active (M,)`` bool: the marker belongs to a body; an inactive marker is never predicted,
      gated or labeled.
    - ``age (M,)`` int64: frames observed in a row (a recovery snapshot needs ``snapshot_age``).
    - ``n_reject (M,)`` int64: 3D-check refusals in a row (at most ``reject_limit``).
    - ``state (M,)`` uint8: :class:`~labeler_service.labeling.frame.MarkerState` of the last
      frame: the output, and the next frame's "was this marker tracked".
    - ``pos (M, 3)`` float32: the position reported for the last frame (observed or recovered,
      NaN when missing); the output.
    - ``subj_ptr (S + 1,)``, ``subj_idx (M,)``: the markers of each subject (CSR), for the
      per-subject common-mode shift.
    - ``kx (M, 3)``: this frame's constant-velocity (Kalman) prediction, before the rigid-body
      prediction replaces it (:mod:`.motion`).
    - ``lost (M,)`` int64: frames missing in a row; ``gone (M,)`` bool: every marker of the
      marker's subject has been missing for ``absent_frames`` frames, or fewer than
      ``presence_min_markers`` of them were observed in the previous frame (the subject left: no
      wide re-acquisition from stale predictions; :func:`.step._absent`).
    - ``anc (M, 2)`` int64: the two anchors of each marker (observed co-members with the most
      rigid window links) at its last observation, -1 none; ``anc_ref (M, 3, 3)``: the positions
      of the marker and its two anchors then; ``anc_cost (M, 2)``: their links' window
      ``A + w D`` (anchored coasting, :mod:`.anchor`).
    - ``subj (M,)`` int64: the marker's subject (row of ``subj_ptr``).
    - Contacts between performers (:mod:`.contact`): ``ct_with (M,)`` int64 the marker of
      another subject whose point came within ``contact_mm`` (-1 none; both markers point at
      each other); ``ct_t (M,)`` seconds since the contact (on the pair's lower marker);
      ``ct_ref (M, 8, 3)`` the marker's recovery snapshot from before the contact.
    - ``seen_at (M,)`` int64: the last frame number in which the marker was observed, -1
      never; ``track_from (M,)`` int64: the frame its track through that observation began
      (observed in every frame since, each point within ``max(jump_mm, 2 sqrt(P + r))`` of the
      prediction; negative: in labeled frames before the labeler's first; :mod:`.anonymous`).
      Both -1 again when the marker is reset (``Labeler._reset``).
    - ``fol (M, 7)``: the point a lost marker's own point went on as (followed from frame to
      frame while unambiguous and free): its position and velocity (mm/s) in the last frame,
      and the frames followed (column 6; 0 none; :mod:`.follow`).
    - ``pair_wait (M,)`` int64: the body partner the pair check's senior anchors asked to give
      the marker's point to in the last frame, -1 none (:func:`.repair._pair_check`).

    Per-marker state of later work goes here: swap-repair bookkeeping (frames since a marker was
    last exchanged, the marker it was exchanged with), a per-marker confidence.
    """

    x: np.ndarray
    P: np.ndarray
    q: np.ndarray
    active: np.ndarray
    age: np.ndarray
    n_reject: np.ndarray
    state: np.ndarray
    pos: np.ndarray
    subj_ptr: np.ndarray
    subj_idx: np.ndarray
    kx: np.ndarray
    lost: np.ndarray
    gone: np.ndarray
    anc: np.ndarray
    anc_ref: np.ndarray
    anc_cost: np.ndarray
    subj: np.ndarray
    ct_with: np.ndarray
    ct_t: np.ndarray
    ct_ref: np.ndarray
    seen_at: np.ndarray
    track_from: np.ndarray
    pair_wait: np.ndarray
    fol: np.ndarray


def new_tracks(q: np.ndarray, active: np.ndarray, groups: Sequence[Sequence[int]]) -> Tracks:
    """Tracks of ``len(q)`` markers, none started; ``groups`` = marker indices per subject."""
    m = q.shape[0]
    return Tracks(
        x=np.full((m, 6), np.nan),
        P=np.zeros((m, 3)),
        q=np.ascontiguousarray(q, dtype=np.float64),
        active=np.ascontiguousarray(active, dtype=np.bool_),
        age=np.zeros(m, dtype=np.int64),
        n_reject=np.zeros(m, dtype=np.int64),
        state=np.zeros(m, dtype=np.uint8),
        pos=np.full((m, 3), np.nan, dtype=np.float32),
        subj_ptr=np.cumsum([0] + [len(g) for g in groups]).astype(np.int64),
        subj_idx=np.array([i for g in groups for i in g], dtype=np.int64),
        kx=np.full((m, 3), np.nan),
        lost=np.zeros(m, dtype=np.int64),
        gone=np.zeros(m, dtype=np.bool_),
        anc=np.full((m, 2), -1, dtype=np.int64),
        anc_ref=np.full((m, 3, 3), np.nan),
        anc_cost=np.zeros((m, 2)),
        subj=_subjects(m, groups),
        ct_with=np.full(m, -1, dtype=np.int64),
        ct_t=np.zeros(m),
        ct_ref=np.full((m, MAX_BODY, 3), np.nan),
        seen_at=np.full(m, -1, dtype=np.int64),
        track_from=np.full(m, -1, dtype=np.int64),
        pair_wait=np.full(m, -1, dtype=np.int64),
        fol=np.zeros((m, 7)),
    )


def _subjects(m: int, groups: Sequence[Sequence[int]]) -> np.ndarray:
    """Marker -> subject (its group's row; -1 for a marker in no group)."""
    subj = np.full(m, -1, dtype=np.int64)
    for s, g in enumerate(groups):
        for i in g:
            subj[i] = s
    return subj


class Bodies(NamedTuple):
    """The structure model (Sec. 3.2): ``B`` rigid bodies of at most ``MAX_BODY`` markers.

    - ``members (B, 8)`` int32: the body's marker indices, ``-1`` after ``size[b]``; body
      position ``k`` indexes the rows and columns of ``D[b]``, ``A[b]``.
    - ``size (B,)`` int32.
    - ``D (B, 8, 8)``, ``A (B, 8, 8)``: mean and deviation of each marker-pair distance, mm,
      symmetric (Eq. 1-2 over the sliding window, the trained values until a link has
      ``min_window_samples`` samples); read by the score Eq. 5. NaN = unknown link.
    - ``D0``, ``A0``: the trained (template) values.
    - ``mb_ptr (M + 1,)``, ``mb_idx``: marker -> bodies containing it (CSR), for Algorithm 1's
      "which bodies must search again".
    - ``ring (B, 8, 8, T)`` float32: the window's last ``T`` distances per link (NaN = not
      both observed); ``s1``, ``s2 (B, 8, 8)``: running sums of the distances and their
      squares; ``cnt (B, 8, 8)`` int64: samples in the window (:mod:`.window`).
    - Rigid-body prediction (:mod:`.motion`): ``mpos (B, 8, 3)`` the members observed in the
      last frame (NaN otherwise); ``R (B, 3, 3)``, ``t (B, 3)`` the last inter-frame rigid
      motion, ``moving (B,)`` bool: it was measured (3+ members in both frames),
      ``motion_dt (B,)`` over which interval (s); ``pred (B, 8, 3)`` this frame's prediction of
      each member; ``err (B, 8)``, ``kerr (B, 8)`` running mean squared error per axis (mm^2)
      of the body's and of the Kalman prediction of each member (NaN = no record).

    - ``ref (B, 8, 3)``: the body's reference shape (its members' positions when last fully
      observed and consistent), ``ref_ok (B,)`` bool: it has one; ``ref_model (B,)`` bool: it
      is still the trained shape of a labeler started from a model (the body was never seen
      whole in the stream); ``ok (B,)`` bool: the
      current assignment passed the 3D template check (the guard of Eq. 1-2);
      ``pending (B,)`` int64: consecutive checks a better permutation was found
      (:mod:`.repair`); ``work_*``: the template fit's work space (rewritten every frame).

    Per-body state of later work goes here: boot from templates, its pose (``R``, ``t``) and
    linear/angular velocity for rigid-body pose prediction.
    """

    members: np.ndarray
    size: np.ndarray
    D: np.ndarray
    A: np.ndarray
    D0: np.ndarray
    A0: np.ndarray
    mb_ptr: np.ndarray
    mb_idx: np.ndarray
    ring: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    cnt: np.ndarray
    mpos: np.ndarray
    R: np.ndarray
    t: np.ndarray
    moving: np.ndarray
    motion_dt: np.ndarray
    pred: np.ndarray
    err: np.ndarray
    kerr: np.ndarray
    ref: np.ndarray
    ref_ok: np.ndarray
    ref_model: np.ndarray
    ok: np.ndarray
    pending: np.ndarray
    work_cur: np.ndarray
    work_pts: np.ndarray
    work_cand: np.ndarray
    work_best: np.ndarray
    work_pos: np.ndarray
    work_choice: np.ndarray
    work_used: np.ndarray
    work_tol: np.ndarray
    work_centre: np.ndarray


def new_bodies(
    n_markers: int,
    bodies: Sequence[Sequence[int]],
    D0: Sequence[np.ndarray],
    A0: Sequence[np.ndarray],
    T: int,
) -> Bodies:
    """Bodies from their marker lists and trained ``(k, k)`` ``D0``, ``A0``; an empty window
    of ``T`` frames (``D``, ``A`` start at the trained values)."""
    nb = len(bodies)
    members = np.full((nb, MAX_BODY), -1, dtype=np.int32)
    size = np.zeros(nb, dtype=np.int32)
    d0 = np.full((nb, MAX_BODY, MAX_BODY), np.nan)
    a0 = np.full((nb, MAX_BODY, MAX_BODY), np.nan)
    for b, body in enumerate(bodies):
        k = len(body)
        members[b, :k] = body
        size[b] = k
        d0[b, :k, :k] = D0[b]
        a0[b, :k, :k] = A0[b]
    # marker -> bodies (CSR)
    counts = np.zeros(n_markers + 1, dtype=np.int64)
    for body in bodies:
        for i in body:
            counts[i + 1] += 1
    mb_ptr = np.cumsum(counts).astype(np.int64)
    mb_idx = np.zeros(max(1, int(mb_ptr[-1])), dtype=np.int32)
    fill = mb_ptr[:-1].copy()
    for b, body in enumerate(bodies):
        for i in body:
            mb_idx[fill[i]] = b
            fill[i] += 1
    return Bodies(
        members=members,
        size=size,
        D=d0.copy(),
        A=a0.copy(),
        D0=d0,
        A0=a0,
        mb_ptr=mb_ptr,
        mb_idx=mb_idx,
        ring=np.full((nb, MAX_BODY, MAX_BODY, T), np.nan, dtype=np.float32),
        s1=np.zeros((nb, MAX_BODY, MAX_BODY)),
        s2=np.zeros((nb, MAX_BODY, MAX_BODY)),
        cnt=np.zeros((nb, MAX_BODY, MAX_BODY), dtype=np.int64),
        mpos=np.full((nb, MAX_BODY, 3), np.nan),
        R=np.zeros((nb, 3, 3)),
        t=np.zeros((nb, 3)),
        moving=np.zeros(nb, dtype=np.bool_),
        motion_dt=np.zeros(nb),
        pred=np.full((nb, MAX_BODY, 3), np.nan),
        err=np.full((nb, MAX_BODY), np.nan),
        kerr=np.full((nb, MAX_BODY), np.nan),
        ref=np.zeros((nb, MAX_BODY, 3)),
        ref_ok=np.zeros(nb, dtype=np.bool_),
        ref_model=np.zeros(nb, dtype=np.bool_),
        ok=np.ones(nb, dtype=np.bool_),
        pending=np.zeros(nb, dtype=np.int64),
        work_cur=np.zeros(MAX_BODY, dtype=np.int64),
        work_pts=np.zeros((MAX_CAND, 3)),
        work_cand=np.zeros(MAX_CAND, dtype=np.int64),
        work_best=np.zeros(MAX_BODY, dtype=np.int64),
        work_pos=np.zeros(MAX_BODY, dtype=np.int64),
        work_choice=np.zeros(MAX_BODY, dtype=np.int64),
        work_used=np.zeros(MAX_CAND, dtype=np.bool_),
        work_tol=np.zeros((MAX_BODY, MAX_BODY)),
        work_centre=np.zeros(3),
    )


class Recovery(NamedTuple):
    """Recovery sets (Sec. 3.3), ``M`` rows: each body marker and its most rigidly linked
    neighbours (lowest ``A + w D``, :mod:`.rigid`).

    - ``members (M, 8)`` int64: ``members[m, 0] == m``, then up to 7 neighbours, ``-1`` after
      ``size[m]``; ``size (M,)`` int64 (0 for a marker without a body).
    - ``ref (M, 8, 3)``: the members' positions the last time all of them had been observed
      for ``snapshot_age`` frames in a row (the reference a hidden marker is estimated from);
      while that cannot happen, a partial snapshot: the marker and 3+ members, NaN rows for
      the others (:func:`.rigid._snapshot`).
    - ``ok (M,)`` bool: ``ref[m]`` holds a snapshot.
    """

    members: np.ndarray
    size: np.ndarray
    ref: np.ndarray
    ok: np.ndarray


def new_recovery(n_markers: int) -> Recovery:
    """Empty recovery sets (the Labeler fills ``members``, ``size``); no snapshot yet."""
    return Recovery(
        members=np.full((n_markers, MAX_BODY), -1, dtype=np.int64),
        size=np.zeros(n_markers, dtype=np.int64),
        ref=np.zeros((n_markers, MAX_BODY, 3)),
        ok=np.zeros(n_markers, dtype=np.bool_),
    )


class FitScratch(NamedTuple):
    """Work space of Algorithm 1 (:func:`.fitting._fit_bodies`).

    Per body: ``score (B,)`` Eq. 5 score of its best assignment (-1 = not searched),
    ``satisfied (B,)``, ``need (B,)`` (queued for a search), ``best (B, 8)`` the point of each
    body position in its best assignment. ``pm_idx (M K,)``: point -> markers CSR entries. Per
    search (:func:`.fitting._search_body`; ``K + 1`` options per marker): ``perm``, ``opts``,
    ``nopts``, ``mot``, ``choice``, ``partial (18,)``, ``best_choice``.
    """

    score: np.ndarray
    pm_idx: np.ndarray
    satisfied: np.ndarray
    need: np.ndarray
    best: np.ndarray
    perm: np.ndarray
    opts: np.ndarray
    nopts: np.ndarray
    mot: np.ndarray
    choice: np.ndarray
    partial: np.ndarray
    best_choice: np.ndarray


def new_fit_scratch(n_markers: int, n_bodies: int, K: int) -> FitScratch:
    """:class:`FitScratch` for ``n_bodies`` bodies and ``K`` candidates per marker."""
    return FitScratch(
        score=np.zeros(n_bodies),
        pm_idx=np.zeros(max(1, n_markers * K), dtype=np.int32),
        satisfied=np.zeros(n_bodies, dtype=np.bool_),
        need=np.zeros(n_bodies, dtype=np.bool_),
        best=np.zeros((n_bodies, MAX_BODY), dtype=np.int32),
        perm=np.zeros(MAX_BODY, dtype=np.int64),
        opts=np.zeros((MAX_BODY, K + 1), dtype=np.int64),
        nopts=np.zeros(MAX_BODY, dtype=np.int64),
        mot=np.zeros((MAX_BODY, K + 1)),
        choice=np.zeros(MAX_BODY, dtype=np.int64),
        partial=np.zeros(2 * MAX_BODY + 2),
        best_choice=np.zeros(MAX_BODY, dtype=np.int64),
    )


class KabschScratch(NamedTuple):
    """Buffers of one Kabsch fit over a recovery set: ``src (8, 3)`` reference positions,
    ``dst (8, 3)`` observed ones, ``R (3, 3)``, ``t (3,)`` the fit (:func:`.rigid._kabsch`)."""

    src: np.ndarray
    dst: np.ndarray
    R: np.ndarray
    t: np.ndarray


def new_kabsch_scratch() -> KabschScratch:
    return KabschScratch(
        src=np.zeros((MAX_BODY, 3)), dst=np.zeros((MAX_BODY, 3)), R=np.zeros((3, 3)), t=np.zeros(3)
    )


class Scratch(NamedTuple):
    """Buffers rewritten every frame (their content means nothing between frames, except
    ``owner``, the last frame's answer).

    - ``s (M,)``: innovation variance ``S = p_pp + r`` of the gate (Sec. 3.1), floored at
      ``s_min``; in the wide re-acquisition pass, each lost marker's search radius (mm).
    - ``cand (M, K)`` int32, ``cand_d2 (M, K)``, ``ncand (M,)`` int32: each marker's gated
      candidate points, best first, and their squared Mahalanobis distances.
    - ``assigned (M,)`` int32: marker -> point, or ``NONE`` (missing), ``UNDECIDED``.
    - ``owner (N,)`` int32: point -> marker or ``NONE``; the first ``N`` entries (this frame's
      points) are the answer ``point_labels``. Grown when a frame has more points.
    - ``obs (M, 3)``: observed positions of this frame (NaN rows otherwise);
      ``rec (M, 3)``: recovered positions (or re-acquisition centres);
      ``has_rec (M,)`` int64: neighbours a recovery used (0 = none);
      ``missing (M,)`` bool: to recover (also the scratch flag of the re-acquisition pass and
      of the 3D check); ``anchored (M,)`` bool: searched around its anchored estimate in the
      re-acquisition pass (kernels/anchor.py).
    - ``cm_buf (3, M)``, ``cm_shift (S, 3)``: the common-mode shift's offsets and result.
    - ``ct_near (M,)`` int64, ``ct_dn (M,)``: each marker's nearest new contact partner and its
      distance (:func:`.contact._contacts`).
    - Anonymous point tracks (:mod:`.anonymous`; kept between frames): ``anon (N,)`` int64
      the frames in a row this frame's point ``j`` was unlabeled before (0: none, or not
      followed), ``avel (N, 3)`` its velocity (mm/s); ``pprev (N, 3)``, ``pvel (N, 3)``,
      ``panon (N,)`` the same of the last frame's points, carried on; ``pinfo (2,)`` int64 how
      many there were and their frame number. Grown (emptied) with ``owner``.
    - ``fit``: :class:`FitScratch`; ``kab``: :class:`KabschScratch`.
    """

    s: np.ndarray
    cand: np.ndarray
    cand_d2: np.ndarray
    ncand: np.ndarray
    assigned: np.ndarray
    owner: np.ndarray
    obs: np.ndarray
    rec: np.ndarray
    has_rec: np.ndarray
    missing: np.ndarray
    anchored: np.ndarray
    cm_buf: np.ndarray
    cm_shift: np.ndarray
    ct_near: np.ndarray
    ct_dn: np.ndarray
    anon: np.ndarray
    avel: np.ndarray
    pprev: np.ndarray
    pvel: np.ndarray
    panon: np.ndarray
    pinfo: np.ndarray
    fit: FitScratch
    kab: KabschScratch


def new_scratch(n_markers: int, n_bodies: int, n_subjects: int, K: int, n_points: int) -> Scratch:
    """:class:`Scratch` for frames of up to ``n_points`` points (see :func:`grow_scratch`)."""
    m = n_markers
    return Scratch(
        s=np.zeros(m),
        cand=np.zeros((m, K), dtype=np.int32),
        cand_d2=np.zeros((m, K)),
        ncand=np.zeros(m, dtype=np.int32),
        assigned=np.zeros(m, dtype=np.int32),
        owner=np.zeros(n_points, dtype=np.int32),
        obs=np.full((m, 3), np.nan),
        rec=np.full((m, 3), np.nan),
        has_rec=np.zeros(m, dtype=np.int64),
        missing=np.zeros(m, dtype=np.bool_),
        anchored=np.zeros(m, dtype=np.bool_),
        cm_buf=np.zeros((3, m)),
        cm_shift=np.zeros((n_subjects, 3)),
        ct_near=np.full(m, -1, dtype=np.int64),
        ct_dn=np.zeros(m),
        **_point_tracks(n_points),
        fit=new_fit_scratch(m, n_bodies, K),
        kab=new_kabsch_scratch(),
    )


def fields(structure: tuple) -> tuple:
    """``structure`` as a plain tuple of its fields, nested structures too (the same arrays):
    how the Labeler passes the state to :func:`.step._process_frame_fields`, which names them
    again at compile time."""
    return tuple(fields(v) if isinstance(v, tuple) else v for v in structure)


def _point_tracks(n_points: int) -> dict[str, np.ndarray]:
    """The anonymous point tracks of :class:`Scratch` for frames of up to ``n_points`` points,
    empty."""
    n = n_points
    return {
        "anon": np.zeros(n, dtype=np.int64),
        "avel": np.zeros((n, 3)),
        "pprev": np.zeros((n, 3)),
        "pvel": np.zeros((n, 3)),
        "panon": np.zeros(n, dtype=np.int64),
        "pinfo": np.zeros(2, dtype=np.int64),
    }


def grow_scratch(scratch: Scratch, n_points: int) -> Scratch:
    """``scratch`` with room for frames of ``n_points`` points (the point tracks start
    again)."""
    return scratch._replace(owner=np.zeros(n_points, dtype=np.int32), **_point_tracks(n_points))
