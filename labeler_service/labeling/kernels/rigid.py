"""Missing-marker recovery (seed 003 Sec. 3.3) and the Kabsch fit behind it.

Each marker has a recovery set: itself and the (up to 7) markers most rigidly linked to it
(lowest ``A + w D``, the rigid-body cost of :mod:`labeler_service.labeling.training`), and a
snapshot ``ref`` of the set's positions the last time all of them were observed (or, while that
cannot happen, of the marker and 3+ members: :func:`_snapshot`). A hidden marker is estimated
from the members observed now:

- ``displacement`` (the paper): the average over observed markers ``k`` of
  ``y_k + (ref_m - ref_k)``: each visible marker predicts the hidden one by its last displacement;
- ``kabsch``: the rotation and translation that best map the observed markers' ``ref`` onto their
  current positions (least squares, reflection excluded) applied to ``ref_m``. Needs 3 observed
  markers; with fewer it falls back to displacement averaging.
"""

from __future__ import annotations

import math

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.frame import OBSERVED
from labeler_service.labeling.kernels.fitting import _pair_term
from labeler_service.labeling.kernels.params import KABSCH
from labeler_service.labeling.kernels.spatial import ANY, FREE, OWNED, _alone, _nearest
from labeler_service.labeling.kernels.state import NONE


@njit
def _kabsch(src, dst, n, R, t):
    """Least-squares rigid transform of the first ``n`` rows of ``src`` onto ``dst``:
    fills ``R (3, 3)`` and ``t (3,)`` so that ``R @ src_i + t ~ dst_i``.

    The minimiser over proper rotations (the Kabsch problem with reflections excluded), solved
    in Horn's closed form: the unit quaternion is the eigenvector of the largest eigenvalue of a
    symmetric 4x4 matrix built from the cross-covariance (:func:`_horn_quaternion`). No LAPACK
    call: this runs ~360 times a frame at 10 performers (every body's inter-frame motion, every
    recovered or checked marker), so the eigenvector is taken in closed form, with no
    allocation, and by cyclic Jacobi rotations (two 4x4 work arrays) only when that is
    ill-conditioned (nearly collinear members).
    """
    cs0 = cs1 = cs2 = 0.0
    cd0 = cd1 = cd2 = 0.0
    for i in range(n):
        cs0 += src[i, 0]
        cs1 += src[i, 1]
        cs2 += src[i, 2]
        cd0 += dst[i, 0]
        cd1 += dst[i, 1]
        cd2 += dst[i, 2]
    cs0 /= n
    cs1 /= n
    cs2 /= n
    cd0 /= n
    cd1 /= n
    cd2 /= n
    cov = COV0
    for i in range(n):
        cov = _cov_add(
            cov,
            src[i, 0] - cs0,
            src[i, 1] - cs1,
            src[i, 2] - cs2,
            dst[i, 0] - cd0,
            dst[i, 1] - cd1,
            dst[i, 2] - cd2,
        )
    q0, q1, q2, q3 = _horn_quaternion(cov)
    R[0, 0] = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
    R[0, 1] = 2.0 * (q1 * q2 - q0 * q3)
    R[0, 2] = 2.0 * (q1 * q3 + q0 * q2)
    R[1, 0] = 2.0 * (q2 * q1 + q0 * q3)
    R[1, 1] = q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3
    R[1, 2] = 2.0 * (q2 * q3 - q0 * q1)
    R[2, 0] = 2.0 * (q3 * q1 - q0 * q2)
    R[2, 1] = 2.0 * (q3 * q2 + q0 * q1)
    R[2, 2] = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3
    t[0] = cd0 - (R[0, 0] * cs0 + R[0, 1] * cs1 + R[0, 2] * cs2)
    t[1] = cd1 - (R[1, 0] * cs0 + R[1, 1] * cs1 + R[1, 2] * cs2)
    t[2] = cd2 - (R[2, 0] * cs0 + R[2, 1] * cs1 + R[2, 2] * cs2)


COV0 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@njit
def _cov_add(cov, ax, ay, az, bx, by, bz):
    """``cov + a b^T`` for a cross-covariance kept as the 9-tuple
    ``(s_xx, s_xy, s_xz, s_yx, ..., s_zz)`` (``a`` a centred source point, ``b`` its target)."""
    return (
        cov[0] + ax * bx,
        cov[1] + ax * by,
        cov[2] + ax * bz,
        cov[3] + ay * bx,
        cov[4] + ay * by,
        cov[5] + ay * bz,
        cov[6] + az * bx,
        cov[7] + az * by,
        cov[8] + az * bz,
    )


# :func:`_horn_quaternion`'s closed form is used when the adjugate's largest diagonal entry is
# at least this fraction of (2 |S|_F)^3. Below it the largest eigenvalue is too close to the
# next (nearly collinear members: the rotation about their line is barely determined) for
# Newton's root and the adjugate to keep precision, and Jacobi decides. On 100,000 random fits
# (3-8 points, planar and nearly collinear sets, noise 0-100 mm) the rotations then agree with
# Jacobi's to 1.5e-11 (1e-6 here: 3e-5; 1e-4: 2e-9).
_ADJ_MIN = 1e-3


