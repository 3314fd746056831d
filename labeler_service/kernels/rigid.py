"""Missing-marker recovery (seed 003 Sec. 3.3) and the Kabsch fit behind it.

Each marker has a recovery set: itself and the (up to 7) markers most rigidly linked to it
(lowest ``A + w D``, the rigid-body cost of :mod:`labeler_service.structure`), and a snapshot
``ref`` of the set's positions the last time all of them were observed. A hidden marker is
estimated from the members observed now:

- ``displacement`` (the paper): the average over observed markers ``k`` of
  ``y_k + (ref_m - ref_k)``: each visible marker predicts the hidden one by its last displacement;
- ``kabsch``: the rotation and translation that best map the observed markers' ``ref`` onto their
  current positions (least squares, reflection excluded) applied to ``ref_m``. Needs 3 observed
  markers; with fewer it falls back to displacement averaging.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit


@njit
def _kabsch(src, dst, n, R, t):
    """Least-squares rigid transform of the first ``n`` rows of ``src`` onto ``dst``:
    fills ``R (3, 3)`` and ``t (3,)`` so that ``R @ src_i + t ~ dst_i``."""
    cs = np.zeros(3)
    cd = np.zeros(3)
    for i in range(n):
        for a in range(3):
            cs[a] += src[i, a]
            cd[a] += dst[i, a]
    for a in range(3):
        cs[a] /= n
        cd[a] /= n
    h = np.zeros((3, 3))
    for i in range(n):
        for a in range(3):
            for c in range(3):
                h[a, c] += (src[i, a] - cs[a]) * (dst[i, c] - cd[c])
    u, _s, vt = np.linalg.svd(h)
    # R = V diag(1, 1, d) U^T with d = sign(det(V U^T))
    v = vt.T
    ut = u.T
    d = np.linalg.det(v @ ut)
    sgn = 1.0 if d >= 0.0 else -1.0
    for a in range(3):
        for c in range(3):
            R[a, c] = v[a, 0] * ut[0, c] + v[a, 1] * ut[1, c] + sgn * v[a, 2] * ut[2, c]
    for a in range(3):
        t[a] = cd[a] - (R[a, 0] * cs[0] + R[a, 1] * cs[1] + R[a, 2] * cs[2])


@njit
def _recover(
    missing, rec_members, rec_size, rec_ref, rec_ok, obs, method, rec, has_rec, src, dst, R, t
):
    """Recovers every marker with ``missing[m]`` into ``rec (M, 3)`` (``has_rec[m]`` says which
    succeeded) from its recovery set: ``rec_members[m, 1:rec_size[m]]`` (``rec_members[m, 0]``
    is ``m``), whose positions at the last frame where the whole set was observed are
    ``rec_ref[m]``. ``obs (M, 3)`` holds this frame's observed positions (NaN otherwise).
    ``method`` 1 = Kabsch (3+ observed), else / fallback = displacement averaging."""
    m_total = missing.shape[0]
    for m in range(m_total):
        has_rec[m] = False
        if not missing[m] or not rec_ok[m]:
            continue
        c = 0
        for k in range(1, rec_size[m]):
            mk = rec_members[m, k]
            if obs[mk, 0] == obs[mk, 0]:
                for a in range(3):
                    src[c, a] = rec_ref[m, k, a]
                    dst[c, a] = obs[mk, a]
                c += 1
        if c == 0:
            continue
        if method == 1 and c >= 3:
            _kabsch(src, dst, c, R, t)
            for a in range(3):
                rec[m, a] = (
                    R[a, 0] * rec_ref[m, 0, 0]
                    + R[a, 1] * rec_ref[m, 0, 1]
                    + R[a, 2] * rec_ref[m, 0, 2]
                    + t[a]
                )
        else:
            for a in range(3):
                acc = 0.0
                for i in range(c):
                    acc += dst[i, a] + rec_ref[m, 0, a] - src[i, a]
                rec[m, a] = acc / c
        has_rec[m] = True


@njit
def _snapshot(assigned, obs, rec_members, rec_size, rec_ref, rec_ok):
    """Stores the recovery-set positions of every marker whose whole set is observed."""
    for m in range(assigned.shape[0]):
        n = rec_size[m]
        if n == 0:
            continue
        full = True
        for k in range(n):
            if assigned[rec_members[m, k]] < 0:
                full = False
                break
        if full:
            for k in range(n):
                for a in range(3):
                    rec_ref[m, k, a] = obs[rec_members[m, k], a]
            rec_ok[m] = True
