"""Labels over a window of frames stacked in one array (a booting labeler's installs).

A booting labeler installs a boot or an extension between two frames, on the frame path: it
gives the found labels to the window's frames along the point tracks (``BootingLabeler._spread``)
and its inner labeler restarts the new markers from the window's labels
(``Labeler._seed``: the labeled positions per frame). Per window frame a few numpy calls
(a search, ``np.unique``, a scatter) cost ~0.4 ms and ~0.8 ms of each such install at 10
performers and 360 Hz (24 frames of ~500 points); here each is one pass over the stacked
frames, frame ``k`` at rows ``starts[k]:starts[k + 1]``.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit


@njit
def _window_obs(points, labels, starts, mask, out):
    """Fills ``out (F, M, 3)`` (NaN beforehand) with the labeled positions of the markers in
    ``mask (M,)``: per frame ``k`` each point with a label in ``0..M-1`` gives that marker's
    position, the first point of the frame with a label only (a label given twice keeps its
    first point, as ``frame.frame_labels``)."""
    m = mask.shape[0]
    seen = np.zeros(m, dtype=np.bool_)
    for k in range(starts.shape[0] - 1):
        for i in range(starts[k], starts[k + 1]):
            lab = labels[i]
            if lab < 0 or lab >= m or seen[lab]:
                continue
            seen[lab] = True
            if mask[lab]:
                for a in range(3):
                    out[k, lab, a] = points[i, a]
        for i in range(starts[k], starts[k + 1]):
            lab = labels[i]
            if 0 <= lab < m:
                seen[lab] = False


@njit
def _spread_labels(tid, tlab, ids, labels, starts, n_labels):
    """Gives each free point (``labels`` < 0) of the stacked frames the label ``tlab[j]`` of
    its track ``tid[j]`` (``tid`` sorted, unique), the first free point of a frame only, and
    only if the frame has no point with that label yet (a track split may repeat a label).
    ``labels (P,)`` is changed in place; returns how many points got a label."""
    taken = np.zeros(n_labels, dtype=np.bool_)
    nt = tid.shape[0]
    given = 0
    if nt == 0:
        return given
    for k in range(starts.shape[0] - 1):
        lo, hi = starts[k], starts[k + 1]
        for i in range(lo, hi):
            if labels[i] >= 0:
                taken[labels[i]] = True
        for i in range(lo, hi):
            if labels[i] >= 0:
                continue
            j = np.searchsorted(tid, ids[i])
            if j >= nt or tid[j] != ids[i]:
                continue
            lab = tlab[j]
            if taken[lab]:
                continue
            taken[lab] = True
            labels[i] = lab
            given += 1
        for i in range(lo, hi):
            if labels[i] >= 0:
                taken[labels[i]] = False
    return given