@njit
def _det3(a, b, c, d, e, f, g, h, i):
    """Determinant of the 3x3 matrix ``[[a, b, c], [d, e, f], [g, h, i]]``."""
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


@njit
def _horn_quaternion(cov):
    """Unit quaternion ``(w, x, y, z)`` of the rotation that best maps the centred source onto
    the centred target, from their cross-covariance ``s_ab = sum src_a dst_b`` (the 9-tuple of
    :func:`_cov_add`; Horn 1987): the eigenvector of the largest eigenvalue of the symmetric,
    trace-free matrix ``N`` of :func:`_horn_jacobi`. :func:`_horn_closed` when it is well
    conditioned, else :func:`_horn_jacobi`."""
    q0, q1, q2, q3 = _horn_closed(cov)
    if q0 != q0:  # noqa: PLR0124 (NaN: ill-conditioned)
        return _horn_jacobi(cov)
    return q0, q1, q2, q3


@njit
def _horn_closed(cov):
    """:func:`_horn_quaternion` in closed form; NaNs when that is ill-conditioned.

    Closed form (the QCP route of Theobald 2005, ours in detail): ``lambda_max`` is the largest
    root of ``det(N - l I) = l^4 + c2 l^2 + c1 l + c0`` (``c2 = -2 |S|_F^2``,
    ``c1 = -8 det S``, ``c0 = det N``), found by Newton's method from ``2 |S|_F >= |N|_2``: above
    the largest root of a polynomial with real roots every derivative is positive, so the
    iterates fall monotonically onto it. The eigenvector is then any column of the adjugate of
    ``N - lambda_max I`` (rank one, ``prod(gaps) v v^T``): the column of its largest diagonal
    entry. A fifth of the time of the Jacobi sweeps; the same rotation to ~1e-11 (tests).
    """
    # scaled by a power of two (exact: the same quaternion to the bit) so that the largest
    # entry is in [0.5, 1): the cofactors grow as the cube of the scale and their norm as its
    # sixth power, which overflowed to a zero rotation at a 1e25 mm spread and underflowed
    # to a division by zero at 1e-27 mm (a review); two steps reach subnormal inputs too
    m = 0.0
    for v in cov:
        m = max(m, abs(v))
    if not (m > 0.0 and m < np.inf):  # (NaN too)
        return np.nan, np.nan, np.nan, np.nan
    e = math.frexp(m)[1]
    h = e // 2
    s1 = math.ldexp(1.0, -h)
    s2 = math.ldexp(1.0, h - e)
    sxx, sxy, sxz, syx, syy, syz, szx, szy, szz = cov
    sxx, sxy, sxz = sxx * s1 * s2, sxy * s1 * s2, sxz * s1 * s2
    syx, syy, syz = syx * s1 * s2, syy * s1 * s2, syz * s1 * s2
    szx, szy, szz = szx * s1 * s2, szy * s1 * s2, szz * s1 * s2
    n00 = sxx + syy + szz
    n01 = syz - szy
    n02 = szx - sxz
    n03 = sxy - syx
    n11 = sxx - syy - szz
    n12 = sxy + syx
    n13 = szx + sxz
    n22 = -sxx + syy - szz
    n23 = syz + szy
    n33 = -sxx - syy + szz
    f2 = sxx * sxx + sxy * sxy + sxz * sxz + syx * syx + syy * syy
    f2 += syz * syz + szx * szx + szy * szy + szz * szz
    if not f2 > 0.0:  # (NaN too)
        return np.nan, np.nan, np.nan, np.nan
    c2 = -2.0 * f2
    c1 = -8.0 * _det3(sxx, sxy, sxz, syx, syy, syz, szx, szy, szz)
    c0 = (
        n00 * _det3(n11, n12, n13, n12, n22, n23, n13, n23, n33)
        - n01 * _det3(n01, n12, n13, n02, n22, n23, n03, n23, n33)
        + n02 * _det3(n01, n11, n13, n02, n12, n23, n03, n13, n33)
        - n03 * _det3(n01, n11, n12, n02, n12, n22, n03, n13, n23)
    )
    top = 2.0 * np.sqrt(f2)
    lam = top
    for _it in range(60):
        l2 = lam * lam
        p = (l2 + c2) * l2 + c1 * lam + c0
        dp = 4.0 * l2 * lam + 2.0 * c2 * lam + c1
        if not dp > 0.0:
            break
        step = p / dp
        lam -= step
        if abs(step) <= 1e-15 * top:
            break
    # M = N - lam I; the diagonal of its adjugate, then the column of the largest entry
    m00, m11, m22, m33 = n00 - lam, n11 - lam, n22 - lam, n33 - lam
    a0 = _det3(m11, n12, n13, n12, m22, n23, n13, n23, m33)
    a1 = _det3(m00, n02, n03, n02, m22, n23, n03, n23, m33)
    a2 = _det3(m00, n01, n03, n01, m11, n13, n03, n13, m33)
    a3 = _det3(m00, n01, n02, n01, m11, n12, n02, n12, m22)
    best = a0
    j = 0
    for k, a in ((1, a1), (2, a2), (3, a3)):
        if abs(a) > abs(best):
            best = a
            j = k
    if not abs(best) >= _ADJ_MIN * top * top * top:
        return np.nan, np.nan, np.nan, np.nan
    # column j of adj(M): entry i is the cofactor C_ji = (-1)^(i+j) det(M without row j, col i)
    # (M symmetric: the same as C_ij)
    if j == 0:
        q0 = a0
        q1 = -_det3(n01, n12, n13, n02, m22, n23, n03, n23, m33)
        q2 = _det3(n01, m11, n13, n02, n12, n23, n03, n13, m33)
        q3 = -_det3(n01, m11, n12, n02, n12, m22, n03, n13, n23)
    elif j == 1:
        q0 = -_det3(n01, n02, n03, n12, m22, n23, n13, n23, m33)
        q1 = a1
        q2 = -_det3(m00, n01, n03, n02, n12, n23, n03, n13, m33)
        q3 = _det3(m00, n01, n02, n02, n12, m22, n03, n13, n23)
    elif j == 2:
        q0 = _det3(n01, n02, n03, m11, n12, n13, n13, n23, m33)
        q1 = -_det3(m00, n02, n03, n01, n12, n13, n03, n23, m33)
        q2 = a2
        q3 = -_det3(m00, n01, n02, n01, m11, n12, n03, n13, n23)
    else:
        q0 = -_det3(n01, n02, n03, m11, n12, n13, n12, m22, n23)
        q1 = _det3(m00, n02, n03, n01, n12, n13, n02, m22, n23)
        q2 = -_det3(m00, n01, n03, n01, m11, n13, n02, n12, n23)
        q3 = a3
    norm = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    if not (norm > 0.0 and norm < np.inf):
        return np.nan, np.nan, np.nan, np.nan
    return q0 / norm, q1 / norm, q2 / norm, q3 / norm


