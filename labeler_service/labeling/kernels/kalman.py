"""Constant-velocity Kalman filter per marker (seed 003 Eq. 3-4).

State ``x = [x, y, z, vx, vy, vz]``, ``F = [[I, dt I], [0, I]]``, ``H = [I, 0]``,
``Q = q [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]]`` (white acceleration of variance ``q`` per
axis, learned per marker), ``R = r I``. With isotropic ``Q``, ``R`` and initial ``P`` the
covariance stays ``P = P2 (x) I3`` (Kronecker), so we store the 2x2 block per marker as
``P[m] = (p_pp, p_pv, p_vv)``: the filter is exact and 9x cheaper than the full 6x6 form (the
test compares it with the full 6x6 filter).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit


@njit
def _predict(x, P, q, active, dt, p_cap):
    """Eq. 3 prediction in place for active markers; the position variance is capped at
    ``p_cap`` (mm^2) so a lost marker's gate stays bounded."""
    m = x.shape[0]
    dt2 = dt * dt
    for i in range(m):
        if not active[i]:
            continue
        for a in range(3):
            # x = F x
            x[i, a] += dt * x[i, 3 + a]
        pp, pv, vv = P[i, 0], P[i, 1], P[i, 2]
        qi = q[i]
        # P = F P F^T + Q
        npp = pp + 2.0 * dt * pv + dt2 * vv + qi * dt2 * dt2 * 0.25
        npv = pv + dt * vv + qi * dt2 * dt * 0.5
        nvv = vv + qi * dt2
        if npp > p_cap:
            f = p_cap / npp
            npp = p_cap
            npv *= np.sqrt(f)
        P[i, 0] = npp
        P[i, 1] = npv
        P[i, 2] = nvv


@njit
def _update_one(x, P, i, z0, z1, z2, r):
    """Eq. 4 update of marker ``i`` with measurement ``z`` and variance ``r`` per axis."""
    pp, pv, vv = P[i, 0], P[i, 1], P[i, 2]
    # S = H P H^T + R ; K = P H^T S^-1
    s = pp + r
    kp = pp / s
    kv = pv / s
    z = (z0, z1, z2)
    for a in range(3):
        innov = z[a] - x[i, a]
        x[i, a] += kp * innov
        x[i, 3 + a] += kv * innov
    # P = (I - K H) P
    P[i, 0] = (1.0 - kp) * pp
    P[i, 1] = (1.0 - kp) * pv
    P[i, 2] = vv - kv * pv


@njit
def _start_or_update(x, P, i, z0, z1, z2, r, v0):
    """Eq. 4 update, or the initial state ``x = [z, 0]``, ``P = (r, 0, v0)`` when marker ``i``
    has no state yet (NaN)."""
    if x[i, 0] == x[i, 0]:
        _update_one(x, P, i, z0, z1, z2, r)
        return
    x[i, 0] = z0
    x[i, 1] = z1
    x[i, 2] = z2
    x[i, 3] = 0.0
    x[i, 4] = 0.0
    x[i, 5] = 0.0
    P[i, 0] = r
    P[i, 1] = 0.0
    P[i, 2] = v0


@njit
def _update(x, P, z, has, r, v0):
    """:func:`_start_or_update` in place of every marker with ``has[i]`` and a finite row
    ``z[i]``."""
    for i in range(x.shape[0]):
        if has[i] and z[i, 0] == z[i, 0]:
            _start_or_update(x, P, i, z[i, 0], z[i, 1], z[i, 2], r, v0)
