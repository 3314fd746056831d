"""The online labeler of seed 003 (Yu, Li, Deng 2007), with no I/O.

``Labeler(marker_names, rate, config)`` follows the
:class:`~labeler_service.labeling.frame.FrameLabeler`
protocol. Frames passed with ``labels`` form the training window (the paper's supervised first
frames). **The structure and motion models are trained when the first frame without labels
arrives** (at least 3 labeled frames are needed); from then on every frame runs the numba loop
of :mod:`labeler_service.labeling.kernels.step` and labels passed with later frames are ignored.

``Labeler.from_model(model, rate)`` starts from a subject template instead: no training is
needed, but the stream must still start with at least one labeled frame, which gives the
initial assignment (the Kalman states) - we chose this over registering each body's reference
shape to the anonymous points of the first frame because with several people close together
that registration is ambiguous, while every capture system labels a calibration (T-pose) frame.

``Labeler.from_model(model, rate, subjects=())`` builds the kernel state of every model subject
with none active; :meth:`Labeler.add_subjects` starts subjects between two frames from recent
labeled frames (the boot's, :mod:`~labeler_service.labeling.booting`), :meth:`Labeler.drop_subject`
stops one, :meth:`Labeler.seed_markers` starts the tracks of markers an active subject lacks;
none of them touches the other subjects' state (no rebuild).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from labeler_service._numba import njit
from labeler_service.capture import split_label, subject_groups
from labeler_service.errors import LabelerError, ModelError
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import (
    LabeledFrame,
    MarkerState,
    frame_labels,
    frame_points,
    window_observations,
)
from labeler_service.labeling.kernels.kalman import _predict, _update
from labeler_service.labeling.kernels.params import kernel_params
from labeler_service.labeling.kernels.rigid import _snapshot
from labeler_service.labeling.kernels.state import (
    MAX_BODY,
    Bodies,
    Recovery,
    Scratch,
    Tracks,
    fields,
    grow_scratch,
    new_bodies,
    new_recovery,
    new_scratch,
    new_tracks,
)
from labeler_service.labeling.kernels.step import _process_frame_fields
from labeler_service.labeling.kernels.window import _window_update
from labeler_service.labeling.restructure import (
    _accumulate,
    add_prior,
    add_samples,
    better_set,
    pair_model,
    recovery_sets,
    reform_bodies,
)
from labeler_service.labeling.templates import LabelerModel
from labeler_service.labeling.training import train_subject

MIN_TRAIN_FRAMES = 3
#: the window fields of :class:`Bodies` (per body) :meth:`Labeler.add_subjects` seeds
_PER_BODY = ("ring", "s1", "s2", "cnt", "D", "A")
#: the per-body state a body kept by :meth:`Labeler.restructure` carries over
_BODY_STATE = (
    *_PER_BODY,
    *("mpos", "R", "t", "moving", "motion_dt", "pred", "err", "kerr"),
    *("ref", "ref_ok", "ref_model", "ok", "pending"),
)


class Labeler:
    """Seed-003 online labeler: Kalman gating + greedy exhaustive rigid-body fitting."""

    def __init__(
        self, marker_names: Sequence[str], rate: float, config: LabelerConfig | None = None
    ) -> None:
        names = tuple(str(n) for n in marker_names)
        if not names:
            raise LabelerError("a labeler needs at least one marker name")
        if len(set(names)) != len(names):
            raise LabelerError("marker names must be unique")
        if not (np.isfinite(rate) and rate > 0):
            raise LabelerError(f"invalid frame rate {rate}")
        self._names = names
        self.rate = float(rate)
        self.config = config or LabelerConfig()
        self._params = kernel_params(self.config)
        self._index = {n: i for i, n in enumerate(names)}
        self._pending: list[tuple[float, np.ndarray]] = []
        self.model: LabelerModel | None = None
        self._ready = False
        self._built = False
        self._t_prev = np.nan
        self._frame_no = 0
        # the kernel state (kernels/state.py), built from the model by _build
        self._tracks: Tracks
        self._bodies: Bodies
        self._recovery: Recovery
        self._scratch: Scratch
        self._fields: tuple[tuple, ...] = ()  # the same as plain tuples, for the kernel call
        # pair-distance evidence of the confident output (labeling/restructure.py): sums of the
        # distance, its square and the count per marker pair (upper triangle), or None (off)
        self._ev: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._ref0: np.ndarray  # every body's first reference shape (and whether it has one)
        self._ref0_ok: np.ndarray
        self._subject_bodies: dict[str, np.ndarray] = {}  # per subject: its body indices
        self._ev_base: dict[str, float] = {}  # per subject: the count before the stream's
        self.restructures = 0  # re-formings that changed the structure

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_model(
        cls,
        model: LabelerModel,
        rate: float,
        config: LabelerConfig | None = None,
        subjects: Sequence[str] | None = None,
    ) -> Labeler:
        """A labeler from a subject template; the first frame(s) must still carry labels.

        The state is built here, not on the first unlabeled frame: a live stream started from a
        model pays no set-up stall (26 ms at 10 performers) inside a frame period.

        ``subjects``: the model subjects labeled from the start (default: all). The others are
        built but inactive (never predicted, gated or labeled; their labels are never given)
        until :meth:`add_subjects` starts them; with ``subjects=()`` no labeled frame is needed
        at all: :meth:`add_subjects` starts the labeler."""
        lab = cls(model.marker_names, rate, config)
        lab.model = model
        lab._build(model)
        lab._built = True
        prior = lab.config.restructure_prior_s * lab.rate
        if lab._ev is not None and prior >= lab.config.restructure_max_train_frames:
            lab._ev = None  # the model counts as enough samples: its structure stays
        if lab._ev is not None:
            # the trained model is the anchor: its D, A count as restructure_prior_s of samples
            for s in model.subjects:
                cols = lab._subject_cols[s.name]
                add_prior(cols, s.D_array(), s.A_array(), prior, *lab._ev)
            lab._ev_mark()
        if subjects is not None:
            known = {s.name for s in model.subjects}
            unknown = sorted(set(subjects) - known)
            if unknown:
                raise LabelerError(f"subjects {unknown} are not in the model")
            for s in model.subjects:
                if s.name not in subjects:
                    lab._tracks.active[lab._subject_markers[s.name]] = False
        return lab

    @property
    def marker_names(self) -> tuple[str, ...]:
        return self._names

    @property
    def trained(self) -> bool:
        return self._ready

    @property
    def n_bodies(self) -> int:
        return int(self._bodies.members.shape[0]) if self._ready else 0

    def body_extent(self) -> np.ndarray:
        """``(M,)`` mm: per marker the longest marker-pair distance ``D`` of the smallest rigid
        body containing it (seed 003 Fig. 8 normalises recovery errors by it); NaN for markers
        without a body, or everywhere before training."""
        m = len(self._names)
        out = np.full(m, np.nan)
        if not self._ready:
            return out
        bodies = self._bodies
        for b in range(bodies.members.shape[0]):
            k = int(bodies.size[b])
            ext = float(np.nanmax(bodies.D0[b, :k, :k])) if k > 1 else np.nan
            for i in bodies.members[b, :k]:
                if not np.isfinite(out[i]) or ext < out[i]:
                    out[i] = ext
        return out

    # ------------------------------------------------------------------ subjects
    @property
    def active_subjects(self) -> tuple[str, ...]:
        """The model subjects labeled now (model order); empty before a model is built."""
        if not self._built or self.model is None:
            return ()
        act = self._tracks.active
        return tuple(
            s.name
            for s in self.model.subjects
            if self._subject_markers[s.name].size
            and (act | self._withdrawn)[self._subject_markers[s.name]].all()
        )

    def add_subjects(
        self, names: Sequence[str], frames: Sequence[tuple[float, np.ndarray, np.ndarray]]
    ) -> None:
        """Starts labeling the inactive model subjects ``names`` (see :meth:`from_model`),
        between two frames, without touching any other subject's state.

        ``frames``: recent labeled frames ``(t, points (N, 3), labels (N,))`` (labels: this
        labeler's marker index per point, -1 unknown), oldest first, the last one being the
        frame this labeler processed last (or, on a labeler not started yet, the current one).
        Only the labels of the added subjects are read: their Kalman states, sliding windows
        (Eq. 1-2) and recovery snapshots restart from these frames, as a rebuild with them as
        labeled first frames would start them, at the cost of the added subjects alone. A
        labeler from a model with no subject active is started by this call (no labeled frame
        passes through :meth:`process`)."""
        self._check_subjects_call(frames)
        tr = self._tracks
        markers, bodies = [], []
        for name in names:
            if name not in self._subject_markers:
                raise LabelerError(f"subject {name!r} is not in the model")
            mk = self._subject_markers[name]
            if mk.size and tr.active[mk].any():
                raise LabelerError(f"subject {name!r} is labeled already")
            self._withdrawn[mk] = False
            markers.append(mk)
            bodies.append(self._subject_bodies[name])
        if not markers:
            return
        mk = np.concatenate(markers)
        bidx = np.concatenate(bodies)
        self._reset(mk, bidx)
        tr.active[mk] = True
        self._seed(mk, bidx, frames)

    def seed_markers(
        self,
        markers: Sequence[int] | np.ndarray,
        frames: Sequence[tuple[float, np.ndarray, np.ndarray]],
    ) -> None:
        """Restarts the tracks of ``markers`` (of active subjects; e.g. markers hidden when
        their subject was added, labeled since from the template) from the labels of
        ``frames`` (as :meth:`add_subjects`); every other marker and every body window stays
        as it is. Markers in no rigid body (never labeled by this labeler) are skipped."""
        self._check_subjects_call(frames)
        mk = np.unique(np.asarray(markers, dtype=np.int64))
        if mk.size and (mk[0] < 0 or mk[-1] >= len(self._names)):
            raise LabelerError(f"marker index out of range 0..{len(self._names) - 1}")
        mk = mk[self._body_marker[mk]]
        if mk.size == 0:
            return
        back = mk[self._withdrawn[mk]]  # withdrawn (withdraw_markers): placed again
        self._tracks.active[back] = True
        self._withdrawn[back] = False
        if not self._tracks.active[mk].all():
            raise LabelerError("seed_markers takes markers of active subjects only")
        # an open contact between performers (kernels/contact.py) outlives the restart: the
        # pair is still touching, and its pre-contact references (tracks.ct_ref) are untouched
        # by the new track; cleared, the partner would drop the contact undecided and a swap
        # made while the points are still close would last
        ct = self._tracks.ct_with
        partner = ct[mk].copy()
        self._reset(mk, np.zeros(0, dtype=np.int64))
        self._seed(mk, np.zeros(0, dtype=np.int64), frames)
        open_ = partner >= 0
        open_[open_] = ct[partner[open_]] == mk[open_]
        ct[mk[open_]] = partner[open_]

    def drop_subject(self, name: str) -> None:
        """Stops labeling subject ``name`` (it left): its markers become inactive, so from the
        next frame on none of its labels is given to any point; its state is cleared, every
        other subject's state stays as it is. :meth:`add_subjects` starts it again."""
        if not self._built or name not in self._subject_markers:
            raise LabelerError(f"subject {name!r} is not in the model")
        mk = self._subject_markers[name]
        self._reset(mk, self._subject_bodies[name])
        self._tracks.active[mk] = False
        self._withdrawn[mk] = False

    def withdraw_markers(self, markers: Sequence[int] | np.ndarray) -> None:
        """Stops labeling ``markers`` of active subjects (their labels were found wrong, e.g.
        by the boot's re-verification): from the next frame on they take no point; their state
        is cleared, and so are the windows of the bodies all of whose markers are withdrawn.
        :meth:`seed_markers` starts them again; every other marker keeps its state."""
        if not self._built:
            raise LabelerError("markers can be withdrawn only once the labeler is built")
        mk = np.unique(np.asarray(markers, dtype=np.int64))
        if mk.size and (mk[0] < 0 or mk[-1] >= len(self._names)):
            raise LabelerError(f"marker index out of range 0..{len(self._names) - 1}")
        mk = mk[self._body_marker[mk] & self._tracks.active[mk]]
        if mk.size == 0:
            return
        gone = np.zeros(len(self._names), dtype=bool)
        gone[mk] = True
        bd = self._bodies
        member = bd.members >= 0
        out = gone[np.maximum(bd.members, 0)] | ~member
        whole = np.flatnonzero(out.all(axis=1) & member.any(axis=1)).astype(np.int64)
        self._reset(mk, whole)
        self._tracks.active[mk] = False
        self._withdrawn[mk] = True

    def _check_subjects_call(self, frames: Sequence) -> None:
        if not self._built:
            raise LabelerError("subjects can be added only to a labeler from a model")
        if not self._ready and self._pending:
            raise LabelerError("labeled first frames are pending: add subjects after them")
        if not frames:
            raise LabelerError("adding markers needs at least one labeled frame")

    def _reset(self, markers: np.ndarray, bodies: np.ndarray) -> None:
        """The state of ``markers`` and ``bodies`` as a fresh build has it (in place)."""
        tr, bd = self._tracks, self._bodies
        tr.x[markers] = np.nan
        tr.P[markers] = 0.0
        tr.kx[markers] = np.nan
        for a in (tr.age, tr.n_reject, tr.lost):
            a[markers] = 0
        tr.gone[markers] = False
        tr.ct_with[markers] = -1
        tr.seen_at[markers] = -1  # anonymous point tracks: no track (kernels/anonymous.py)
        tr.track_from[markers] = -1
        tr.pair_wait[markers] = -1
        tr.fol[markers, 6] = 0.0
        tr.state[markers] = MarkerState.MISSING
        tr.pos[markers] = np.nan
        self._recovery.ok[markers] = False
        if bodies.size == 0:
            return
        bd.D[bodies] = bd.D0[bodies]
        bd.A[bodies] = bd.A0[bodies]
        for name in ("ring", "mpos", "pred", "err", "kerr"):
            getattr(bd, name)[bodies] = np.nan
        for name in ("s1", "s2", "cnt", "R", "t", "motion_dt", "pending"):
            getattr(bd, name)[bodies] = 0
        bd.moving[bodies] = False
        bd.ref[bodies] = self._ref0[bodies]
        bd.ref_ok[bodies] = self._ref0_ok[bodies]
        bd.ref_model[bodies] = self._ref0_ok[bodies]
        bd.ok[bodies] = True

    def _seed(
        self,
        markers: np.ndarray,
        bodies: np.ndarray,
        frames: Sequence[tuple[float, np.ndarray, np.ndarray]],
    ) -> None:
        """:meth:`_warm_start` for ``markers`` and the windows of ``bodies`` only (one kernel
        call: :func:`_seed_frames`)."""
        p, tr, m = self._params, self._tracks, len(self._names)
        mask = np.zeros(m, dtype=np.bool_)
        mask[markers] = True
        bd = self._bodies
        read = (*_PER_BODY, "members", "size", "D0", "A0", "ok")
        sub = Bodies(
            *(a[bodies] if k in read else a for k, a in zip(Bodies._fields, bd, strict=True))
        )
        T = bd.ring.shape[3]
        nf = len(frames)
        obs = window_observations(frames, mask)
        dts = np.empty(nf)
        t_prev = np.nan
        for k, (t, _, _) in enumerate(frames):
            dt = float(t) - t_prev
            dts[k] = dt if np.isfinite(dt) and dt > 0 else 1.0 / self.rate
            t_prev = float(t)
        slots = (self._frame_no - nf + np.arange(nf)) % T
        age = np.zeros(m, dtype=np.int64)
        lost = np.zeros(m, dtype=np.int64)
        _seed_frames(
            obs, dts, slots, mask, tr.x, tr.P, tr.q, sub, self._recovery, age, lost,
            p.p_cap, p.r, p.v0, p.min_window_samples,
        )  # fmt: skip
        obs = obs[-1]
        for name in _PER_BODY:
            if bodies.size:
                getattr(bd, name)[bodies] = getattr(sub, name)
        tr.age[mask] = age[mask]
        tr.lost[mask] = lost[mask]
        seen = mask & np.isfinite(obs[:, 0])
        tr.state[seen] = MarkerState.OBSERVED
        tr.pos[seen] = obs[seen]
        if not self._ready or not self._t_prev >= t_prev:
            # (a labeler that labeled no frame since the frames' last one moves on to it)
            self._t_prev = t_prev
            self._ready = True
        elif self._t_prev > t_prev:  # frames passed since the last labeled one: catch up
            _predict(tr.x, tr.P, tr.q, mask, self._t_prev - t_prev, p.p_cap)

    # ------------------------------------------------------------------ per frame
    def process(
        self, points: np.ndarray, t: float, labels: np.ndarray | None = None
    ) -> LabeledFrame:
        """Labels one frame of anonymous points ``(N, 3)`` mm (see the module docstring)."""
        t0 = time.perf_counter_ns()
        pts = frame_points(points)
        if not self._ready:
            if labels is not None:
                return self._collect(pts, float(t), labels, t0)
            self._start()
        return self._label(pts, float(t), t0)

    def _collect(self, pts: np.ndarray, t: float, labels: np.ndarray, t0: int) -> LabeledFrame:
        m = len(self._names)
        lab = frame_labels(labels, pts.shape[0], m)
        pos = np.full((m, 3), np.nan, dtype=np.float32)
        ok = lab >= 0
        pos[lab[ok]] = pts[ok]
        self._pending.append((t, pos))
        state = np.where(np.isfinite(pos[:, 0]), MarkerState.OBSERVED, MarkerState.MISSING)
        self._t_prev = t
        return LabeledFrame(
            t=t,
            point_labels=lab.astype(np.int32),
            positions=pos,
            state=state.astype(np.uint8),
            process_us=(time.perf_counter_ns() - t0) / 1e3,
        )

    def _label(self, pts: np.ndarray, t: float, t0: int) -> LabeledFrame:
        dt = t - self._t_prev
        if not (np.isfinite(dt) and dt > 0):
            dt = 1.0 / self.rate
        self._t_prev = t
        n = pts.shape[0]
        if n > self._scratch.owner.shape[0]:
            self._scratch = grow_scratch(self._scratch, n)
            self._pack()
        ptr = self._frame_no % self._bodies.ring.shape[3]
        self._frame_no += 1
        self._run(pts, dt, ptr)
        if self._ev is not None:
            self._evidence()
        pos, state = self._tracks.pos.copy(), self._tracks.state.copy()
        weak = (state == MarkerState.RECOVERED) & (
            self._scratch.has_rec < self.config.recovered_min_neighbours
        )
        if weak.any():  # (steered the tracker; not an estimate to publish)
            state[weak] = MarkerState.MISSING
            pos[weak] = np.nan
        return LabeledFrame(
            t=t,
            point_labels=self._scratch.owner[:n].copy(),
            positions=pos,
            state=state,
            process_us=(time.perf_counter_ns() - t0) / 1e3,
        )

    def _evidence(self) -> None:
        """This frame's pair distances of the confident markers into the evidence (at most
        ``restructure_sample_hz``), and the structure re-formed every ``restructure_s``."""
        c, f, ev = self.config, self._frame_no, self._ev
        assert ev is not None
        if f % max(1, round(self.rate / c.restructure_sample_hz)) == 0:
            tr, bd = self._tracks, self._bodies
            _accumulate(
                tr.state, tr.age, tr.pos, bd.ok, bd.mb_ptr, bd.mb_idx, tr.subj_ptr, tr.subj_idx,
                c.restructure_age, self._ev_conf, *ev,
            )  # fmt: skip
        if f % max(1, round(self.rate * c.restructure_s)) == 0:
            self.restructure()

    def _ev_mark(self) -> None:
        """Records each subject's evidence count now (before the stream's own samples)."""
        assert self._ev is not None
        n = self._ev[2]
        self._ev_base = {
            name: float(n[np.ix_(cols, cols)].sum()) for name, cols in self._subject_cols.items()
        }

    def restructure(self) -> bool:
        """Re-forms the rigid bodies (and, with ``restructure_recovery``, the recovery sets) of
        every subject the stream gave evidence for (labeling/restructure.py), between two
        frames; the Kalman tracks and every body whose members stay keep their state. Returns
        whether the structure changed.

        ``process`` calls it every ``restructure_s`` of stream. Cost: the body rule on each
        subject's pair matrix and, when something changed, a rebuild of the body arrays: 13-36
        ms for 10 simulated performers (shared machine), more than a 360 Hz frame period, so a
        live service should call it between frames off the hot path."""
        if self._ev is None or not self._ready or self.model is None:
            return False
        c, m = self.config, len(self._names)
        s1, s2, n = self._ev
        old, old_rec = self._bodies, self._recovery
        keys = self._body_keys()
        bodies: list[list[int]] = []
        d0: list[np.ndarray] = []
        a0: list[np.ndarray] = []

        def keep(ob: int) -> None:  # a current body, with its trained D, A
            k = int(old.size[ob])
            bodies.append(list(self._members(ob)))
            d0.append(old.D0[ob, :k, :k])
            a0.append(old.A0[ob, :k, :k])

        recovery = new_recovery(m)  # the current sets, changed below where re-formed
        recovery.members[:] = old_rec.members
        recovery.size[:] = old_rec.size
        subject_bodies: dict[str, np.ndarray] = {}
        for subj in self.model.subjects:
            cols = self._subject_cols[subj.name]
            first = len(bodies)
            base = self._ev_base.get(subj.name, 0.0)
            if float(n[np.ix_(cols, cols)].sum()) <= base:  # no evidence of the stream: keep
                for b in self._subject_bodies[subj.name]:
                    keep(int(b))
            else:
                D, A = pair_model(cols, s1, s2, n)
                local = {int(g): k for k, g in enumerate(cols)}
                old_b = [  # the trained bodies (added ones are chosen again, or not)
                    [local[v] for v in self._members(ob)]
                    for ob in self._subject_bodies[subj.name]
                    if self._members(ob) in self._trained
                ]
                kept, added = reform_bodies(D, A, self._body_marker[cols], old_b, c)
                for body in kept:
                    keep(keys[tuple(int(cols[i]) for i in body)])
                for body in added:
                    bodies.append([int(cols[i]) for i in body])
                    d0.append(D[np.ix_(body, body)])
                    a0.append(A[np.ix_(body, body)])
                sets = (
                    recovery_sets(D, A, self._body_marker[cols], c)
                    if c.restructure_recovery
                    else {}
                )
                for i, members in sets.items():
                    g = int(cols[i])
                    mine = [int(cols[j]) for j in members]
                    k0 = int(old_rec.size[g])
                    prev = [int(v) for v in old_rec.members[g, :k0]]
                    if (
                        set(prev) != set(mine)
                        and k0
                        and not better_set(D, A, i, members, [local[v] for v in prev], c)
                    ):
                        mine = prev  # hysteresis: the old set is about as rigid
                    recovery.members[g] = -1
                    recovery.members[g, : len(mine)] = mine
                    recovery.size[g] = len(mine)
            subject_bodies[subj.name] = np.arange(first, len(bodies))
        same_rec = (recovery.members == old_rec.members).all(axis=1)
        if len(bodies) == len(keys) and all(tuple(b) in keys for b in bodies) and same_rec.all():
            return False
        self._install(bodies, d0, a0, recovery, subject_bodies, keys, same_rec)
        self.restructures += 1
        return True

    def _members(self, b: int) -> tuple[int, ...]:
        """The markers of current body ``b``, in order."""
        return tuple(int(v) for v in self._bodies.members[b, : self._bodies.size[b]])

    def _body_keys(self) -> dict[tuple[int, ...], int]:
        """Each current body's index by its markers (in order)."""
        return {self._members(b): b for b in range(self._bodies.members.shape[0])}

    def _install(
        self,
        bodies: list[list[int]],
        d0: list[np.ndarray],
        a0: list[np.ndarray],
        recovery: Recovery,
        subject_bodies: dict[str, np.ndarray],
        keys: dict[tuple[int, ...], int],
        same_rec: np.ndarray,
    ) -> None:
        """Installs a new structure between two frames: a body with the same members (in the
        same order) as a current one (``keys``: :meth:`_body_keys`) keeps its state, and a
        recovery set with the same members (``same_rec``) its snapshot; the tracks are not
        touched."""
        c, m = self.config, len(self._names)
        old, old_rec = self._bodies, self._recovery
        new = new_bodies(m, bodies, d0, a0, c.window_T)
        ref0 = np.zeros_like(new.ref)
        ref0_ok = np.zeros_like(new.ref_ok)
        tr = self._tracks
        for b, body in enumerate(bodies):
            ob = keys.get(tuple(body))
            if ob is not None:  # the same members: the body keeps its state
                for name in _BODY_STATE:
                    getattr(new, name)[b] = getattr(old, name)[ob]
                ref0[b] = self._ref0[ob]
                ref0_ok[b] = self._ref0_ok[ob]
                continue
            seen = tr.state[body] == MarkerState.OBSERVED
            new.mpos[b, : len(body)][seen] = tr.pos[body][seen]
            if (
                seen.all()
                and (tr.age[body] >= c.snapshot_age).all()
                and old.ok[
                    [old.mb_idx[q] for i in body for q in range(old.mb_ptr[i], old.mb_ptr[i + 1])]
                ].all()
            ):
                new.ref[b, : len(body)] = tr.pos[body]  # a reference the confident tracks give
                new.ref_ok[b] = True
                continue
            for ob in range(old.size.shape[0]):  # else the rows of a body it is part of
                k = int(old.size[ob])
                row = {int(v): e for e, v in enumerate(old.members[ob, :k])}
                if old.ref_ok[ob] and all(i in row for i in body):
                    new.ref[b, : len(body)] = old.ref[ob, [row[i] for i in body]]
                    new.ref_ok[b] = True
                    new.ref_model[b] = old.ref_model[ob]
                    break
        tr.ct_with[:] = -1  # contact references are rows of the old recovery sets
        recovery.ref[same_rec] = old_rec.ref[same_rec]
        recovery.ok[same_rec] = old_rec.ok[same_rec]
        self._bodies, self._recovery = new, recovery
        self._ref0, self._ref0_ok = ref0, ref0_ok
        self._subject_bodies = subject_bodies
        owner = self._scratch.owner
        groups = self._tracks.subj_ptr.shape[0] - 1
        self._scratch = new_scratch(m, len(bodies), groups, c.K, owner.shape[0])
        self._scratch.owner[:] = owner
        self._pack()

    def _run(self, pts: np.ndarray, dt: float, ptr: int) -> None:
        _process_frame_fields(pts, dt, ptr, self._frame_no, *self._fields)

    def _pack(self) -> None:
        """The kernel call's arguments: each structure as a plain tuple of its (shared) arrays
        (:func:`~labeler_service.labeling.kernels.step._process_frame_fields` says why)."""
        state = (self._tracks, self._bodies, self._recovery, self._scratch, self._params)
        self._fields = tuple(fields(s) for s in state)

    # ------------------------------------------------------------------ training
    def train_model(self) -> LabelerModel:
        """Eq. 1-2 and the motion noise from the collected labeled frames (one template per
        subject)."""
        if len(self._pending) < MIN_TRAIN_FRAMES:
            raise LabelerError(
                f"the labeler needs at least {MIN_TRAIN_FRAMES} labeled frames before the first "
                f"unlabeled one (got {len(self._pending)})"
            )
        pos = np.stack([p for _, p in self._pending])  # (F, M, 3)
        times = np.array([t for t, _ in self._pending])
        steps = np.diff(times)
        steps = steps[np.isfinite(steps) & (steps > 0)]
        rate = float(1.0 / np.median(steps)) if steps.size else self.rate
        c = self.config
        subjects = []
        for name, cols in subject_groups(self._names).items():
            markers = [split_label(self._names[i])[1] for i in cols]
            subjects.append(train_subject(name, markers, pos[:, cols], rate, **c.body_rule()))
        return LabelerModel(rate=rate, subjects=subjects, source="training window")

    def _start(self) -> None:
        if not self._pending:
            raise LabelerError(
                "the first frame must carry labels: the labeler learns from (or, with a model, "
                "acquires its markers from) labeled frames"
            )
        trained_here = self.model is None
        model = self.train_model() if self.model is None else self.model
        self.model = model
        if not self._built:
            self._build(model, from_file=not trained_here)
            self._built = True
        if trained_here and len(self._pending) >= self.config.restructure_max_train_frames:
            self._ev = None  # a window of that many samples: its structure stays
        if self._ev is not None:  # the labeled frames are evidence (trained on: the baseline)
            tr = self._tracks
            add_samples(np.stack([p for _, p in self._pending]), tr.subj_ptr, tr.subj_idx,
                        *self._ev)  # fmt: skip
            if trained_here:
                self._ev_mark()
        self._warm_start()
        self._pending.clear()
        self._ready = True

    def _build(self, model: LabelerModel, from_file: bool = True) -> None:
        """The kernel state (:mod:`~labeler_service.labeling.kernels.state`) from a template;
        ``from_file``: a model trained elsewhere, whose shapes are the first references."""
        c = self.config
        m = len(self._names)
        bodies: list[list[int]] = []
        d0: list[np.ndarray] = []
        a0: list[np.ndarray] = []
        shapes: list[np.ndarray] = []
        q = np.full(m, np.nan)
        recovery = new_recovery(m)
        for subj in model.subjects:
            try:
                gidx = [self._index[label] for label in subj.labels]
            except KeyError as exc:
                raise ModelError(f"model marker {exc.args[0]!r} is not a labeler marker") from exc
            Dm = subj.D_array()
            Am = subj.A_array()
            q[gidx] = subj.motion_noise
            self._recovery_sets(recovery, gidx, Dm, Am, subj.bodies)
            for body, shape in zip(subj.bodies, subj.shapes, strict=True):
                bodies.append([gidx[i] for i in body])
                d0.append(Dm[np.ix_(body, body)])
                a0.append(Am[np.ix_(body, body)])
                shapes.append(np.asarray(shape, dtype=np.float64))
        active = np.zeros(m, dtype=np.bool_)
        for body in bodies:
            active[body] = True
        groups = list(subject_groups(self._names).values())
        # per subject: its body markers (the ones add/drop switch) and its bodies
        self._subject_markers: dict[str, np.ndarray] = {}
        self._subject_bodies = {}
        nb = 0
        self._subject_cols: dict[str, np.ndarray] = {}  # every marker of the subject
        for subj in model.subjects:
            cols = np.array([self._index[label] for label in subj.labels])
            self._subject_cols[subj.name] = cols
            self._subject_markers[subj.name] = cols[active[cols]]
            self._subject_bodies[subj.name] = np.arange(nb, nb + len(subj.bodies))
            nb += len(subj.bodies)
        self._body_marker = active.copy()
        self._withdrawn = np.zeros(m, dtype=bool)  # markers withdrawn (withdraw_markers)
        self._tracks = new_tracks(np.where(np.isfinite(q), q, 1.0e6), active, groups)
        self._bodies = new_bodies(m, bodies, d0, a0, c.window_T)
        if from_file:
            # a model trained elsewhere: its shapes are the bodies' first references (the 3D
            # check and the joint re-acquisition need one before a body is first seen whole,
            # as a booted subject's bodies are not)
            for b, ref in enumerate(shapes):
                self._bodies.ref[b, : ref.shape[0]] = ref
            self._bodies.ref_ok[:] = True
            self._bodies.ref_model[:] = True
        self._ref0 = self._bodies.ref.copy()
        self._ref0_ok = self._bodies.ref_ok.copy()
        self._trained = {tuple(b) for b in bodies}  # (restructure keeps these, or drops them)
        self._recovery = recovery
        self._scratch = new_scratch(m, len(bodies), len(groups), c.K, max(64, 2 * m))
        self._pack()
        if c.restructure_s > 0:
            self._ev = (np.zeros((m, m)), np.zeros((m, m)), np.zeros((m, m)))
            self._ev_conf = np.zeros(m, dtype=np.bool_)

    def _recovery_sets(
        self,
        recovery: Recovery,
        gidx: list[int],
        Dm: np.ndarray,
        Am: np.ndarray,
        bodies: list[list[int]],
    ) -> None:
        """Recovery set of each body marker: itself and the markers of lowest ``A + w D``."""
        c = self.config
        in_body = np.zeros(len(gidx), dtype=bool)
        for body in bodies:
            in_body[body] = True
        cost = Am + c.body_distance_weight * Dm
        cost = np.where(np.isfinite(cost), cost, np.inf)
        np.fill_diagonal(cost, np.inf)
        cost[:, ~in_body] = np.inf
        k = min(MAX_BODY - 1, c.recovery_set_size)
        for i in np.flatnonzero(in_body):
            order = [
                int(j) for j in np.argsort(cost[i], kind="stable")[:k] if np.isfinite(cost[i, j])
            ]
            members = [gidx[i]] + [gidx[j] for j in order]
            recovery.members[gidx[i], : len(members)] = members
            recovery.size[gidx[i]] = len(members)

    def _warm_start(self) -> None:
        """Runs the Kalman filter (Eq. 3-4) and the window (Eq. 1-2) over the labeled frames."""
        from labeler_service.labeling.kernels.kalman import _predict, _update
        from labeler_service.labeling.kernels.rigid import _snapshot
        from labeler_service.labeling.kernels.window import _window_update

        p = self._params
        tr = self._tracks
        t_prev = np.nan
        T = self._bodies.ring.shape[3]
        for t, pos in self._pending:
            dt = t - t_prev
            if not (np.isfinite(dt) and dt > 0):
                dt = 1.0 / self.rate
            t_prev = t
            _predict(tr.x, tr.P, tr.q, tr.active, dt, p.p_cap)
            obs = pos.astype(np.float64)
            _update(tr.x, tr.P, obs, tr.active, p.r, p.v0)
            _window_update(self._bodies, obs, self._frame_no % T, p.min_window_samples)
            self._frame_no += 1
            seen = np.isfinite(obs[:, 0])
            tr.age[:] = np.where(seen, tr.age + 1, 0)
            _snapshot(tr.age, 1, obs, self._recovery)
        self._t_prev = t_prev

    # ------------------------------------------------------------------ warm-up
    def warmup(self) -> None:
        """Compiles (or loads from cache) every kernel on a synthetic frame without touching
        this labeler's state: the first real frame pays no compile time."""
        rng = np.random.default_rng(0)
        names = [f"w:m{i}" for i in range(6)]
        base = rng.normal(0, 100, (6, 3)).astype(np.float32)
        lab = Labeler(names, self.rate, self.config)
        for k in range(MIN_TRAIN_FRAMES + 2):
            pts = base + np.float32(k)
            lab.process(pts, k / self.rate, np.arange(6))
        for k in range(3):
            pts = base[1:] + np.float32(5 + k)
            lab.process(pts, (5 + k) / self.rate)


@njit
def _seed_frames(obs, dts, slots, mask, x, P, q, bodies, recovery, age, lost, p_cap, r, v0, n_min):
    """The warm start of :meth:`Labeler._seed` in one call: for each labeled frame
    ``obs[k] (M, 3)`` (NaN rows = not labeled), the Kalman prediction over ``dts[k]`` and update
    of the markers in ``mask``, the window update of ``bodies`` (a subset, :class:`Bodies`) at
    ring slot ``slots[k]``, ``age``/``lost`` (frames observed / missing in a row) and the
    recovery snapshots (as :meth:`Labeler._warm_start`, snapshot age 1)."""
    for k in range(obs.shape[0]):
        _predict(x, P, q, mask, dts[k], p_cap)
        _update(x, P, obs[k], mask, r, v0)
        if bodies.members.shape[0] > 0:
            _window_update(bodies, obs[k], slots[k], n_min)
        for i in range(obs.shape[1]):
            if obs[k, i, 0] == obs[k, i, 0]:  # noqa: PLR0124 (NaN test)
                age[i] += 1
                lost[i] = 0
            else:
                age[i] = 0
                lost[i] += 1
        _snapshot(age, 1, obs[k], recovery)