@njit
def _horn_jacobi(cov):
    """:func:`_horn_quaternion` by cyclic Jacobi rotations of the symmetric matrix ``N`` below:
    the eigenvector of its largest eigenvalue (the closed form's fallback)."""
    sxx, sxy, sxz, syx, syy, syz, szx, szy, szz = cov
    a = np.empty((4, 4))
    a[0, 0] = sxx + syy + szz
    a[0, 1] = a[1, 0] = syz - szy
    a[0, 2] = a[2, 0] = szx - sxz
    a[0, 3] = a[3, 0] = sxy - syx
    a[1, 1] = sxx - syy - szz
    a[1, 2] = a[2, 1] = sxy + syx
    a[1, 3] = a[3, 1] = szx + sxz
    a[2, 2] = -sxx + syy - szz
    a[2, 3] = a[3, 2] = syz + szy
    a[3, 3] = -sxx - syy + szz
    v = np.zeros((4, 4))
    for i in range(4):
        v[i, i] = 1.0
    scale = 0.0
    for i in range(4):
        for j in range(4):
            scale += a[i, j] * a[i, j]
    tiny = 1e-30 * scale
    for _sweep in range(50):
        off = 0.0
        for p in range(3):
            for q in range(p + 1, 4):
                off += a[p, q] * a[p, q]
        if off <= tiny:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                # the rotation that zeroes a[p, q] (Numerical Recipes' stable form)
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                tt = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    tt = -tt
                c = 1.0 / np.sqrt(tt * tt + 1.0)
                sn = tt * c
                for k in range(4):
                    akp = a[k, p]
                    akq = a[k, q]
                    a[k, p] = c * akp - sn * akq
                    a[k, q] = sn * akp + c * akq
                for k in range(4):
                    apk = a[p, k]
                    aqk = a[q, k]
                    a[p, k] = c * apk - sn * aqk
                    a[q, k] = sn * apk + c * aqk
                for k in range(4):
                    vkp = v[k, p]
                    vkq = v[k, q]
                    v[k, p] = c * vkp - sn * vkq
                    v[k, q] = sn * vkp + c * vkq
    best = 0
    for i in range(1, 4):
        if a[i, i] > a[best, best]:
            best = i
    q0 = v[0, best]
    q1 = v[1, best]
    q2 = v[2, best]
    q3 = v[3, best]
    norm = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    return q0 / norm, q1 / norm, q2 / norm, q3 / norm


