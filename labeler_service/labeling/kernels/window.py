"""Sliding-window structure model (seed 003 Eq. 1-2).

For every link of every body a ring buffer of the last ``T`` distances (NaN when the two markers
were not both observed) gives ``D`` (mean) and ``A`` (deviation) over the window; missing samples
are skipped. Until a link has ``min_samples`` samples the trained ``D``, ``A`` stay in use.

Guard (ours, issue 10): with ``guard`` a body whose assignment failed the 3D template check
(``bodies.ok[b]`` False, :mod:`.repair`) pushes no sample this frame (its slot is NaN), so a
swapped assignment is never learned; with ``drift > 0`` the window's ``D`` stays within
``drift`` mm of the trained ``D0`` (the template is the anchor).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit


@njit
def _window_update(bodies, obs, ptr, min_samples, guard=False, drift=0.0):
    """Pushes the distances of frame ``obs (M, 3)`` (NaN rows = not observed) at ring slot
    ``ptr`` of ``bodies.ring`` and refreshes ``bodies.D``, ``bodies.A`` of the touched links in
    place (:class:`.state.Bodies`); ``guard``, ``drift``: the module docstring."""
    body_markers, body_size = bodies.members, bodies.size
    ring, s1, s2, cnt = bodies.ring, bodies.s1, bodies.s2, bodies.cnt
    D0, A0, D, A = bodies.D0, bodies.A0, bodies.D, bodies.A
    nb = body_markers.shape[0]
    for b in range(nb):
        n = body_size[b]
        skip = guard and not bodies.ok[b]
        for i in range(n):
            mi = body_markers[b, i]
            for j in range(i + 1, n):
                mj = body_markers[b, j]
                old = ring[b, i, j, ptr]
                if old == old:
                    s1[b, i, j] -= old
                    s2[b, i, j] -= old * old
                    cnt[b, i, j] -= 1
                dx = obs[mi, 0] - obs[mj, 0]
                dy = obs[mi, 1] - obs[mj, 1]
                dz = obs[mi, 2] - obs[mj, 2]
                d = np.sqrt(dx * dx + dy * dy + dz * dz)
                if skip:
                    d = np.nan
                ring[b, i, j, ptr] = d
                d = ring[b, i, j, ptr]  # the stored (float32) value, subtracted exactly later
                if d == d:
                    s1[b, i, j] += d
                    s2[b, i, j] += d * d
                    cnt[b, i, j] += 1
                c = cnt[b, i, j]
                if c >= min_samples and c > 0:
                    mean = s1[b, i, j] / c
                    var = s2[b, i, j] / c - mean * mean
                    if drift > 0.0 and D0[b, i, j] == D0[b, i, j]:
                        mean = min(max(mean, D0[b, i, j] - drift), D0[b, i, j] + drift)
                    D[b, i, j] = mean
                    A[b, i, j] = np.sqrt(var) if var > 0.0 else 0.0
                else:
                    D[b, i, j] = D0[b, i, j]
                    A[b, i, j] = A0[b, i, j]
                D[b, j, i] = D[b, i, j]
                A[b, j, i] = A[b, i, j]
