"""What every frame labeler returns, and the interface they share.

A labeler is anything with :class:`FrameLabeler`'s ``marker_names``, ``process(points, t,
labels=None)``, ``warmup()`` and ``body_extent()``: the online labeler (Yu, Li and Deng 2007,
``labeler_service.labeling.labeler``) and the closest-point baseline
(``labeler_service.labeling.baseline``) both fit, so ``evaluate``, ``label`` and the service
treat them alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING, Protocol

import numpy as np

from labeler_service.errors import LabelerError
from labeler_service.labeling.kernels.stacked import _window_obs

if TYPE_CHECKING:
    from labeler_service.labeling.templates import LabelerModel


class MarkerState(IntEnum):
    """Per-marker state in a labeled frame (wire values too).

    The numba kernels use the plain ``int`` copies below (``MISSING``, ``OBSERVED``,
    ``RECOVERED``): numba reads module-level ints as compile-time constants, and this enum stays
    the one definition of the values.
    """

    MISSING = 0  # neither seen nor recovered: position is NaN
    OBSERVED = 1  # a point of this frame carries the label
    RECOVERED = 2  # hidden this frame; position estimated (e.g. from its rigid body)


MISSING = int(MarkerState.MISSING)
OBSERVED = int(MarkerState.OBSERVED)
RECOVERED = int(MarkerState.RECOVERED)


@dataclass(slots=True)
class LabeledFrame:
    """The labeler's answer for one input frame.

    ``point_labels[i]`` is the marker index (into ``marker_names``) given to input point ``i``,
    or -1 when the point stays unlabeled (ghost or unknown). ``positions`` and ``state`` cover
    every marker of the model, ``(M, 3)`` float32 mm (NaN when missing) and ``(M,)`` uint8
    :class:`MarkerState`. ``process_us`` is the labeling time of this frame.
    """

    t: float
    point_labels: np.ndarray
    positions: np.ndarray
    state: np.ndarray
    process_us: float = 0.0

    @property
    def n_observed(self) -> int:
        return int(np.count_nonzero(self.state == MarkerState.OBSERVED))

    @property
    def n_recovered(self) -> int:
        return int(np.count_nonzero(self.state == MarkerState.RECOVERED))

    @property
    def n_unlabeled(self) -> int:
        return int(np.count_nonzero(self.point_labels < 0))


class FrameLabeler(Protocol):
    """The interface shared by the online labeler and the closest-point baseline.

    ``process`` takes one frame of anonymous points ``(N, 3)`` float32 mm (finite; missing
    points are simply absent) and its capture time. During the training window the caller
    passes ``labels`` too: ``(N,)`` int marker indices, -1 for points without a label.

    ``warmup()`` compiles (or loads) whatever the labeler runs per frame without touching its
    state, so the first real frame pays no compile time. ``body_extent()`` is ``(M,)`` mm per
    marker, the longest marker-pair distance of its smallest rigid body (NaN for a marker
    without one, or before training); scorers divide recovery errors by it. ``model`` is the
    subject model it labels from (trained, loaded or booted from); None for a labeler without
    one (the baseline, or before training).
    """

    @property
    def model(self) -> LabelerModel | None: ...

    @property
    def marker_names(self) -> tuple[str, ...]: ...

    def process(
        self, points: np.ndarray, t: float, labels: np.ndarray | None = None
    ) -> LabeledFrame: ...

    def warmup(self) -> None: ...

    def body_extent(self) -> np.ndarray: ...


def frame_points(points: np.ndarray) -> np.ndarray:
    """A frame's anonymous points as the labelers take them: ``(N, 3)`` float32, C-contiguous,
    all finite (a missing point is left out, never NaN). Raises :class:`LabelerError`."""
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise LabelerError(f"points must be (N, 3), got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise LabelerError("points must be finite (drop missing points instead of NaN)")
    return np.ascontiguousarray(pts)


def frame_labels(labels: np.ndarray, n_points: int, n_markers: int) -> np.ndarray:
    """A labeled frame's labels as the labelers take them: ``(n_points,)`` int64 marker
    indices, -1 for a point without one (a negative or out-of-range label included), and a
    label given to several points kept by the first of them only (the others -1: which point
    is the marker cannot be told, and no output frame may carry a label twice). Raises
    :class:`LabelerError` when the count does not match the points."""
    lab = np.asarray(labels).astype(np.int64, copy=False).reshape(-1)
    if lab.shape[0] != n_points:
        raise LabelerError(f"{lab.shape[0]} labels for {n_points} points")
    lab = np.where((lab >= 0) & (lab < n_markers), lab, -1)
    have = np.flatnonzero(lab >= 0)
    _, first = np.unique(lab[have], return_index=True)
    lab[np.delete(have, first)] = -1
    return lab


def window_observations(
    frames: Sequence[tuple[float, np.ndarray, np.ndarray]], mask: np.ndarray
) -> np.ndarray:
    """``(F, M, 3)`` float64: per labeled frame ``(t, points, labels)`` of ``frames`` the
    position of each marker in ``mask (M,)`` bool, NaN where the frame does not label it.
    Points and labels are read as :func:`frame_points` and :func:`frame_labels` read them (the
    same errors; a label given twice in a frame goes to its first point), in one kernel pass
    over the stacked frames (:func:`~.kernels.stacked._window_obs`): per frame, those two calls
    and a scatter cost ~0.8 ms of a booting labeler's install on the frame path (24 frames at
    360 Hz, 10 performers)."""
    m = mask.shape[0]
    nf = len(frames)
    obs = np.full((nf, m, 3), np.nan)
    if nf == 0:
        return obs
    pts = [np.asarray(f[1], dtype=np.float32) for f in frames]
    labs = [np.asarray(f[2]).astype(np.int64, copy=False).reshape(-1) for f in frames]
    for p, lab in zip(pts, labs, strict=True):
        if p.ndim != 2 or p.shape[1] != 3:
            raise LabelerError(f"points must be (N, 3), got shape {p.shape}")
        if lab.shape[0] != p.shape[0]:
            raise LabelerError(f"{lab.shape[0]} labels for {p.shape[0]} points")
    allp = frame_points(np.concatenate(pts))  # (the finite check, once for the window)
    starts = np.zeros(nf + 1, dtype=np.int64)
    np.cumsum([p.shape[0] for p in pts], out=starts[1:])
    _window_obs(allp, np.concatenate(labs), starts, np.ascontiguousarray(mask, dtype=np.bool_), obs)
    return obs
