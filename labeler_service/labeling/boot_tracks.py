"""Frame-to-frame tracks of anonymous points for the boot (step 1 of labeling/boot.py):
``PointTracker`` gives each point a track id, ``track_history`` the tracks' positions over a
window, ``labels_along_tracks`` spreads the last frame's labels over the window."""

from __future__ import annotations

import numpy as np

from labeler_service.errors import LabelerError
from labeler_service.labeling.boot_config import BootConfig
from labeler_service.labeling.kernels.track import _track_history, _track_step


# ---------------------------------------------------------------------------- tracking
def track_gates(config: BootConfig, dt: float) -> tuple[float, float]:
    """The tracker's gates (mm) over a frame step ``dt``: around a constant-velocity prediction
    (``track_gate_mm`` plus ``track_accel_mm_s2`` dt^2), and around a point with no velocity
    yet (that plus ``track_speed_mm_s`` dt)."""
    g0 = config.track_gate_mm + config.track_accel_mm_s2 * dt * dt
    return g0, g0 + config.track_speed_mm_s * dt


class PointTracker:
    """Frame-to-frame identity of anonymous points (nearest neighbour with velocity).

    ``update(points, t)`` returns one track id per point: the id of the previous frame's point
    it continues, or a new id. A match must be mutual (each is the other's nearest) and within
    ``track_gate_mm + a dt^2`` of the constant-velocity prediction. A track with no velocity yet
    (one frame old) is predicted at the mean velocity of its nearest tracked neighbours within
    ``track_neighbour_mm`` (gate ``+ track_relative_speed_mm_s dt``, while that gate is at most
    ``track_neighbour_gate_mm``: at 25 Hz and below it is not), or not moved (gate ``+
    track_speed_mm_s dt``): a point that broke its track in a fast limb would
    otherwise never be continued. Ambiguous points simply start new tracks: the boot wants few,
    clean tracks.
    A frame with no point at all (a dropout) leaves the tracks as they were, up to
    ``track_hold_frames`` such frames in a row; the next points continue them over the gap.
    """

    def __init__(self, rate: float, config: BootConfig | None = None) -> None:
        if not (np.isfinite(rate) and rate > 0):
            raise LabelerError(f"invalid frame rate {rate}")
        self.rate = float(rate)
        self.config = config or BootConfig()
        self._next = 0
        self._pts = np.zeros((0, 3))
        self._vel = np.zeros((0, 3))
        self._has_vel = np.zeros(0, dtype=bool)
        self._ids = np.zeros(0, dtype=np.int64)
        self._birth = np.zeros(0)  # (per current point) when its track started
        self._t = np.nan
        self._empty = 0  # empty frames in a row held over
        #: tracks the last :meth:`update` began (its other points continue the frame before's)
        self.born = 0

    def update(self, points: np.ndarray, t: float) -> np.ndarray:
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        if pts.shape[0] == 0 and self._ids.size and self._empty < self.config.track_hold_frames:
            self._empty += 1
            self.born = 0
            return np.zeros(0, dtype=np.int64)
        self._empty = 0
        dt = t - self._t
        if not (np.isfinite(dt) and dt > 0):
            dt = 1.0 / self.rate
        c = self.config
        g0, _ = track_gates(c, dt)
        rel_dt = c.track_relative_speed_mm_s * dt
        # mutual nearest prediction within its gate (kernels/track.py: a sweep index with
        # bounded searches; two KD-trees cost ~0.5 ms a frame at 500 points), the prediction,
        # the gates and the new state in the same kernel
        ids, vel, has_vel, birth, nxt = _track_step(
            pts,
            self._pts,
            self._vel,
            self._has_vel,
            self._ids,
            self._birth,
            float(dt),
            float(t),
            float(g0),
            float(c.track_speed_mm_s * dt),
            self._next,
            float(rel_dt),
            float(c.track_neighbour_mm if g0 + rel_dt <= c.track_neighbour_gate_mm else 0.0),
        )
        self.born = int(nxt) - self._next  # (ids are numbered in order: new ones from _next)
        self._next = int(nxt)
        self._pts, self._vel, self._has_vel, self._ids, self._t = pts, vel, has_vel, ids, t
        self._birth = birth
        return ids

    def ages(self) -> np.ndarray:
        """``(N,)`` seconds each point of the last :meth:`update` has been tracked."""
        return self._t - self._birth


def track_history(frames: list[tuple[np.ndarray, np.ndarray]], ids: np.ndarray) -> np.ndarray:
    """``(N, W, 3)`` positions of the tracks ``ids`` in the window ``frames`` (list of
    ``(points, ids)``, oldest first), NaN where a track has no point in a frame."""
    out = np.full((ids.shape[0], len(frames), 3), np.nan)
    if not frames:
        return out
    # one numba pass over the stacked window (kernels/track.py): a sort and a search per frame
    # cost ~0.7 ms of each snapshot on the frame thread at 500 points and 24 frames
    sizes = np.array([f[1].shape[0] for f in frames], dtype=np.int64)
    starts = np.zeros(sizes.size + 1, dtype=np.int64)
    np.cumsum(sizes, out=starts[1:])
    pts = np.concatenate([np.asarray(f[0], dtype=np.float64).reshape(-1, 3) for f in frames])
    fids = np.concatenate([np.asarray(f[1], dtype=np.int64) for f in frames])
    _track_history(np.ascontiguousarray(ids, dtype=np.int64), pts, fids, starts, out)
    return out


def labels_along_tracks(
    window: list[tuple[np.ndarray, np.ndarray]], ids: np.ndarray, labels: np.ndarray
) -> list[np.ndarray]:
    """Spreads the labels of tracks ``ids`` over every frame of ``window``."""
    lab = labels >= 0
    tid, tl = ids[lab], labels[lab]
    order = np.argsort(tid)
    tid, tl = tid[order], tl[order]
    out = []
    for _, fids in window:
        res = np.full(fids.shape[0], -1, dtype=np.int64)
        if tid.size:
            pos = np.minimum(np.searchsorted(tid, fids), tid.size - 1)
            hit = tid[pos] == fids
            res[hit] = tl[pos[hit]]
        out.append(res)
    return out