@njit
def _aligned_mean(frames, ref, out):
    """Mean of ``frames (F, n, 3)``, each moved onto ``ref (n, 3)`` by its Kabsch fit, into
    ``out (n, 3)`` (a body's reference shape from its complete training frames)."""
    n = ref.shape[0]
    R = np.empty((3, 3))
    t = np.empty(3)
    out[:] = 0.0
    for f in range(frames.shape[0]):
        src = frames[f]
        _kabsch(src, ref, n, R, t)
        for i in range(n):
            for a in range(3):
                out[i, a] += R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a]
    if frames.shape[0] > 0:
        for i in range(n):
            for a in range(3):
                out[i, a] /= frames.shape[0]


@njit
def _robust_kabsch(src, dst, n, R, t, tau):
    """Kabsch fit that drops the worst-fitting member and refits while its residual exceeds
    ``tau`` mm and more than 3 members remain (a marker's neighbourhood may span a joint that
    has moved since the snapshot). Returns the members kept (compacted to the front)."""
    while True:
        _kabsch(src, dst, n, R, t)
        if n <= 3:
            return n
        worst = -1.0
        wi = -1
        for i in range(n):
            e2 = 0.0
            for a in range(3):
                d = R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a]
                d -= dst[i, a]
                e2 += d * d
            if e2 > worst:
                worst = e2
                wi = i
        if worst <= tau * tau:
            return n
        n -= 1
        for a in range(3):
            src[wi, a] = src[n, a]
            dst[wi, a] = dst[n, a]


@njit
def _gather(m, recovery, obs, src, dst):
    """Pairs (reference, observed) of ``m``'s recovery-set members seen this frame into
    ``src``/``dst``; returns how many (``recovery``: :class:`.state.Recovery`, the recovery
    sets of the module docstring)."""
    rec_members, rec_size, rec_ref = recovery.members, recovery.size, recovery.ref
    c = 0
    for k in range(1, rec_size[m]):
        mk = rec_members[m, k]
        # observed (not NaN) and in the snapshot (a partial one leaves a member NaN)
        if obs[mk, 0] == obs[mk, 0] and rec_ref[m, k, 0] == rec_ref[m, k, 0]:
            for a in range(3):
                src[c, a] = rec_ref[m, k, a]
                dst[c, a] = obs[mk, a]
            c += 1
    return c


@njit
def _place(m, rec_ref, R, t, out):
    """``out = R @ rec_ref[m, 0] + t``: marker ``m``'s reference position moved by the fit."""
    for a in range(3):
        out[a] = (
            R[a, 0] * rec_ref[m, 0, 0]
            + R[a, 1] * rec_ref[m, 0, 1]
            + R[a, 2] * rec_ref[m, 0, 2]
            + t[a]
        )


@njit
def _recover(missing, recovery, obs, method, rec, has_rec, kab, tau):
    """Recovers every marker with ``missing[m]`` into ``rec (M, 3)``.

    ``has_rec[m]`` receives how many neighbours were used (0 = not recovered). The recovery set
    of ``m`` is ``recovery.members[m, 1:size[m]]`` (``members[m, 0]`` is ``m``);
    ``recovery.ref[m]`` holds the set's positions the last time all were observed; ``obs (M, 3)``
    this frame's observed positions (NaN otherwise). ``method`` ``KABSCH`` (3+ observed), else
    (or with fewer) displacement averaging (``DISPLACEMENT``, :mod:`.params`). ``kab``:
    :class:`.state.KabschScratch`; ``tau``: ``robust_fit_mm``.
    """
    rec_ref, rec_ok = recovery.ref, recovery.ok
    src, dst, R, t = kab.src, kab.dst, kab.R, kab.t
    m_total = missing.shape[0]
    for m in range(m_total):
        has_rec[m] = 0
        if not missing[m] or not rec_ok[m]:
            continue
        c = _gather(m, recovery, obs, src, dst)
        if c == 0:
            continue
        if method == KABSCH and c >= 3:
            _robust_kabsch(src, dst, c, R, t, tau)
            _place(m, rec_ref, R, t, rec[m])
        else:
            for a in range(3):
                acc = 0.0
                for i in range(c):
                    acc += dst[i, a] + rec_ref[m, 0, a] - src[i, a]
                rec[m, a] = acc / c
        has_rec[m] = c


@njit
def _snapshot(age, min_age, obs, recovery):
    """Stores the recovery-set positions of every marker whose whole set is observed and has
    been for at least ``min_age`` frames in a row (``age``): a fresh, possibly wrong, assignment
    never becomes the reference that later checks it.

    While no full snapshot can be taken (a member hidden for good: a marker behind a partner,
    a heel the cameras lose), the marker and at least 3 members observed that long give a
    *partial* one: the other members' rows are NaN, and every fit skips them (:func:`_gather`).
    A partial snapshot is refreshed while it stays partial; a full one replaces it and is never
    replaced by a partial one.
    """
    rec_members, rec_size = recovery.members, recovery.size
    rec_ref, rec_ok = recovery.ref, recovery.ok
    need = max(min_age, 1)  # frames observed in a row (and observed now)
    for m in range(age.shape[0]):
        n = rec_size[m]
        if n == 0:
            continue
        seen = 0
        for k in range(n):
            if age[rec_members[m, k]] >= need:
                seen += 1
        if seen == n or (
            seen >= 4  # the marker itself and 3+ members: a Kabsch fit
            and age[m] >= need
            and not _full(m, n, rec_ref, rec_ok)
        ):
            for k in range(n):
                mk = rec_members[m, k]
                for a in range(3):
                    rec_ref[m, k, a] = obs[mk, a] if age[mk] >= need else np.nan
            rec_ok[m] = True


