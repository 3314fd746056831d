"""Anchor-triangle placements of a body at boot (:func:`~labeler_service.labeling.boot_match.
_body_candidates`), in two kernels.

A boot attempt of 10 hugging performers searches ~24,000 anchor triangles (point triples whose
sides match a body's anchor triangle) in ~250 body searches; in numpy, joining the edges into
triples and fitting each triple (a batched SVD) cost ~0.12 s of a 0.68 s attempt, mostly in
per-call overhead on arrays of ~100 rows:

- :func:`_join_triangles`: the triples, in exactly the order of the numpy join it replaces
  (edge 01 in its order, then the edges 02 sharing vertex 0 in their stable order by vertex,
  kept when edge 12 exists and the two far vertices differ);
- :func:`_anchor_predict`: per triple, the proper rotation and translation mapping the body's
  anchor triangle onto it (:func:`.rigid._kabsch`, Horn's closed form) applied to every member
  of the body's reference shape.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.rigid import _kabsch


@njit
def _join_triangles(a1, b1, a2s, b2s, keys3, n):
    """Triples ``(C, 3)`` ``(p, q, r)``: ``(p, q)`` an edge of ``a1, b1``, ``(p, r)`` an edge of
    ``a2s, b2s`` (sorted by ``a2s``, stable), ``(q, r)`` an edge whose key ``q * n + r`` is in
    the sorted ``keys3``, and ``q != r``."""
    nk = keys3.shape[0]
    if nk == 0:
        return np.empty((0, 3), dtype=np.int64)
    lo = np.searchsorted(a2s, a1, side="left")
    hi = np.searchsorted(a2s, a1, side="right")
    out = np.empty((np.sum(hi - lo), 3), dtype=np.int64)
    c = 0
    for i in range(a1.shape[0]):
        p = a1[i]
        q = b1[i]
        for j in range(lo[i], hi[i]):
            r = b2s[j]
            if q == r:
                continue
            key = q * n + r
            pos = np.searchsorted(keys3, key)
            if pos < nk and keys3[pos] == key:
                out[c, 0] = p
                out[c, 1] = q
                out[c, 2] = r
                c += 1
    return out[:c]


@njit
def _anchor_predict(tri_shape, shape, pts, trip):
    """``pred (C, k, 3)``: every member of ``shape (k, 3)`` moved by the proper rigid motion
    that best maps ``tri_shape (3, 3)`` (the anchor triangle's reference positions) onto the
    points ``pts[trip[c]]`` of each triple ``c``."""
    C = trip.shape[0]
    k = shape.shape[0]
    pred = np.empty((C, k, 3))
    dst = np.empty((3, 3))
    R = np.empty((3, 3))
    t = np.empty(3)
    for c in range(C):
        for v in range(3):
            for a in range(3):
                dst[v, a] = pts[trip[c, v], a]
        _kabsch(tri_shape, dst, 3, R, t)
        for j in range(k):
            for a in range(3):
                pred[c, j, a] = (
                    R[a, 0] * shape[j, 0] + R[a, 1] * shape[j, 1] + R[a, 2] * shape[j, 2] + t[a]
                )
    return pred
