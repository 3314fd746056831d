"""Boot: which anonymous points belong to which subject, and which marker each is.

A live capture has no labels. :func:`boot` takes a model (one
:class:`~labeler_service.labeling.templates.SubjectTemplate` per subject) and a short window of
anonymous frames, tracked point by point (:class:`PointTracker`), and labels the points of the
window's last frame. The structure model of seed 003 (Sec. 3.1: rigid bodies, marker-pair
distance means ``D`` and deviations ``A``) is all it uses; no pose is assumed.

Order:

1. **Tracks** (:class:`PointTracker`): nearest neighbour with constant-velocity prediction,
   mutual and gated (a few mm at 120 Hz), so every point of the last frame carries its own
   trajectory over the window. Points tracked for less than ``min_track_fraction`` of the
   window are not considered (short-lived ghosts, points just born).
2. **Body candidates by distance signature**: every rigid body of every template has up to
   ``anchors_per_body`` *anchor triangles* (three of its markers with long, rigid, distinct
   pair distances). All point pairs closer than the longest anchor edge are listed once
   (KD-tree) and sorted by distance; an anchor edge ``(i, j)`` selects the pairs within
   ``D_ij +- tol_ij`` by binary search (``tol = tol_mm + tol_sigma A + tol_relative D``: noise,
   soft tissue, a small body-size difference), and a join on the shared vertices gives the
   candidate triangles. No combinatorial search over point subsets happens.
3. **3D verification**: each triangle is registered to the body's reference shape (Kabsch,
   proper rotation), the body's other markers are predicted and matched to the nearest points
   within ``fit_mm`` (up to ``body_hidden`` may be missing, three must remain), and the
   candidate's pair distances must hold along the tracks (distance constancy).
4. **Node graph** (:class:`_Graph`, rows in numba): candidates become (marker, point) nodes;
   pairs of nodes *agree* (a rigid pair, ``A + rigid_weight D <= rigid_a_mm``, at its distance),
   *clash* (one marker on two points, one point for two markers, a rigid pair off its
   distance, an articulated pair beyond its reach) or *link* (an articulated pair within its
   trained range ``D +- (tol_mm + link_sigma A)``).
5. **Hypotheses** (:func:`_hypotheses`): from each seed body (most rigid agreement first; every
   symmetric reading of the seed's points tried), the node with most agreements (at least
   ``min_support``) and no clash joins; when none is left, the body candidate of another
   segment with most links (soft count, ``link_fraction`` of its articulated pairs in range);
   then trilateration (:func:`_grow`), distance constancy along the tracks
   (:func:`_constancy`). A hypothesis needs ``min_fraction`` of its template's markers on that
   rigid evidence: a subject not seen enough is not guessed. Markers with no rigid evidence
   then join from their steadiest placed partners when exactly one free point fits
   (:func:`_articulate`); the readings of symmetric bodies and segments, mirror segments, pairs
   of markers and single markers (moved to free points) are decided by the subject's
   negative log-likelihood of its pair distances (:func:`_symmetries`, :func:`_readings`,
   :func:`_swap_mirrors`, :func:`_exchange`, :func:`_relocate`).
6. **Joint resolution** (:meth:`Booter.run`): hypotheses of all templates are taken greedily
   by score (markers explained, less their squared rigid and articulated distance errors);
   where two templates explain one performer the one with clearly lower rigid-distance RMS
   (``rms_ratio``) goes first (similar performers); a template is used once and a point goes to
   one subject only (a later hypothesis loses the points already taken and must still reach
   ``min_fraction``). Two performers with one template appear as hypotheses of each of the two
   identical templates; the greedy pass gives one to each, in an arbitrary but then fixed
   (continuity) order.

:class:`~labeler_service.labeling.booting.BootingLabeler` runs this on the stream and hands the
result to the online :class:`~labeler_service.labeling.labeler.Labeler`.

Modules: this one holds the public API (:class:`Booter`, :class:`BootResult`, :func:`boot`,
and re-exports the rest); ``boot_config.py`` the parameters (:class:`BootConfig`);
``boot_tracks.py`` step 1 (:class:`PointTracker`, :func:`track_history`,
:func:`labels_along_tracks`); ``boot_match.py`` steps 2-5 (templates, candidates, node graph,
hypotheses, readings, completion). Step 6 is :meth:`Booter.run`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from labeler_service.errors import LabelerError
from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.boot_match import (
    EXCHANGE_MARGIN,
    _complete,
    _complete_weak,
    _doubtful,
    _evidence,
    _fill,
    _free_readings,
    _hypotheses,
    _Hypothesis,
    _kabsch_batch,
    _Ledger,
    _ledger_exchange,
    _Pairs,
    _prepare,
    _reach,
    _score,
    _Template,
    _tied,
    _window_exchange,
    _window_mirrors,
    _window_symmetries,
    memo,
    warmup_kernels,
)
from labeler_service.labeling.boot_tracks import PointTracker, labels_along_tracks, track_history
from labeler_service.labeling.templates import LabelerModel, SubjectTemplate

__all__ = [
    "BootConfig",
    "BootResult",
    "Booter",
    "HypothesesShare",
    "PointTracker",
    "boot",
    "labels_along_tracks",
    "track_history",
    "warmup_kernels",
]


# ---------------------------------------------------------------------------- public API
#: ``share(booter, subjects, pts, hist, pairs)`` -> the hypotheses of ``subjects`` in their
#: order, as ``[booter.hypotheses(s, pts, hist, pairs) for s in subjects]`` concatenated
HypothesesShare = Callable[["Booter", list[int], np.ndarray, np.ndarray, _Pairs], list[_Hypothesis]]


@dataclass
class BootResult:
    """``labels[i]``: global marker index (into ``model.marker_names``) of input point ``i``,
    -1 unlabeled; ``subjects``: names of the subjects booted; ``scores``: their scores."""

    labels: np.ndarray
    subjects: list[str]
    scores: dict[str, float]


class Booter:
    """The boot of a model, prepared once (anchor triangles per body), run on windows."""

    def __init__(self, model: LabelerModel, config: BootConfig | None = None) -> None:
        self.model = model
        self.config = config or BootConfig()
        self._templates = _prepare(model, self.config)
        r = 0.0
        for tpl in self._templates:
            for body in tpl.bodies:
                for tri in body.anchors:
                    mk = body.markers[list(tri)]
                    for a, b in ((0, 1), (0, 2), (1, 2)):
                        r = max(r, float(tpl.D[mk[a], mk[b]] + tpl.tol[mk[a], mk[b]]))
        self._r_max = r
        #: per subject: its template knows nothing of some of its markers (no trained distance:
        #: never seen in the training frames, e.g. a labeled init window); see :meth:`extend`
        self._blind = [bool(np.any(_untrained(tpl))) for tpl in self._templates]
        #: per subject: evidence for exchanging pairs of its placed markers, summed over
        #: extensions (:func:`_ledger_exchange`)
        self._ledgers = [_Ledger.of(tpl.n) for tpl in self._templates]
        self._prepare_acquire()

    def _prepare_acquire(self) -> None:
        """Model-wide arrays for :meth:`acquire`: pairs of one trained body (``strict``), their
        ``D`` and tolerances, and per marker its bodies (global markers, reference shape)."""
        m = len(self.model.marker_names)
        strict = np.zeros((m, m), dtype=bool)
        d = np.full((m, m), np.nan)
        tol = np.full((m, m), np.inf)
        bodies: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(m)]
        for tpl in self._templates:
            sl = slice(tpl.offset, tpl.offset + tpl.n)
            strict[sl, sl] = tpl.strict
            d[sl, sl] = tpl.D
            tol[sl, sl] = tpl.tol
            for body in tpl.bodies:
                g = tpl.offset + body.markers
                for k in g:
                    bodies[k].append((g, body.shape))
        reach = np.where(strict, d + tol, 0.0)
        self._a_strict, self._a_D, self._a_tol, self._a_bodies = strict, d, tol, bodies
        self._a_reach = float(np.nanmax(reach)) if strict.any() else 0.0
        self._a_subject = np.repeat(
            np.arange(len(self._templates)), [t.n for t in self._templates]
        ).astype(np.int64)

    @property
    def templates(self) -> tuple[SubjectTemplate, ...]:
        return tuple(self.model.subjects)

    def run(
        self,
        points: np.ndarray,
        history: np.ndarray | None = None,
        *,
        free: np.ndarray | None = None,
        subjects: list[int] | None = None,
        share: HypothesesShare | None = None,
    ) -> BootResult:
        """Labels ``points (N, 3)`` (the window's last frame).

        ``history (N, W, 3)``: each point's track over the window (NaN where untracked; its
        last column is ``points``); without it the boot relies on one frame. ``free``: points
        that may be labeled (default all); ``subjects``: model subject indices to look for
        (default all). ``share``: computes the hypotheses of the subjects (each template's
        are a pure function of it and the points: :meth:`hypotheses`) with help, e.g. of
        another process (the service's boot worker); it returns them in the subjects' order.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = pts.shape[0]
        hist = pts[:, None, :] if history is None else np.asarray(history, dtype=np.float64)
        if hist.shape[0] != n or hist.ndim != 3 or hist.shape[2] != 3:
            raise LabelerError(f"history must be ({n}, W, 3), got {hist.shape}")
        ok = np.ones(n, dtype=bool) if free is None else np.asarray(free, dtype=bool).copy()
        w = hist.shape[1]
        tracked = np.isfinite(hist[:, :, 0]).sum(axis=1)
        ok &= tracked >= max(1, int(np.ceil(self.config.min_track_fraction * w)))
        idx = np.flatnonzero(ok)
        if idx.size < 3:
            return BootResult(np.full(n, -1, dtype=np.int64), [], {})
        sub_pts, sub_hist = pts[idx], hist[idx]
        pairs = self.pairs(sub_pts)
        wanted = list(range(len(self._templates)) if subjects is None else subjects)
        hyps: list[_Hypothesis] = []
        if share is not None:
            hyps = share(self, wanted, sub_pts, sub_hist, pairs)
        else:
            for s in wanted:
                hyps += self.hypotheses(s, sub_pts, sub_hist, pairs)
        # one performer explained by several templates (similar bodies): the template whose
        # rigid distances fit clearly better goes first, whatever the marker counts
        sets = [set(h.assign[h.assign >= 0].tolist()) for h in hyps]
        for i, hi in enumerate(hyps):
            for j, hj in enumerate(hyps):
                if hi.template == hj.template or i == j:
                    continue
                common = len(sets[i] & sets[j])
                if common > 0.5 * min(len(sets[i]), len(sets[j])) and (
                    hi.rms > self.config.rms_ratio * hj.rms
                ):
                    hi.score = min(hi.score, hj.score - 1.0)
        hyps.sort(key=lambda h: -h.score)
        taken = np.full(idx.size, -1, dtype=np.int64)  # the accepted hypothesis holding a point
        accepted: list[tuple[_Hypothesis, np.ndarray]] = []  # with its markers' rigid support
        used: set[int] = set()
        for h in hyps:
            if h.template in used:
                continue
            tpl = self._templates[h.template]
            assign = h.assign.copy()
            support = _rigid_support(tpl, assign, sub_pts)
            have = np.flatnonzero(assign >= 0)
            holder = taken[assign[have]]
            lost = np.zeros(have.size, dtype=bool)
            wins: list[tuple[int, int]] = []  # (accepted hypothesis, its marker) giving a point
            for k in np.flatnonzero(holder >= 0):
                other, o_sup = accepted[holder[k]]
                o_m = int(np.flatnonzero(other.assign == assign[have[k]])[0])
                # a contested point goes to the subject whose rigid evidence for it is
                # stronger: a performer's own chest marker (several rigid partners placed)
                # over a hugging partner's hand read on it (one or none)
                if support[have[k]] > o_sup[o_m] + 1:
                    wins.append((int(holder[k]), o_m))
                else:
                    lost[k] = True
            assign[have[lost]] = -1
            if int((assign >= 0).sum()) < self.config.boot_markers(tpl.n):
                continue
            for j, o_m in wins:
                other, _ = accepted[j]
                other.assign[o_m] = -1
            used.add(h.template)
            kept = assign >= 0
            taken[assign[kept]] = len(accepted)
            accepted.append((_Hypothesis(h.template, assign, h.score, h.rms), support))
        # a reading that gave points to later ones (their rigid evidence stronger) and kept
        # fewer than its boot count is not enough evidence any more: its subject waits
        accepted = [
            (h, s)
            for h, s in accepted
            if (h.assign >= 0).sum() >= self.config.boot_markers(self._templates[h.template].n)
        ]
        self._reclaim([h for h, _ in accepted], sub_pts, sub_hist)
        labels = np.full(n, -1, dtype=np.int64)
        booted: list[str] = []
        scores: dict[str, float] = {}
        for h, _ in accepted:
            tpl = self._templates[h.template]
            m = np.flatnonzero(h.assign >= 0)
            labels[idx[h.assign[m]]] = tpl.offset + m
            booted.append(tpl.name)
            scores[tpl.name] = _score(tpl, h.assign, sub_pts)
        return BootResult(labels, booted, scores)

    def hypotheses(
        self, subject: int, pts: np.ndarray, hist: np.ndarray, pairs: _Pairs | None = None
    ) -> list[_Hypothesis]:
        """The hypotheses of one subject on ``pts`` (the free tracked points of :meth:`run`,
        ``hist`` their tracks; ``pairs`` their :class:`_Pairs`, built when None)."""
        if pairs is None:
            pairs = self.pairs(pts)
        return _hypotheses(self._templates[subject], pts, hist, pairs, self.config)

    def pairs(self, pts: np.ndarray) -> _Pairs:
        """The point pairs :meth:`hypotheses` reads (within the longest anchor edge)."""
        return _Pairs(pts, self._r_max)

    def _reclaim(self, accepted: list[_Hypothesis], pts: np.ndarray, hist: np.ndarray) -> None:
        """Limbs read on another subject's points: each accepted subject is completed
        (:func:`_complete`) with the other subjects' points free; markers it then places on
        points another subject holds move to it when its model explains those points better
        given the rest of it (:func:`_evidence`, the readings' log-likelihood ratios: lower by
        more than ``EXCHANGE_MARGIN``), the holder's rigid pairs to the rest of it do not tie
        them clearly more (:func:`_tied`) and the loser keeps its 50 %. Two performers side by
        side: the hypotheses are grown per template, and one took the other's forearm and hand
        for its own hand through articulated links while the owner's hypothesis had left that
        arm out (no point was contested, so the resolution above never saw it)."""
        if len(accepted) < 2:
            return
        n = pts.shape[0]
        holder = np.full(n, -1, dtype=np.int64)
        for j, h in enumerate(accepted):
            holder[h.assign[h.assign >= 0]] = j
        for i, h in enumerate(accepted):
            tpl = self._templates[h.template]
            have = h.assign >= 0
            if have.all():
                continue
            # only another subject's points within this one's reach can be reclaimed
            centre = pts[h.assign[have]].mean(axis=0)
            near = np.linalg.norm(pts - centre, axis=1) <= tpl.extent
            if not np.any(near & (holder >= 0) & (holder != i)):
                continue
            grown = _complete(
                tpl, h.assign, pts, hist, np.zeros(n, dtype=bool), self.config, partial=True
            )
            fresh = np.flatnonzero((grown >= 0) & (h.assign < 0))
            if fresh.size == 0:
                continue
            owners = holder[grown[fresh]]
            for j in np.unique(owners[owners >= 0]):
                if j == i:
                    continue
                mine = fresh[owners == j]
                other = accepted[j]
                # the same points as the other subject's markers
                ot = self._templates[other.template]
                theirs = np.flatnonzero(np.isin(other.assign, grown[mine]))
                need = self.config.boot_markers(ot.n)
                if int((other.assign >= 0).sum()) - theirs.size < need:
                    continue
                # the likelihood of those points under each subject, given the rest of it,
                # against their being unrelated to it (:func:`_evidence`)
                ob = other.assign.copy()
                ob[theirs] = -1
                nll_mine = _evidence(tpl, mine, grown[mine], h.assign, pts)
                nll_theirs = _evidence(ot, theirs, other.assign[theirs], ob, pts)
                # and never against clearly stronger rigid evidence tying them to the rest of
                # their holder (the rule of the contested points above; :func:`_tied`): a
                # partner's hand, rigid with the rest of its hand, is not an upper-arm marker
                # that fits this subject's loose ranges
                tie_mine = _tied(tpl, mine, grown[mine], h.assign, pts)
                tie_theirs = _tied(ot, theirs, other.assign[theirs], ob, pts)
                if nll_mine < nll_theirs - EXCHANGE_MARGIN and tie_theirs <= tie_mine + 1:
                    other.assign[theirs] = -1
                    h.assign[mine] = grown[mine]
                    holder[grown[mine]] = i

    def extend(
        self,
        points: np.ndarray,
        history: np.ndarray,
        labels: np.ndarray,
        subjects: list[int],
        age: np.ndarray | None = None,
        checked: list[int] | tuple[int, ...] = (),
    ) -> np.ndarray:
        """Labels free points of subjects already labeled (:func:`_complete`): ``labels (N,)``
        global marker indices (-1 free) of ``points``, ``history (N, W, 3)`` their tracks; the
        subject's labeled points seed the node graph of its body candidates on the free tracked
        points near it (other segments join through their articulated links), then
        trilateration; new markers must keep their rigid distances along the tracks. With
        ``age (N,)`` (seconds each point's track has lived) the markers still missing then
        take free tracks at least ``fill_min_age_s`` old, judged jointly (:func:`_fill`).
        Labels already given are never changed, except that with ``age`` the completion and
        the fill may move a subject's weakly placed markers (:func:`_weak_markers`,
        :func:`_complete_weak`), and that the readings of the subjects ``checked`` (booted from
        the stream's points, not labeled by it) first have pairs of markers on each other's
        points exchanged back (:func:`_window_exchange` on the window's evidence,
        :func:`_ledger_exchange` on the evidence summed over calls since the two readings
        began, kept per subject in this booter). Returns the new labels (a copy).

        A subject whose template has untrained markers (no distance to any other: unseen in
        the training frames) cannot tell a free point near it from one of those: it gets only
        new markers with rigid evidence (two or more pairs of one trained body in place,
        :func:`_rigid_only`, the standard of :meth:`acquire`) and no joint fill (which reads
        every leftover point as a leftover *known* marker). Without this, the labeled start
        through the model-based labeler (init window's model; the BTS walker's scapula and
        bar markers never seen in it) put ``r heel`` on the ``r met`` point and ``SCR2`` on
        ``r bar 2`` for 50-190 frames (holdout07 ``half`` 96.20 -> 94.64 %)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        hist = np.asarray(history, dtype=np.float64)
        out = np.asarray(labels, dtype=np.int64).copy()
        w = hist.shape[1]
        taken0 = np.zeros(pts.shape[0], dtype=bool)
        tree = None  # (the frame's points, for the segments read again onto free points)
        for s in subjects:  # markers of one subject on each other's points (_window_exchange)
            if s not in checked:
                continue
            tpl = self._templates[s]
            assign, mine = _subject_assign(tpl, out)
            others = pts[(out >= 0) & ~mine]
            swapped = _window_exchange(tpl, assign, hist, others, self.config.verify_contact_mm)
            swapped = _window_mirrors(tpl, swapped, hist, others, self.config.verify_contact_mm)
            swapped = _window_symmetries(tpl, swapped, hist)
            # (markers the re-checks above moved start a new reading: their evidence goes)
            self._ledgers[s].clear(np.flatnonzero(swapped != assign))
            swapped = _ledger_exchange(
                tpl, swapped, hist, self._ledgers[s], others, self.config.verify_contact_mm, age
            )
            # a segment of three or more placed markers read again onto free points
            # (:func:`_free_readings`): two points keep one distance, which a plate's two
            # diagonals share (a head plate's LBHD and RFHD read onto RBHD's and LFHD's
            # points); not while a marker outside the segment is doubtful (a reading already
            # wrong elsewhere, moved from one wrong reading to another: the pile)
            read = swapped.copy()
            tree = cKDTree(pts) if tree is None else tree
            have = np.flatnonzero(read >= 0)
            doubt = np.zeros(tpl.n, dtype=bool)
            doubt[have] = _doubtful(tpl, have, hist[read[have], -1])
            _free_readings(tpl, read, pts, out < 0, tree, hist, doubtful=doubt)
            if not np.array_equal(read, swapped):
                swapped = read
            if swapped is not assign:
                _take(tpl, assign, swapped, out, taken0)
        tracked = np.isfinite(hist[:, :, 0]).sum(axis=1)
        usable = tracked >= max(1, int(np.ceil(self.config.min_track_fraction * w)))
        taken = (out >= 0) | ~usable
        if np.all(taken):
            return out
        for s in subjects:
            tpl = self._templates[s]
            assign, _ = _subject_assign(tpl, out)
            if np.all(assign >= 0):
                continue  # (every marker placed: the completion has none to add or move)
            # (the re-readings complete the subject again, mostly on the same local points:
            # their pairs and body candidates are computed once, :class:`boot_match._Memo`)
            with memo():
                if age is None:
                    grown = _complete(tpl, assign, pts, hist, taken, self.config)
                else:  # (may move weakly placed markers: :func:`_complete_weak`)
                    grown = _complete_weak(
                        tpl, assign, pts, hist, taken, self.config, exchange=s in checked
                    )
            if self._blind[s]:
                grown = _rigid_only(tpl, assign, grown, pts)
            _take(tpl, assign, grown, out, taken)
        if age is None:
            return out
        old = np.asarray(age, dtype=np.float64) >= self.config.fill_min_age_s
        # per subject, the free old points one of its leftover markers could be on (the fill's
        # candidates nearer another subject are offered only when no other subject reaches
        # them: :func:`_fill`); a subject's entry is refreshed after its own fill
        cand = np.flatnonzero(~taken & old)

        def reach(o: int) -> np.ndarray:
            tpl_o = self._templates[o]
            got = np.zeros(pts.shape[0], dtype=bool)
            got[cand] = _reach(tpl_o, _subject_assign(tpl_o, out)[0], pts, cand, self.config)
            return got

        past = self.config.fill_past_partner and cand.size > 0
        reach_of = {o: reach(o) for o in subjects} if past else {}
        for s in subjects:
            if self._blind[s]:
                continue  # (no joint fill: see above)
            tpl = self._templates[s]
            assign, mine = _subject_assign(tpl, out)
            if not mine.any():
                continue
            others = pts[(out >= 0) & ~mine]
            claimed = np.zeros(pts.shape[0], dtype=bool) if past else None
            for o, r in reach_of.items():
                if o != s and claimed is not None:
                    claimed |= r
            grown = _fill(
                tpl, assign, pts, hist, ~taken & old, others, self.config, claimed, s in checked
            )
            # the fill may move weakly placed markers (:func:`_weak_markers`) to other points
            _take(tpl, assign, grown, out, taken)
            if reach_of and grown is not assign:
                reach_of[s] = reach(s)
        return out

    def acquire(self, points: np.ndarray, labels: np.ndarray, subjects: list[int]) -> np.ndarray:
        """Labels free points of one frame as markers of ``subjects`` that have no point in it
        (hidden at boot, or just back), from the template alone: a free point takes marker
        ``m`` when its distances to two or more labeled points keep ``m``'s pairs of one trained
        body (``D +- tol``), none of those pairs is off, ``m`` is the only such marker, and,
        where a body of ``m`` has three or more labeled markers, the body's reference shape
        fitted to them (Kabsch) puts ``m`` within ``fit_mm`` of the point (three agreeing pairs
        are needed otherwise). ``labels (N,)`` global marker indices, -1 free; returns a copy
        with the new labels. Cheap enough for every frame: only the free points are looked at,
        against their nearest labeled points. A label of -2 marks a point neither labeled nor
        to be looked at (it stays as it is)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.asarray(labels, dtype=np.int64).copy()
        if not subjects or self._a_reach <= 0:
            return out
        on = np.zeros(len(self._templates), dtype=bool)
        on[subjects] = True  # (np.isin over every marker cost ~10 us a frame)
        active = on[self._a_subject]
        have = np.flatnonzero((out >= 0) & active[np.maximum(out, 0)])
        free = np.flatnonzero(out == -1)
        if have.size < 2 or free.size == 0:
            return out
        unlabeled = active.copy()
        unlabeled[out[out >= 0]] = False
        if not unlabeled.any():
            return out
        k = min(8, have.size)
        dist, near = _nearest_within(pts[free], pts[have], k, self._a_reach)
        cand = np.flatnonzero(unlabeled)
        fit_mm = self.config.fit_mm
        # the pair tests of every free point at once, (C candidates, F free points, k nearest):
        # a loop over the free points with three fancy indexings each cost ~30 us a point
        # (the (C, F, k) blocks are read in one fancy index each: through ``[cand]`` first
        # every candidate's whole row of the model (~500 markers) was copied, 0.39 -> 0.16 ms
        # a call at 10 performers)
        ok_all = np.isfinite(dist)
        g_all = out[have[np.where(ok_all, near, 0)]]
        at = (cand[:, None, None], g_all[None])
        st_all = self._a_strict[at] & ok_all[None]
        fit_all = st_all & (np.abs(dist[None] - self._a_D[at]) <= self._a_tol[at])
        n_fit_all = fit_all.sum(axis=2)
        base_all = (n_fit_all >= 2) & ~np.any(st_all & ~fit_all, axis=2)
        # only the free points some marker may take now: the loop below takes markers one by
        # one (``unlabeled`` only shrinks), so a point none fits before it none fits in it (a
        # sender's junk, 1,200 free points a frame, cost 4 ms a frame in two sums a point)
        maybe = (ok_all.sum(axis=1) >= 2) & np.any(base_all & unlabeled[cand][:, None], axis=0)
        for i in np.flatnonzero(maybe).tolist():
            n_fit = n_fit_all[:, i]
            good = base_all[:, i] & unlabeled[cand]
            if good.sum() != 1:
                continue  # none, or a symmetric pair of markers: not guessed
            m = int(cand[np.flatnonzero(good)[0]])
            q = pts[free[i]]
            checked = False
            placed_ok = True
            for gm, shape in self._a_bodies[m]:
                pos = np.full(gm.size, -1, dtype=np.int64)
                lab_here = np.flatnonzero(np.isin(out, gm))
                for j in lab_here:
                    pos[np.flatnonzero(gm == out[j])[0]] = j
                seen = pos >= 0
                if seen.sum() < 3:
                    continue
                R, cs, cd = _kabsch_batch(shape[seen], pts[pos[seen]][None])
                pred = (shape[gm == m][0] - cs) @ R[0].T + cd[0]
                checked = True
                if np.linalg.norm(pred - q) > fit_mm:
                    placed_ok = False
                    break
            if not placed_ok or (not checked and int(n_fit[np.flatnonzero(good)[0]]) < 3):
                continue
            out[free[i]] = m
            unlabeled[m] = False
        return out


#: Above this many query-point pairs :func:`_nearest_within` builds a KD-tree instead.
NEAREST_BLOCK = 20_000


def _nearest_within(
    query: np.ndarray, points: np.ndarray, k: int, reach: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(Q, k)`` distances and indices of the ``k`` points nearest each query point, ``inf``
    (and an index to ignore) beyond ``reach``, as ``cKDTree.query(k=k,
    distance_upper_bound=reach)`` (order within a row aside). The acquisition asks this for
    the few free points of a frame against every labeled one (~500 at 10 performers): the
    distances of that small block cost less than building a KD-tree over the labeled points
    in every frame (0.3 ms); a large block (many free points at once) still gets the tree."""
    if query.shape[0] * points.shape[0] > NEAREST_BLOCK:
        dist, near = cKDTree(points).query(query, k=k, distance_upper_bound=reach)
        return dist.reshape(query.shape[0], k), near.reshape(query.shape[0], k)
    d = np.linalg.norm(query[:, None, :] - points[None, :, :], axis=2)
    if k < points.shape[0]:
        near = np.argpartition(d, k - 1, axis=1)[:, :k]
    else:
        near = np.broadcast_to(np.arange(points.shape[0]), d.shape).copy()
    dist = np.take_along_axis(d, near, axis=1)
    dist[~(dist < reach)] = np.inf
    return dist, near


def _rigid_support(tpl, assign: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``(m,)`` per placed marker of ``assign`` the number of its pairs of one trained body
    (``strict``) placed within their tolerance: the rigid evidence for its point (0 for markers
    not placed, or placed by articulated links only)."""
    out = np.zeros(tpl.n, dtype=np.int64)
    have = np.flatnonzero(assign >= 0)
    if have.size < 2:
        return out
    p = pts[assign[have]]
    d = np.linalg.norm(p[:, None] - p[None, :], axis=2)
    ok = tpl.strict[np.ix_(have, have)] & (
        np.abs(d - tpl.D[np.ix_(have, have)]) <= tpl.tol[np.ix_(have, have)]
    )
    out[have] = ok.sum(axis=1)
    return out


def boot(
    model: LabelerModel,
    frames: list[np.ndarray],
    rate: float,
    config: BootConfig | None = None,
) -> list[np.ndarray]:
    """Labels a short window of anonymous frames from a model, with no labeled frame.

    ``frames``: ``(N_k, 3)`` point arrays (mm, finite, any order). Returns per frame a label per
    point: the global marker index into ``model.marker_names`` or -1. The boot runs on the last
    frame with the whole window as evidence; earlier frames get the labels of their tracks
    (points of tracks that do not reach the last frame stay unlabeled).
    """
    if not frames:
        raise LabelerError("boot needs at least one frame")
    cfg = config or BootConfig()
    tracker = PointTracker(rate, cfg)
    window = []
    for k, f in enumerate(frames):
        pts = np.asarray(f, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(pts).all():
            raise LabelerError(f"frame {k}: points must be finite")
        window.append((pts, tracker.update(pts, k / rate)))
    last_pts, last_ids = window[-1]
    res = Booter(model, cfg).run(last_pts, track_history(window, last_ids))
    return labels_along_tracks(window, last_ids, res.labels)


def _untrained(tpl: _Template) -> np.ndarray:
    """``(n,)`` bool: markers of ``tpl`` with no trained distance to any other marker."""
    d = np.isfinite(tpl.D)
    np.fill_diagonal(d, False)
    return ~d.any(axis=1)


def _rigid_only(
    tpl: _Template, assign: np.ndarray, grown: np.ndarray, pts: np.ndarray
) -> np.ndarray:
    """``grown`` (a completion of ``assign``) without the new markers that have fewer than two
    pairs of one trained body (``strict``) placed within their tolerance (``D +- tol``) in
    ``grown``; markers ``assign`` had placed stay as ``grown`` has them."""
    fresh = np.flatnonzero((assign < 0) & (grown >= 0))
    if fresh.size == 0:
        return grown
    out = grown.copy()
    placed = np.flatnonzero(grown >= 0)
    for m in fresh:
        rest = placed[placed != m]
        d = np.linalg.norm(pts[grown[rest]] - pts[grown[m]], axis=1)
        fit = tpl.strict[m, rest] & (np.abs(d - tpl.D[m, rest]) <= tpl.tol[m, rest])
        if np.count_nonzero(fit) < 2:
            out[m] = -1
    return out


def _subject_assign(tpl: _Template, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Subject ``tpl``'s reading of the global ``labels (N,)``: its marker -> point map (-1
    unplaced) and the mask of the points labeled as its markers."""
    mine = (labels >= tpl.offset) & (labels < tpl.offset + tpl.n)
    assign = np.full(tpl.n, -1, dtype=np.int64)
    assign[labels[mine] - tpl.offset] = np.flatnonzero(mine)
    return assign, mine


def _take(
    tpl: _Template, assign: np.ndarray, grown: np.ndarray, labels: np.ndarray, taken: np.ndarray
) -> None:
    """Writes subject ``tpl``'s new reading ``grown`` (from ``assign``) into the global
    ``labels`` and ``taken`` masks: points of moved markers are freed, new points taken."""
    moved = assign[(assign >= 0) & (grown != assign)]
    labels[moved] = -1
    taken[moved] = False
    fresh = (grown >= 0) & (grown != assign)
    labels[grown[fresh]] = tpl.offset + np.flatnonzero(fresh)
    taken[grown[fresh]] = True