@njit(inline="always")
def _full(m, n, rec_ref, rec_ok):
    """``rec_ref[m]`` holds a full snapshot (none of its ``n`` rows NaN)."""
    full = rec_ok[m]
    k = 0
    while full and k < n:
        full = rec_ref[m, k, 0] == rec_ref[m, k, 0]  # noqa: PLR0124 (NaN: a partial snapshot)
        k += 1
    return full


@njit
def _set_estimate(m, recovery, obs, kab, out, tau):
    """Kabsch estimate of marker ``m`` from its observed recovery-set members (3+ needed);
    returns the number of members the robust fit kept (0 when fewer than 3 were observed)."""
    src, dst, R, t = kab.src, kab.dst, kab.R, kab.t
    c = _gather(m, recovery, obs, src, dst)
    if c < 3:
        return 0
    c = _robust_kabsch(src, dst, c, R, t, tau)
    _place(m, recovery.ref, R, t, out)
    return c


@njit
def _verify(points, index, frame_no, tracks, recovery, scratch, params):
    """3D check of the fit against each marker's rigid neighbourhood (after Algorithm 1).

    Eq. 5 only sees distances, so a ghost, or another person's marker at the place of a hidden
    one, can fit a body's links as well as the true point. For every marker that is suspect -
    several candidates, not observed in the previous frame (``prev_state != 1``), a point more
    than ``jump_mm`` from the Kalman prediction ``x``, a free point within ``suspect_mm`` of its
    prediction (a reappearing marker whose label another point has taken), its turn in a round
    robin over ``verify_every`` frames, or missing - the Kabsch estimate from its observed
    recovery set (3+ neighbours, ``robust_fit_mm``) is computed:

    - an observed marker whose point is more than ``verify_mm`` from the estimate moves to a
      free point at most half as far; with ``swap_check``, if another marker holds that point
      and the exchange halves the two markers' summed distances to their estimates, the two
      swap (persistent swaps between performers in contact); failing that, a marker that was
      not observed in the
      previous frame drops a point farther than ``reject_mm`` from an estimate that at least 4
      mutually consistent neighbours support (it stays missing), at most ``reject_limit``
      frames in a row (``n_reject`` counts them): real bodies are not perfectly rigid, and a
      marker that really moved on its body must not be locked out;
    - a missing marker takes the nearest free point within ``reacquire_near_mm`` of the
      estimate (re-acquisition predicted from the rigid body, not from a stale Kalman state).

    Reads and changes ``scratch.assigned``, ``owner`` and keeps ``scratch.obs`` in sync;
    ``tracks.state`` is the previous frame's, ``tracks.n_reject`` is updated;
    ``scratch.missing`` is its scratch flag "suspect". ``index``: the sweep index of
    ``points``; ``frame_no`` drives the round robin. Returns the number of changes.
    """
    assigned, owner, ncand, obs = scratch.assigned, scratch.owner, scratch.ncand, scratch.obs
    suspect, kab = scratch.missing, scratch.kab
    active, prev_state, x, n_reject = tracks.active, tracks.state, tracks.x, tracks.n_reject
    verify_mm, reacquire_mm = params.verify_mm, params.reacquire_near_mm
    reject_mm, jump_mm, suspect_mm = params.reject_mm, params.jump_mm, params.suspect_mm
    tau, reject_limit = params.robust_fit_mm, params.reject_limit
    verify_every, swap_check = params.verify_every, params.swap_check
    n = points.shape[0]
    est = np.empty(3)
    est2 = np.empty(3)
    rec_ok = recovery.ok
    changes = 0
    m_total = assigned.shape[0]
    s2 = suspect_mm * suspect_mm
    for m in range(m_total):
        suspect[m] = False
    for j in range(n):
        if owner[j] >= 0:
            continue
        for m in range(m_total):
            if assigned[m] < 0 or suspect[m]:
                continue
            d2 = 0.0
            for c in range(3):
                d = points[j, c] - x[m, c]
                d2 += d * d
            suspect[m] = d2 < s2
    for m in range(m_total):
        if not active[m] or not rec_ok[m]:
            continue
        a = assigned[m]
        fresh = prev_state[m] != OBSERVED
        jumped = False
        if a >= 0 and not fresh:
            i2 = 0.0
            for c in range(3):
                d = points[a, c] - x[m, c]
                i2 += d * d
            jumped = i2 > jump_mm * jump_mm  # far from the Kalman prediction
        turn = verify_every > 0 and (m + frame_no) % verify_every == 0  # round robin
        if a >= 0 and ncand[m] < 2 and not fresh and not jumped and not suspect[m] and not turn:
            continue
        kept = _set_estimate(m, recovery, obs, kab, est, tau)
        if kept == 0:
            continue
        e2 = 0.0
        if a >= 0:
            for c in range(3):
                d = points[a, c] - est[c]
                e2 += d * d
            if e2 <= verify_mm * verify_mm:
                continue
            lim = 0.25 * e2  # half the distance
        else:
            lim = reacquire_mm * reacquire_mm
        bj, best = _nearest(points, index, est, lim, owner, FREE, -1)
        if bj < 0 and a >= 0 and swap_check:
            # the point the estimate wants may be held by another marker: swap when both fit
            # their rigid neighbourhoods better after the exchange
            bk, best = _nearest(points, index, est, 0.25 * e2, owner, OWNED, a)
            if bk >= 0:
                m2 = owner[bk]
                if rec_ok[m2]:
                    k2 = _set_estimate(m2, recovery, obs, kab, est2, tau)
                    if k2 > 0:
                        now2 = 0.0
                        sw2 = 0.0
                        for c in range(3):
                            d = points[bk, c] - est2[c]
                            now2 += d * d
                            d = points[a, c] - est2[c]
                            sw2 += d * d
                        if np.sqrt(best) + np.sqrt(sw2) < 0.5 * (np.sqrt(e2) + np.sqrt(now2)):
                            owner[a] = m2
                            owner[bk] = m
                            assigned[m] = bk
                            assigned[m2] = a
                            for c in range(3):
                                obs[m, c] = points[bk, c]
                                obs[m2, c] = points[a, c]
                            changes += 1
                            continue
        if bj < 0:
            if (
                a >= 0
                and fresh
                and kept >= 4
                and n_reject[m] < reject_limit
                and e2 > reject_mm * reject_mm
            ):
                n_reject[m] += 1
                owner[a] = NONE
                assigned[m] = NONE
                for c in range(3):
                    obs[m, c] = np.nan
                changes += 1
            continue
        _take(m, bj, points, assigned, owner, obs)
        changes += 1
    return changes


