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
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from labeler_service.capture import split_label
from labeler_service.errors import LabelerError, ModelError
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import LabeledFrame, MarkerState
from labeler_service.labeling.templates import LabelerModel
from labeler_service.labeling.training import train_subject

MIN_TRAIN_FRAMES = 3
V0 = 1.0e6  # initial velocity variance of a new track, (mm/s)^2 (1 m/s deviation)


def subjects_of(marker_names: Sequence[str]) -> dict[str, list[int]]:
    """Subject name -> global marker indices, in order of first appearance."""
    out: dict[str, list[int]] = {}
    for i, name in enumerate(marker_names):
        subject, _ = split_label(name)
        out.setdefault(subject or "", []).append(i)
    return out


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
        self._index = {n: i for i, n in enumerate(names)}
        self._pending: list[tuple[float, np.ndarray]] = []
        self.model: LabelerModel | None = None
        self._ready = False
        self._built = False
        self._t_prev = np.nan
        self._frame_no = 0

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_model(
        cls, model: LabelerModel, rate: float, config: LabelerConfig | None = None
    ) -> Labeler:
        """A labeler from a subject template; the first frame(s) must still carry labels.

        The state is built here, not on the first unlabeled frame: a live stream started from a
        model pays no set-up stall (26 ms at 10 performers) inside a frame period."""
        lab = cls(model.marker_names, rate, config)
        lab.model = model
        lab._build(model)
        lab._built = True
        return lab

    @property
    def marker_names(self) -> tuple[str, ...]:
        return self._names

    @property
    def trained(self) -> bool:
        return self._ready

    @property
    def n_bodies(self) -> int:
        return int(self._body_markers.shape[0]) if self._ready else 0

    def body_extent(self) -> np.ndarray:
        """``(M,)`` mm: per marker the longest marker-pair distance ``D`` of the smallest rigid
        body containing it (seed 003 Fig. 8 normalises recovery errors by it); NaN for markers
        without a body, or everywhere before training."""
        m = len(self._names)
        out = np.full(m, np.nan)
        if not self._ready:
            return out
        for b in range(self._body_markers.shape[0]):
            k = int(self._body_size[b])
            ext = float(np.nanmax(self._D0[b, :k, :k])) if k > 1 else np.nan
            for i in self._body_markers[b, :k]:
                if not np.isfinite(out[i]) or ext < out[i]:
                    out[i] = ext
        return out

    # ------------------------------------------------------------------ per frame
    def process(
        self, points: np.ndarray, t: float, labels: np.ndarray | None = None
    ) -> LabeledFrame:
        """Labels one frame of anonymous points ``(N, 3)`` mm (see the module docstring)."""
        t0 = time.perf_counter_ns()
        pts = np.asarray(points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise LabelerError(f"points must be (N, 3), got shape {pts.shape}")
        if not np.isfinite(pts).all():
            raise LabelerError("points must be finite (drop missing points instead of NaN)")
        pts = np.ascontiguousarray(pts)
        if not self._ready:
            if labels is not None:
                return self._collect(pts, float(t), labels, t0)
            self._start()
        return self._label(pts, float(t), t0)

    def _collect(self, pts: np.ndarray, t: float, labels: np.ndarray, t0: int) -> LabeledFrame:
        lab = np.asarray(labels).astype(np.int64, copy=False).reshape(-1)
        if lab.shape[0] != pts.shape[0]:
            raise LabelerError(f"{lab.shape[0]} labels for {pts.shape[0]} points")
        m = len(self._names)
        lab = np.where((lab >= 0) & (lab < m), lab, -1)
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
        if n > self._owner.shape[0]:
            self._grow(n)
        ptr = self._frame_no % self._ring.shape[3]
        self._frame_no += 1
        self._run(pts, dt, ptr, n)
        return LabeledFrame(
            t=t,
            point_labels=self._point_labels[:n].copy(),
            positions=self._out_pos.copy(),
            state=self._out_state.copy(),
            process_us=(time.perf_counter_ns() - t0) / 1e3,
        )

    def _run(self, pts: np.ndarray, dt: float, ptr: int, n: int) -> None:
        from labeler_service.labeling.kernels.step import _process_frame

        c = self.config
        _process_frame(
            pts, dt, self._x, self._P, self._q, self._active, self._r, self._r_rec, self._s_min, V0,
            self._p_cap, c.velocity_decay, c.gate_chi2, c.K, self._s, self._cand,
            self._cand_d2, self._ncand, self._bodies, self._D0, self._A0, self._ring, ptr, self._s1,
            self._s2, self._cnt, c.min_window_samples, c.a_floor_mm, c.a_relative, self._miss_term,
            c.motion_weight, self._rset,
            self._method, self._assigned,
            self._owner[:n], self._fit, self._obs, self._rec,
            self._has_rec, self._missing, self._kab,
            self._point_labels[:n], self._out_pos, self._out_state, self._subj_ptr,
            self._subj_idx, c.common_mode_radius_mm, c.common_mode_iters, self._cm_buf,
            self._cm_shift, c.reacquire_mm, c.verify_mm, c.reacquire_near_mm,
            self._miss_reacq, c.reacquire_all, c.robust_fit_mm, c.reject_mm,
            c.jump_mm, c.suspect_mm, self._n_reject, c.reject_limit, self._age, c.snapshot_age,
            c.reacquire_estimate_mm, c.reacquire_keep_observed, c.verify_every, self._frame_no,
            c.swap_check, c.contest, c.reacquire_loose_mm,
        )  # fmt: skip

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
        for name, cols in subjects_of(self._names).items():
            markers = [split_label(self._names[i])[1] for i in cols]
            subjects.append(
                train_subject(
                    name,
                    markers,
                    pos[:, cols],
                    rate,
                    tolerance_mm=c.body_tolerance_mm,
                    distance_weight=c.body_distance_weight,
                    min_size=c.body_min_size,
                    max_size=c.body_max_size,
                    all_seeds=c.body_all_seeds,
                )
            )
        return LabelerModel(rate=rate, subjects=subjects, source="training window")

    def _start(self) -> None:
        if not self._pending:
            raise LabelerError(
                "the first frame must carry labels: the labeler learns from (or, with a model, "
                "acquires its markers from) labeled frames"
            )
        if self.model is None:
            self.model = self.train_model()
        if not self._built:
            self._build(self.model)
            self._built = True
        self._warm_start()
        self._pending.clear()
        self._ready = True

    def _build(self, model: LabelerModel) -> None:
        """State arrays (struct of arrays) from a template."""
        from labeler_service.labeling.kernels.fitting import fit_scratch
        from labeler_service.labeling.kernels.rigid import kabsch_scratch

        c = self.config
        m = len(self._names)
        bodies: list[list[int]] = []
        d0: list[np.ndarray] = []
        a0: list[np.ndarray] = []
        q = np.full(m, np.nan)
        self._rec_members = np.full((m, 8), -1, dtype=np.int64)
        self._rec_size = np.zeros(m, dtype=np.int64)
        for subj in model.subjects:
            try:
                gidx = [self._index[f"{subj.name}:{mk}"] for mk in subj.markers]
            except KeyError as exc:
                raise ModelError(f"model marker {exc.args[0]!r} is not a labeler marker") from exc
            Dm = subj.D_array()
            Am = subj.A_array()
            q[gidx] = subj.motion_noise
            self._recovery_sets(gidx, Dm, Am, subj.bodies)
            for body in subj.bodies:
                bodies.append([gidx[i] for i in body])
                d0.append(Dm[np.ix_(body, body)])
                a0.append(Am[np.ix_(body, body)])
        nb = len(bodies)
        T = c.window_T
        self._body_markers = np.full((nb, 8), -1, dtype=np.int32)
        self._body_size = np.zeros(nb, dtype=np.int32)
        self._D0 = np.full((nb, 8, 8), np.nan)
        self._A0 = np.full((nb, 8, 8), np.nan)
        for b, body in enumerate(bodies):
            k = len(body)
            self._body_markers[b, :k] = body
            self._body_size[b] = k
            self._D0[b, :k, :k] = d0[b]
            self._A0[b, :k, :k] = a0[b]
        self._rec_ref = np.zeros((m, 8, 3))
        self._rec_ok = np.zeros(m, dtype=np.bool_)
        self._rset = (self._rec_members, self._rec_size, self._rec_ref, self._rec_ok)
        self._D = self._D0.copy()
        self._A = self._A0.copy()
        self._ring = np.full((nb, 8, 8, T), np.nan, dtype=np.float32)
        self._s1 = np.zeros((nb, 8, 8))
        self._s2 = np.zeros((nb, 8, 8))
        self._cnt = np.zeros((nb, 8, 8), dtype=np.int64)
        # marker -> bodies (CSR)
        counts = np.zeros(m + 1, dtype=np.int64)
        for body in bodies:
            for i in body:
                counts[i + 1] += 1
        self._mb_ptr = np.cumsum(counts).astype(np.int64)
        self._mb_idx = np.zeros(max(1, int(self._mb_ptr[-1])), dtype=np.int32)
        fill = self._mb_ptr[:-1].copy()
        for b, body in enumerate(bodies):
            for i in body:
                self._mb_idx[fill[i]] = b
                fill[i] += 1
        self._active = counts[1:] > 0
        self._bodies = (
            self._body_markers,
            self._body_size,
            self._D,
            self._A,
            self._mb_ptr,
            self._mb_idx,
        )
        self._q = np.where(np.isfinite(q), q, 1.0e6)
        self._x = np.full((m, 6), np.nan)
        self._P = np.zeros((m, 3))
        self._r = c.measurement_noise_mm**2
        self._r_rec = c.recovered_noise_mm**2
        self._s_min = c.min_gate_mm**2 / c.gate_chi2
        self._p_cap = c.max_position_sd_mm**2
        self._miss_term = float(np.exp(-0.5 * c.missing_sigma**2))
        self._miss_reacq = float(np.exp(-0.5 * c.reacquire_sigma**2))
        self._method = 1 if c.recovery == "kabsch" else 0
        K = c.K
        self._s = np.zeros(m)
        self._cand = np.zeros((m, K), dtype=np.int32)
        self._cand_d2 = np.zeros((m, K))
        self._ncand = np.zeros(m, dtype=np.int32)
        self._assigned = np.zeros(m, dtype=np.int32)
        self._fit = fit_scratch(m, nb, K)
        self._obs = np.full((m, 3), np.nan)
        self._rec = np.full((m, 3), np.nan)
        self._has_rec = np.zeros(m, dtype=np.int64)
        self._missing = np.zeros(m, dtype=np.bool_)
        self._n_reject = np.zeros(m, dtype=np.int64)
        self._age = np.zeros(m, dtype=np.int64)
        self._kab = kabsch_scratch()
        groups = list(subjects_of(self._names).values())
        self._subj_ptr = np.cumsum([0] + [len(g) for g in groups]).astype(np.int64)
        self._subj_idx = np.array([i for g in groups for i in g], dtype=np.int64)
        self._cm_buf = np.zeros((3, m))
        self._cm_shift = np.zeros((len(groups), 3))
        self._out_pos = np.full((m, 3), np.nan, dtype=np.float32)
        self._out_state = np.zeros(m, dtype=np.uint8)
        self._grow(max(64, 2 * m))

    def _recovery_sets(
        self, gidx: list[int], Dm: np.ndarray, Am: np.ndarray, bodies: list[list[int]]
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
        k = min(7, c.recovery_set_size)
        for i in np.flatnonzero(in_body):
            order = [
                int(j) for j in np.argsort(cost[i], kind="stable")[:k] if np.isfinite(cost[i, j])
            ]
            members = [gidx[i]] + [gidx[j] for j in order]
            self._rec_members[gidx[i], : len(members)] = members
            self._rec_size[gidx[i]] = len(members)

    def _grow(self, n: int) -> None:
        """(Re)allocates the per-point scratch buffers for up to ``n`` points."""
        self._owner = np.zeros(n, dtype=np.int32)
        self._point_labels = np.zeros(n, dtype=np.int32)

    def _warm_start(self) -> None:
        """Runs the Kalman filter (Eq. 3-4) and the window (Eq. 1-2) over the labeled frames."""
        from labeler_service.labeling.kernels.kalman import _predict, _update
        from labeler_service.labeling.kernels.rigid import _snapshot
        from labeler_service.labeling.kernels.window import _window_update

        c = self.config
        t_prev = np.nan
        T = self._ring.shape[3]
        for t, pos in self._pending:
            dt = t - t_prev
            if not (np.isfinite(dt) and dt > 0):
                dt = 1.0 / self.rate
            t_prev = t
            _predict(self._x, self._P, self._q, self._active, dt, self._p_cap)
            obs = pos.astype(np.float64)
            _update(self._x, self._P, obs, self._active, self._r, V0)
            _window_update(
                self._body_markers, self._body_size, obs, self._ring, self._frame_no % T,
                self._s1, self._s2, self._cnt, self._D0, self._A0, c.min_window_samples,
                self._D, self._A,
            )  # fmt: skip
            self._frame_no += 1
            seen = np.isfinite(obs[:, 0])
            self._age = np.where(seen, self._age + 1, 0)
            _snapshot(self._age, 1, obs, self._rset)
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
