"""``PointTracker.update`` in one kernel (kernels/track.py ``_track_step``) against the numpy
steps it replaced: the same track ids, velocities and birth times, to the bit."""

from __future__ import annotations

import numpy as np

from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.boot_tracks import PointTracker
from labeler_service.labeling.kernels.track import _match_tracks


class _NumpyTracker:
    """The former ``PointTracker.update`` (numpy around the matching kernel)."""

    def __init__(self, rate: float, config: BootConfig) -> None:
        self.rate, self.config = rate, config
        self._next = 0
        self._pts = np.zeros((0, 3))
        self._vel = np.zeros((0, 3))
        self._has_vel = np.zeros(0, dtype=bool)
        self._ids = np.zeros(0, dtype=np.int64)
        self._birth = np.zeros(0)
        self._t = np.nan
        self._empty = 0

    def update(self, points: np.ndarray, t: float) -> np.ndarray:
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        n = pts.shape[0]
        if n == 0 and self._ids.size and self._empty < self.config.track_hold_frames:
            self._empty += 1  # a dropout frame: the tracks are held
            return np.zeros(0, dtype=np.int64)
        self._empty = 0
        dt = t - self._t
        if not (np.isfinite(dt) and dt > 0):
            dt = 1.0 / self.rate
        c = self.config
        ids = np.full(n, -1, dtype=np.int64)
        vel = np.zeros((n, 3))
        has_vel = np.zeros(n, dtype=bool)
        birth = np.full(n, float(t))
        if n and self._pts.shape[0]:
            pred = self._pts + np.where(self._has_vel[:, None], self._vel * dt, 0.0)
            g0 = c.track_gate_mm + c.track_accel_mm_s2 * dt * dt
            gate = np.where(self._has_vel, g0, g0 + c.track_speed_mm_s * dt)
            moved = self._has_vel
            rel_dt = c.track_relative_speed_mm_s * dt
            near_ok = g0 + rel_dt <= c.track_neighbour_gate_mm
            if c.track_neighbour_mm > 0 and near_ok and moved.any():  # with its neighbours
                near = np.linalg.norm(self._pts[:, None] - self._pts[moved][None], axis=2)
                for j in np.flatnonzero(~moved):
                    order = np.argsort(near[j], kind="stable")[:3]
                    order = order[near[j][order] < c.track_neighbour_mm]
                    if order.size:
                        pred[j] = self._pts[j] + self._vel[moved][order].mean(axis=0) * dt
                        gate[j] = g0 + c.track_relative_speed_mm_s * dt
            j_pt = _match_tracks(np.ascontiguousarray(pts), pred, gate.astype(np.float64))
            ok = j_pt >= 0
            k = j_pt[ok]
            ids[ok] = self._ids[k]
            birth[ok] = self._birth[k]
            vel[ok] = (pts[ok] - self._pts[k]) / dt
            has_vel[ok] = True
        new = ids < 0
        ids[new] = np.arange(self._next, self._next + int(new.sum()))
        self._next += int(new.sum())
        self._pts, self._vel, self._has_vel, self._ids, self._t = pts, vel, has_vel, ids, t
        self._birth = birth
        return ids


def test_tracker_kernel_matches_the_numpy_steps(rng):
    cfg = BootConfig()
    rate = 50.0
    a, b = PointTracker(rate, cfg), _NumpyTracker(rate, cfg)
    n = 120
    base = rng.normal(scale=400.0, size=(n, 3))
    speed = rng.normal(scale=600.0, size=(n, 3))  # mm/s: fast points leave their gates
    t = 0.0
    for f in range(300):
        t += (1.0 + 0.5 * rng.random()) / rate  # uneven frame times
        pos = base + speed * t + rng.normal(scale=2.0, size=(n, 3))
        keep = rng.random(n) > 0.1  # dropouts: tracks end and start
        ghosts = rng.normal(scale=400.0, size=(rng.integers(0, 6), 3))
        pts = np.concatenate([pos[keep], ghosts])[
            rng.permutation(int(keep.sum()) + ghosts.shape[0])
        ]
        if f == 150 or 200 <= f < 200 + cfg.track_hold_frames + 1:
            pts = pts[:0]  # an empty frame; then more in a row than the tracks outlive
        ia, ib = a.update(pts.astype(np.float32), t), b.update(pts.astype(np.float32), t)
        np.testing.assert_array_equal(ia, ib)
        np.testing.assert_array_equal(a.ages(), b._t - b._birth)
        np.testing.assert_array_equal(a._vel, b._vel)
        np.testing.assert_array_equal(a._has_vel, b._has_vel)
    assert a._next == b._next > n  # tracks did break and restart


def test_a_fast_limb_is_tracked_with_its_neighbours():
    """A sprinter at 250 Hz: the body moves 9 m/s, the swinging foot 12 m/s (48 mm a frame,
    beyond the gate of a point with no velocity yet, which is left in place). The foot's points
    break their tracks at once; predicted with their tracked neighbours' velocity they are
    continued from the next frame on, where left in place they would start a new track every
    frame. A lone point as fast, with no neighbour, is never continued."""
    rate = 250.0
    start = np.array([[0.0, 0, 0], [0, 90, 0], [0, 0, 90], [0, 150, 150], [0, 250, 150],
                      [0, 5000, 0]])  # fmt: skip
    speed = np.array([9000.0, 9000, 9000, 12000, 12000, 12000])  # mm/s along x
    for cfg, continued in ((BootConfig(), True), (BootConfig(track_neighbour_mm=0.0), False)):
        tr = PointTracker(rate, cfg)
        ids = np.array([tr.update(start + np.outer(speed * f / rate, [1, 0, 0]), f / rate)
                        for f in range(8)])  # fmt: skip
        assert (ids[1:, :3] == ids[0, :3]).all()  # the body: one track each throughout
        assert (ids[1, 3:] != ids[0, 3:]).all()  # the fast points broke at once
        assert bool((ids[2:, 3:5] == ids[1, 3:5]).all()) is continued
        assert len(set(ids[:, 3])) == (2 if continued else 8)
        assert len(set(ids[:, 5])) == 8  # the lone point: never continued