@njit(inline="always")
def _take(m, j, points, assigned, owner, obs):
    """Marker ``m`` takes point ``j`` (its former point, if any, is free); ``obs`` follows."""
    a = assigned[m]
    if a >= 0:
        owner[a] = NONE
    owner[j] = m
    assigned[m] = j
    for c in range(3):
        obs[m, c] = points[j, c]


@njit
def _estimate_distance(m, a, points, recovery, obs, kab, est, tau):
    """Distance (mm) from point ``a`` to the Kabsch estimate of marker ``m`` (Sec. 3.3 with
    3+ observed neighbours); ``inf`` when there is no estimate."""
    if not recovery.ok[m]:
        return np.inf
    if _set_estimate(m, recovery, obs, kab, est, tau) == 0:
        return np.inf
    e2 = 0.0
    for c in range(3):
        d = points[a, c] - est[c]
        e2 += d * d
    return np.sqrt(e2)


CONTEST_PASSES = 3  # a marker that lost its point in one pass may take back its own in the next


@njit
def _contest(points, tracks, recovery, scratch, params):
    """Track continuity after Algorithm 1: a point goes back to the marker that was tracked onto
    it when the fit gave it to a marker that had to jump for it.

    Eq. 5 only sees distances, and in close contact another person's marker sits where a hidden
    one would be; a body that spans a joint fits its links loosely and loses the greedy order
    (Algorithm 1 line 12) to the hidden marker's body. For every point ``a`` held by a marker
    ``m`` more than ``jump_mm`` from its Kalman prediction (Eq. 3), the marker ``m2`` missing
    after the fit with the smallest squared Mahalanobis distance ``d2 / s[m2]`` to ``a``
    (``scratch.s`` the innovation variance of the gate), if that is below ``gate_chi2`` and a
    quarter of ``m``'s, takes the point (``m`` is missing); a marker observed in the previous
    frame (``tracks.state == OBSERVED``) must moreover predict ``a`` within ``jump_mm``. A rigid
    neighbourhood can veto: ``m`` keeps the point when its Kabsch estimate (3+ observed
    neighbours) lies within ``verify_mm`` of it, and ``m2`` does not take it when its own
    estimate is farther from the point than ``m``'s. The markers are taken in index order, and
    again (up to :data:`CONTEST_PASSES` passes) while a pass hands something over: a marker that
    lost a point it jumped for may be the one to take back the point another jumped for.

    Changes ``scratch.assigned``, ``owner``; ``scratch.obs (M, 3)`` holds the observed
    positions (NaN otherwise) and is kept in sync. Returns the number of points handed over.
    """
    assigned, owner, obs = scratch.assigned, scratch.owner, scratch.obs
    s, kab = scratch.s, scratch.kab
    active, prev_state, x = tracks.active, tracks.state, tracks.x
    gate, jump_mm, verify_mm = params.gate_chi2, params.jump_mm, params.verify_mm
    tau = params.robust_fit_mm
    m_total = assigned.shape[0]
    est = np.empty(3)
    changes = 0
    for _pass in range(CONTEST_PASSES):
        before = changes
        for m in range(m_total):
            a = assigned[m]
            if a < 0:
                continue
            i2 = 0.0
            for c in range(3):
                d = points[a, c] - x[m, c]
                i2 += d * d
            if i2 <= jump_mm * jump_mm:
                continue
            # takers compete on the Mahalanobis distance (Sec. 3.1): at most a quarter of the
            # holder's and inside the gate
            lim = min(gate, 0.25 * i2 / s[m])
            bm = -1
            for m2 in range(m_total):
                if assigned[m2] >= 0 or not active[m2]:
                    continue
                d2 = 0.0
                for c in range(3):
                    d = points[a, c] - x[m2, c]
                    d2 += d * d
                if prev_state[m2] == OBSERVED and d2 >= jump_mm * jump_mm:
                    continue  # a tracked marker takes back only a point it predicts sharply
                if d2 / s[m2] < lim:
                    lim = d2 / s[m2]
                    bm = m2
            if bm < 0:
                continue
            e_m = _estimate_distance(m, a, points, recovery, obs, kab, est, tau)
            if e_m <= verify_mm:
                continue
            e_bm = _estimate_distance(bm, a, points, recovery, obs, kab, est, tau)
            if np.isfinite(e_bm) and e_bm > e_m:
                continue
            owner[a] = bm
            assigned[bm] = a
            assigned[m] = NONE
            for c in range(3):
                obs[bm, c] = points[a, c]
                obs[m, c] = np.nan
            changes += 1
        if changes == before:
            break
    return changes


