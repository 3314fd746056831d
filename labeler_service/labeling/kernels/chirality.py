"""Signed volumes of marker quadruples and their statistics over training frames, in one loop
(``structure.chirality_quads`` and ``twin_witnesses``; ours).

For each quadruple ``[a, b, c, d]`` and frame, the signed volume ``(b - a) . ((c - a) x
(d - a))`` (NaN where a marker is unseen); per quadruple, the frames where it is seen, the
fraction of them positive and the 10th percentile (numpy's linear interpolation) of the
thickness, the cube root of ``|volume|`` (0 where none is seen). The window model of a labeled
start trains these for every subject in-stream: the numpy version built ``(F, Q, 3)`` stacks
for up to 20,000 quadruples a subject, ~80 % of a 10-person window's training. Compiled without
fastmath: the window models it gives are the numpy version's, byte for byte (checked on 45
windows when it replaced it); its twin, per frame with ``np.linalg.det``, is
``tests/reference.py``'s ``volume_stats``.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit


@njit(fastmath=False)
def volume_stats(p, q, quantile):
    """``(n, pos_frac, thick)`` per row of ``q (Q, 4)`` over the frames of ``p (F, m, 3)``."""
    f_count = p.shape[0]
    rows = q.shape[0]
    n = np.zeros(rows, dtype=np.int64)
    pos_frac = np.zeros(rows, dtype=np.float64)
    thick = np.zeros(rows, dtype=np.float64)
    size = np.empty(f_count, dtype=np.float64)
    for k in range(rows):
        a, b, c, d = q[k, 0], q[k, 1], q[k, 2], q[k, 3]
        seen = 0
        positive = 0
        for f in range(f_count):
            # differences in p's dtype, then float64 (as the numpy twin takes them)
            u0 = np.float64(p[f, b, 0] - p[f, a, 0])
            u1 = np.float64(p[f, b, 1] - p[f, a, 1])
            u2 = np.float64(p[f, b, 2] - p[f, a, 2])
            v0 = np.float64(p[f, c, 0] - p[f, a, 0])
            v1 = np.float64(p[f, c, 1] - p[f, a, 1])
            v2 = np.float64(p[f, c, 2] - p[f, a, 2])
            w0 = np.float64(p[f, d, 0] - p[f, a, 0])
            w1 = np.float64(p[f, d, 1] - p[f, a, 1])
            w2 = np.float64(p[f, d, 2] - p[f, a, 2])
            c0 = v1 * w2 - v2 * w1
            c1 = v2 * w0 - v0 * w2
            c2 = v0 * w1 - v1 * w0
            vol = u0 * c0 + u1 * c1 + u2 * c2
            if np.isfinite(vol):
                size[seen] = np.cbrt(abs(vol))
                seen += 1
                if vol > 0:
                    positive += 1
        n[k] = seen
        pos_frac[k] = positive / max(seen, 1)
        if seen:
            s = np.sort(size[:seen])
            at = quantile * (seen - 1)
            lo = int(np.floor(at))
            hi = min(lo + 1, seen - 1)
            thick[k] = s[lo] + (at - lo) * (s[hi] - s[lo])
    return n, pos_frac, thick
