"""The vouch check (ours, issue 10 ``ghosts3``: a performer walking out takes ghosts).

A label is either a *continuing* one - the marker was observed in the previous frame and its
point this frame lies within ``vouch_track_mm`` of its prediction (the Kalman one or the
rigid-body / common-mode one, :mod:`.motion`, :mod:`.gating`) or of its previous point -
or a *new* one: an
acquisition (the marker was missing) or a hop (its previous point vanished or it moved to
another point). A continuing label is kept as it is. A new label is kept only when it is
vouched for: one of the marker's rigid bodies has ``vouch_need`` other members holding a
continuing label whose distances to the new point agree with the body's ``D`` (within
``presence_tol_mm`` plus 3 ``A``).

Ghosts are born next to the markers still visible and live a few frames; the markers of a
performer walking out have lost their rigid neighbourhood, so nothing continuing vouches for a
ghost, and since every ghost label must start as a new label, following a ghost never starts
either (two ghosts cannot vouch for each other: neither continues a labeled track).

A marker that reappears with its whole rigid neighbourhood (an occluded hand, a body part
back from a gap) has nobody to vouch for it. It is kept as a *tentative* track: once it has
been given the same point (the point proposed within ``vouch_track_mm`` of the one proposed in
the previous frame) for ``vouch_wait`` frames in a row, the label is accepted - unless its
subject is thin (fewer than half of its markers on continuing tracks observed for
``vouch_wait`` frames or more: it is walking out), where a tentative track needs, besides, one
member of its body on a continuing label or on a tentative track as old, keeping its ``D``
(a part of the body re-appearing together; two ghosts rarely keep a link for that long).
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.kernels.state import NONE


@njit
def _near(points, j, ref, i, lim2):
    """Point ``j`` lies within ``sqrt(lim2)`` of ``ref[i]`` (False when ``ref[i]`` is NaN)."""
    d2 = 0.0
    for a in range(3):
        d = np.float64(points[j, a]) - np.float64(ref[i, a])
        d2 += d * d
    return d2 <= lim2  # a NaN reference compares False


@njit
def _vouched(m, j, points, assigned, cont, tent, wait, bodies, need, tol):
    """``need`` members of one of ``m``'s bodies keep their ``D`` to point ``j``: members on a
    continuing label (``cont``) or on a tentative track ``wait`` frames old (``|tent|``)."""
    members, size, D, A = bodies.members, bodies.size, bodies.D, bodies.A
    for q in range(bodies.mb_ptr[m], bodies.mb_ptr[m + 1]):
        b = bodies.mb_idx[q]
        km = -1
        for k in range(size[b]):
            if members[b, k] == m:
                km = k
        c = 0
        for k in range(size[b]):
            e = members[b, k]
            je = assigned[e]
            if e == m or je < 0 or D[b, km, k] != D[b, km, k]:  # noqa: PLR0124 (NaN)
                continue
            if not cont[e] and abs(tent[e]) < wait:
                continue
            d2 = 0.0
            for a in range(3):
                d = np.float64(points[j, a]) - np.float64(points[je, a])
                d2 += d * d
            if abs(np.sqrt(d2) - D[b, km, k]) <= tol + 3.0 * A[b, km, k]:
                c += 1
        if c >= need:
            return True
    return False


@njit
def _held(i, j, points, tracks, lim2):
    """Point ``j`` continues the track of a marker ``e != i`` of ``i``'s subject observed in
    the previous frame (within ``sqrt(lim2)`` of its previous point or its prediction): a
    real point changing hands (a swap, for the 3D check and the repair), not a point born now."""
    subj_ptr, subj_idx = tracks.subj_ptr, tracks.subj_idx
    for s in range(subj_ptr.shape[0] - 1):
        inside = False
        for k in range(subj_ptr[s], subj_ptr[s + 1]):
            if subj_idx[k] == i:
                inside = True
                break
        if not inside:
            continue
        for k in range(subj_ptr[s], subj_ptr[s + 1]):
            e = subj_idx[k]
            if e == i or tracks.age[e] <= 0:
                continue
            if _near(points, j, tracks.pos, e, lim2) or _near(points, j, tracks.x, e, lim2):
                return True
        return False
    return False


@njit
def _vouch(points, frame_no, tracks, bodies, scratch, params):
    """Drops the new labels of thin subjects nobody vouches for (module docstring), in place
    of ``scratch.assigned`` / ``scratch.owner``; keeps ``tracks.tent`` / ``tracks.tent_pos``
    (the tentative tracks). Uses ``scratch.missing`` as the "continuing" flag (rewritten
    after, by the Kalman update)."""
    x, kx, age, active = tracks.x, tracks.kx, tracks.age, tracks.active
    assigned, owner, cont = scratch.assigned, scratch.owner, scratch.missing
    tent, tent_pos = tracks.tent, tracks.tent_pos
    lim2 = params.vouch_track_mm * params.vouch_track_mm
    held2 = 0.25 * lim2
    use_kx = params.body_prediction
    need, tol, wait = params.vouch_need, params.presence_tol_mm, params.vouch_wait
    subj_ptr, subj_idx = tracks.subj_ptr, tracks.subj_idx
    for s in range(subj_ptr.shape[0] - 1):
        n_act = 0
        n_est = 0
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            i = subj_idx[e]
            if active[i]:
                n_act += 1
                if age[i] > 0:
                    n_est += 1
        if n_act == 0 or 2 * n_est >= n_act:
            for e in range(subj_ptr[s], subj_ptr[s + 1]):
                tent[subj_idx[e]] = 0
                cont[subj_idx[e]] = False
            continue  # not thin: nothing to judge
        pending = False
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            i = subj_idx[e]
            j = assigned[i]
            cont[i] = (
                j >= 0
                and age[i] > 0
                and (
                    _near(points, j, x, i, lim2)
                    or (use_kx and _near(points, j, kx, i, lim2))
                    or _near(points, j, tracks.pos, i, lim2)
                )
            )
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            i = subj_idx[e]
            j = assigned[i]
            if j < 0 or cont[i]:
                tent[i] = 0
            elif not _vouched(
                i, j, points, assigned, cont, tent, 1 << 30, bodies, need, tol
            ) and not _held(i, j, points, tracks, held2):
                # new, not vouched by continuing members, not a held point: tentative
                if tent[i] > 0 and _near(points, j, tent_pos, i, lim2):
                    tent[i] += 1
                else:
                    tent[i] = 1
                for a in range(3):
                    tent_pos[i, a] = points[j, a]
                pending = True
            else:
                tent[i] = 0
        if not pending:
            continue
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            i = subj_idx[e]
            if tent[i] <= 0:
                continue
            if tent[i] >= wait and _vouched(
                i, assigned[i], points, assigned, cont, tent, wait, bodies, 1, tol
            ):
                continue  # accepted below: a continuing label from the next frame on
            tent[i] = -tent[i]  # dropped below (still a voucher for the others)
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            i = subj_idx[e]
            if tent[i] > 0:
                tent[i] = 0
            elif tent[i] < 0:
                tent[i] = -tent[i]
                owner[assigned[i]] = NONE
                assigned[i] = NONE