@njit
def _shape_allows(m, q, partner, points, bodies, assigned, a_floor, a_rel, miss_term):
    """True when marker ``m`` on point ``q`` fits every link of its bodies to an assigned
    co-member (``partner``, whose point changes too, left out) no worse than Eq. 5's missing
    marker: the body's shape does not refute the reading (:func:`_exchange`)."""
    members, size, D, A = bodies.members, bodies.size, bodies.D, bodies.A
    for e in range(bodies.mb_ptr[m], bodies.mb_ptr[m + 1]):
        b = bodies.mb_idx[e]
        pi = -1
        for k in range(size[b]):
            if members[b, k] == m:
                pi = k
        for k in range(size[b]):
            o = members[b, k]
            if o == m or o == partner or assigned[o] < 0:  # noqa: SIM109 (numba: no mixed-int tuple)
                continue
            t = _pair_term(D[b], A[b], pi, k, a_floor, a_rel, miss_term, points, q, assigned[o])
            if t < miss_term:
                return False
    return True


@njit
def _exchange(points, tracks, bodies, scratch, params):
    """Track continuity between two tracked markers that hold each other's points (ours).

    A body whose shape is nearly symmetric (a pelvis triangle with its third marker near the
    midline: exchanging ``RASI`` and ``LASI`` is a proper rotation) cannot tell two readings
    apart by Eq. 5 or the 3D check, and a prediction a few deviations off leaves the motion
    term no weight: at 25 Hz such a pair was exchanged for 20 frames while each point lay
    40 mm from its own marker's prediction and 240 mm from the other's. For every marker ``m``
    observed in the previous frame whose point lies more than ``jump_mm`` from its prediction,
    and every co-member ``m2`` (a marker sharing a body with it) also observed then: the two
    exchange their points when that brings their summed distances to their predictions below
    ``exchange_ratio`` (a quarter) of the current ones and the exchanged reading fits each one's
    body links no worse than a missing marker would (shape does not refute it). Changes
    ``scratch.assigned`` and ``owner``; returns the exchanges."""
    assigned, owner = scratch.assigned, scratch.owner
    active, prev_state, x = tracks.active, tracks.state, tracks.x
    jump2 = params.jump_mm * params.jump_mm
    a_floor, a_rel, miss_term = params.a_floor_mm, params.a_relative, params.miss_term
    members, size = bodies.members, bodies.size
    changes = 0
    for m in range(assigned.shape[0]):
        a = assigned[m]
        if a < 0 or not active[m] or prev_state[m] != OBSERVED:
            continue
        e11 = 0.0
        for c in range(3):
            d = points[a, c] - x[m, c]
            e11 += d * d
        if e11 <= jump2:
            continue
        e11 = np.sqrt(e11)
        for e in range(bodies.mb_ptr[m], bodies.mb_ptr[m + 1]):
            b = bodies.mb_idx[e]
            done = False
            for k in range(size[b]):
                m2 = members[b, k]
                a2 = assigned[m2]
                if m2 == m or a2 < 0 or prev_state[m2] != OBSERVED:
                    continue
                e22 = e12 = e21 = 0.0
                for c in range(3):
                    d = points[a2, c] - x[m2, c]
                    e22 += d * d
                    d = points[a2, c] - x[m, c]
                    e12 += d * d
                    d = points[a, c] - x[m2, c]
                    e21 += d * d
                # (written so that a NaN prediction never exchanges)
                if not np.sqrt(e12) + np.sqrt(e21) < params.exchange_ratio * (e11 + np.sqrt(e22)):
                    continue
                if not _shape_allows(m, a2, m2, points, bodies, assigned, a_floor, a_rel,
                                     miss_term):  # fmt: skip
                    continue
                if not _shape_allows(m2, a, m, points, bodies, assigned, a_floor, a_rel,
                                     miss_term):  # fmt: skip
                    continue
                assigned[m], assigned[m2] = a2, a
                owner[a], owner[a2] = m2, m
                changes += 1
                done = True
                break
            if done:
                break
    return changes


@njit
def _max_residual(src, dst, n, R, t):
    """Largest distance (mm) between ``R @ src_i + t`` and ``dst_i`` over the first ``n`` rows:
    how far the neighbours kept by a Kabsch estimate (Sec. 3.3) are from one rigid motion."""
    worst = 0.0
    for i in range(n):
        e2 = 0.0
        for a in range(3):
            d = R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a] - dst[i, a]
            e2 += d * d
        if e2 > worst:
            worst = e2
    return np.sqrt(worst)


@njit
def _keep_tracks(points, index, dt, tracks, recovery, scratch, params):
    """Track continuity against untracked takers (ours, docs/algorithm.md).

    A marker ``m`` tracked in the previous frame continues its track onto point ``j`` when
    ``j`` is the point nearest ``m``'s last point moved by its velocity (the continuation
    ``c``), within ``jump_mm`` of it, and no other point lies within twice ``m``'s predicted
    deviation (``sqrt(scratch.s[m])``, at least ``jump_mm``) of ``c``: a loose track (a low
    rate, a fast limb) needs a wider berth. When the steps before gave ``j`` to a marker that
    was not tracked in the previous frame, or tracked for fewer frames than ``m`` and than
    ``snapshot_age``, or to nobody, ``m`` takes it: the other marker is missing, ``m``'s other
    point (a ghost the shifted prediction fell on) is freed. A coasting state, a prediction the
    common-mode shift moved (a walker leaving the volume, most of his markers coasting), a
    track begun on a ghost two frames ago are no evidence against a continuing track; two
    established tracks are the contest's and the exchange's. A rigid neighbourhood vetoes as in
    the contest: the holder keeps the point when its Kabsch estimate (3+ observed neighbours)
    lies within ``verify_mm`` of it and ``m``'s does not lie nearer (a marker back from an
    occlusion beside its body, the tracked one on its point since a contact). Changes
    ``scratch.assigned``, ``owner``, ``obs``; returns the points handed over."""
    assigned, owner, obs = scratch.assigned, scratch.owner, scratch.obs
    prev_state, pos, x, active = tracks.state, tracks.pos, tracks.x, tracks.active
    age, snapshot_age = tracks.age, params.snapshot_age
    near = params.jump_mm
    kab, tau, verify_mm = scratch.kab, params.robust_fit_mm, params.verify_mm
    c = np.empty(3)
    est = np.empty(3)
    synced = False  # obs follows assigned (the steps before changed it)
    changes = 0
    for m in range(assigned.shape[0]):
        if not active[m] or prev_state[m] != OBSERVED or pos[m, 0] != pos[m, 0]:  # noqa: PLR0124
            continue
        for k in range(3):
            c[k] = pos[m, k] + x[m, 3 + k] * dt
        j, _ = _nearest(points, index, c, near * near, owner, ANY, -1)
        if j < 0 or assigned[m] == j:
            continue
        h = owner[j]
        if h >= 0 and prev_state[h] == OBSERVED and age[h] >= min(snapshot_age, age[m]):
            continue  # a rival tracked as long (the contest's, the exchange's)
        # alone within twice the track's predicted deviation (at least jump_mm)
        iso = 2.0 * max(near, np.sqrt(scratch.s[m]))
        if not _alone(points, index, c, iso, j):
            continue
        if h >= 0:
            if not synced:
                for i in range(assigned.shape[0]):
                    a = assigned[i]
                    for k in range(3):
                        obs[i, k] = points[a, k] if a >= 0 else np.nan
                synced = True
            e_h = _estimate_distance(h, j, points, recovery, obs, kab, est, tau)
            if e_h <= verify_mm and not (
                _estimate_distance(m, j, points, recovery, obs, kab, est, tau) < e_h
            ):
                continue  # the holder's body places it there
            assigned[h] = NONE
            for k in range(3):
                obs[h, k] = np.nan
        _take(m, j, points, assigned, owner, obs)
        changes += 1
    return changes
