"""Training subject templates from labeled frames (seed 003 Sec. 3.1).

Used twice: by :class:`~labeler_service.labeling.labeler.Labeler` on its training window and by the
offline trainer (``mocap-labeler train structure``).

Structure model (Eq. 1-2): ``D[i, j]`` is the mean and ``A[i, j]`` the standard deviation of the
distance between markers ``i`` and ``j`` over the frames where both are visible (missing samples
are skipped; a pair seen fewer than ``min_pair_frames`` times stays unknown, NaN).

Rigid bodies (our rule; the paper only says "groups with small group-internal deviation, 3-8
markers"): the cost of a pair is ``c[i, j] = A[i, j] + distance_weight * D[i, j]``, i.e. its
distance deviation plus a small preference for close markers (markers on one segment are
close; during a quiet training window far pairs can look rigid by accident). Seeds are the
markers in increasing order of their own rigidity (mean of their two lowest costs). Starting
from each seed not yet covered by a body, we greedily add the marker whose *largest* cost to the
current members is smallest, while that largest cost is at most ``tolerance_mm`` and the body has
fewer than ``max_size`` markers. A body that ends with fewer than ``min_size`` markers is
completed with the lowest-cost markers regardless of the tolerance (the fit then simply allows
the larger ``A`` of those pairs). Every usable marker is therefore in at least one body; bodies
may share markers, which links them during fitting. Duplicate bodies are dropped.

Reference shape of a body: the frames where the whole body is visible are aligned (Kabsch) to
the first such frame and averaged, then expressed in the body frame (centroid origin, principal
axes). When the body is never fully visible, classical multidimensional scaling of ``D``
gives the shape.

Motion noise (Eq. 3, ``Q``): per marker the mean squared second difference of its positions,
scaled to an acceleration variance per axis ``(mm/s^2)^2``; it includes the measurement noise
at that rate, which is what the gate must tolerate. Markers with too few samples take the
subject median.
"""

from __future__ import annotations

import numpy as np

from labeler_service.errors import LabelerError
from labeler_service.labeling.templates import (
    LABELS_OFF_MM,
    MOTION_NOISE_RANGE,
    PAIR_DISTANCE_MM,
    SubjectTemplate,
    body_link_spread,
    make_subject,
)


def pair_statistics(pos: np.ndarray, min_pair_frames: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 1-2 over all frames: ``D`` (mean distance) and ``A`` (its deviation), NaN-robust.

    ``pos`` is ``(F, M, 3)`` with NaN for missing samples. Returns ``(M, M)`` float64 arrays,
    NaN where a pair was seen together fewer than ``min_pair_frames`` times.
    """
    p = np.asarray(pos, dtype=np.float64)
    f, m, _ = p.shape
    s1 = np.zeros((m, m))
    s2 = np.zeros((m, m))
    n = np.zeros((m, m))
    for k in range(f):
        d = np.sqrt(((p[k, :, None, :] - p[k, None, :, :]) ** 2).sum(-1))
        ok = np.isfinite(d)
        d = np.where(ok, d, 0.0)
        s1 += d
        s2 += d * d
        n += ok
    return stats_from_sums(s1, s2, n, min_pair_frames)


def stats_from_sums(
    s1: np.ndarray, s2: np.ndarray, n: np.ndarray, min_count: int
) -> tuple[np.ndarray, np.ndarray]:
    """``D``, ``A`` (Eq. 1-2) of square matrices of sums of the distance ``s1``, of its square
    ``s2`` and of sample counts ``n``; NaN where a pair has fewer than ``min_count`` samples,
    0 on the diagonal."""
    with np.errstate(invalid="ignore", divide="ignore"):
        D = s1 / n
        A = np.sqrt(np.maximum(s2 / n - D * D, 0.0))
    bad = n < max(1, min_count)
    D[bad] = np.nan
    A[bad] = np.nan
    np.fill_diagonal(D, 0.0)
    np.fill_diagonal(A, 0.0)
    return D, A


def model_pair_statistics(
    pos: np.ndarray, min_pair_frames: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pair_statistics` as a subject template stores them, within the ranges every model
    must keep (``templates.PAIR_DISTANCE_MM``, ``A < D``): a pair whose mean distance is outside
    them (one point recorded under two names; a glitch) is unknown (NaN), and a pair whose
    distance varied as much as its mean (a few samples of a fast limb: a 5-frame window at
    12.5 Hz) keeps a deviation just below its distance - either way it is not rigid. Without
    this a trained model could fail its own validation."""
    return within_model_ranges(*pair_statistics(pos, min_pair_frames))


def within_model_ranges(D: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``D``, ``A`` (changed in place) within the ranges every model must keep (see
    :func:`model_pair_statistics`)."""
    lo, hi = PAIR_DISTANCE_MM
    off = np.isfinite(D) & (np.clip(D, lo, hi) != D)
    np.fill_diagonal(off, False)
    D[off] = np.nan
    A[off] = np.nan
    wide = np.isfinite(A) & (A >= D) & (D > 0)
    A[wide] = 0.999 * D[wide]
    return D, A


def select_bodies(
    D: np.ndarray,
    A: np.ndarray,
    usable: np.ndarray,
    *,
    tolerance_mm: float = 6.0,
    distance_weight: float = 0.02,
    min_size: int = 3,
    max_size: int = 6,
    all_seeds: bool = False,
) -> list[list[int]]:
    """Rigid bodies by low distance deviation (the rule in the module docstring).

    With ``all_seeds`` every marker seeds a body (not only those no body covers yet); bodies
    contained in another are then dropped.
    """
    if not 1 <= min_size <= max_size <= 8:
        raise LabelerError(
            f"body sizes must satisfy 1 <= min <= max <= 8, got {min_size}, {max_size}"
        )
    idx = np.flatnonzero(usable)
    if idx.size == 0:
        return []
    cost = A + distance_weight * D
    cost = np.where(np.isfinite(cost), cost, np.inf)
    sub = cost[np.ix_(idx, idx)].copy()
    np.fill_diagonal(sub, np.inf)
    if idx.size <= min_size:
        return [idx.tolist()]
    two = np.sort(sub, axis=1)[:, :2]
    seed_order = np.argsort(two.mean(axis=1), kind="stable")
    covered = np.zeros(idx.size, dtype=bool)
    bodies: list[list[int]] = []
    seen: set[tuple[int, ...]] = set()
    for s in seed_order:
        if covered[s] and not all_seeds:
            continue
        members = [int(s)]
        worst = sub[s].copy()  # largest cost of each candidate to the current members
        worst[s] = np.inf
        while len(members) < max_size:
            j = int(np.argmin(worst))
            if not np.isfinite(worst[j]) or (worst[j] > tolerance_mm and len(members) >= min_size):
                break
            members.append(j)
            worst = np.maximum(worst, sub[j])
            worst[members] = np.inf
        if len(members) < min_size:  # complete with the lowest-cost markers to the seed
            for j in np.argsort(sub[s], kind="stable"):
                if len(members) >= min_size or not np.isfinite(sub[s, j]):
                    break
                if int(j) not in members:
                    members.append(int(j))
        key = tuple(sorted(members))
        covered[members] = True
        if key in seen:
            continue
        seen.add(key)
        bodies.append([int(idx[k]) for k in key])
    if all_seeds:
        sets = [set(b) for b in bodies]
        bodies = [
            b
            for i, b in enumerate(bodies)
            if not any(i != j and sets[i] < sets[j] for j in range(len(sets)))
        ]
    return bodies


def _body_frame(shape: np.ndarray) -> np.ndarray:
    c = shape - shape.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=True)
    if np.linalg.det(vt) < 0:
        vt[2] *= -1
    return c @ vt.T


def _mds(Dsub: np.ndarray) -> np.ndarray:
    n = Dsub.shape[0]
    d2 = np.nan_to_num(Dsub, nan=float(np.nanmean(Dsub)) if np.isfinite(Dsub).any() else 0.0) ** 2
    j = np.eye(n) - 1.0 / n
    b = -0.5 * j @ d2 @ j
    w, v = np.linalg.eigh(b)
    order = np.argsort(w)[::-1][:3]
    coords = v[:, order] * np.sqrt(np.maximum(w[order], 0.0))
    if coords.shape[1] < 3:
        coords = np.pad(coords, ((0, 0), (0, 3 - coords.shape[1])))
    return coords


def reference_shape(pos: np.ndarray, body: list[int], D: np.ndarray) -> np.ndarray:
    """Mean shape of one body in its body frame (Kabsch-aligned average of complete frames)."""
    sub = np.asarray(pos[:, body, :], dtype=np.float64)
    full = np.flatnonzero(np.isfinite(sub).all(axis=(1, 2)))
    if full.size == 0:
        return _body_frame(_mds(D[np.ix_(body, body)]))
    from labeler_service.labeling.geometry import aligned_mean

    return _body_frame(aligned_mean(sub[full], sub[full[0]]))


def motion_noise(pos: np.ndarray, rate: float, floor: float = 1.0e4) -> np.ndarray:
    """Per-marker acceleration variance per axis, (mm/s^2)^2, from second differences."""
    p = np.asarray(pos, dtype=np.float64)
    m = p.shape[1]
    q = np.full(m, np.nan)
    if p.shape[0] >= 3:
        a = (p[2:] - 2.0 * p[1:-1] + p[:-2]) * rate * rate
        ok = np.all(np.isfinite(a), axis=2)
        for i in range(m):
            if ok[:, i].sum() >= 2:
                q[i] = float(np.mean(a[ok[:, i], i] ** 2))
    fill = float(np.nanmedian(q)) if np.isfinite(q).any() else floor * 100.0
    q = np.where(np.isfinite(q), q, fill)
    return np.maximum(q, floor)


#: two labeled markers whose mean distance over the frames where both are seen is under this
#: are one physical marker tracked twice (a split track, e.g. ``RBAC`` and ``RBAC-1``, 4.4 mm
#: apart for 8 frames of a CMU take): the centres of two markers of 5 mm or more (body markers
#: are 9-25 mm) cannot be closer
DUPLICATE_MM = 5.0


def split_tracks(D: np.ndarray, seen: np.ndarray) -> dict[int, int]:
    """Markers that duplicate another (a split track): ``{duplicate: original}`` for every pair
    whose mean distance ``D`` is under :data:`DUPLICATE_MM`; the marker seen in fewer frames
    (``seen``, per marker) is the duplicate."""
    out: dict[int, int] = {}
    close = np.argwhere(np.triu(np.nan_to_num(D, nan=np.inf) < DUPLICATE_MM, k=1))
    close = close[close[:, 0] != close[:, 1]]
    for i, j in close:
        dup, orig = (int(j), int(i)) if seen[j] <= seen[i] else (int(i), int(j))
        out.setdefault(dup, orig)
    return out


def train_subject(
    name: str,
    markers: list[str],
    pos: np.ndarray,
    rate: float,
    *,
    tolerance_mm: float = 6.0,
    distance_weight: float = 0.02,
    min_size: int = 3,
    max_size: int = 6,
    min_pair_frames: int = 3,
    all_seeds: bool = False,
    glimpsed: bool = False,
) -> SubjectTemplate:
    """The template of one subject from its labeled frames ``pos`` ``(F, M, 3)`` (NaN missing).

    Markers visible in fewer than ``min_pair_frames`` frames, and markers that duplicate
    another (:func:`split_tracks`), get no body (they can never be labeled by the fit, but they
    do not break anything: a duplicate in a body would take its original's point). A subject
    none of whose markers is usable (not seen in the frames) raises :class:`LabelerError`.
    With ``glimpsed`` (a labeled init window: what it glimpsed is all it will ever be told)
    such a marker seen in 1 or 2 frames joins a body of its own instead (:func:`glimpse_bodies`).
    """
    pos = np.asarray(pos, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[1] != len(markers) or pos.shape[2] != 3:
        raise LabelerError(
            f"subject {name!r}: positions must be (frames, {len(markers)}, 3), got {pos.shape}"
        )
    D_raw, A_raw = pair_statistics(pos, min_pair_frames)
    D, A = within_model_ranges(D_raw.copy(), A_raw.copy())  # as model_pair_statistics
    seen = np.isfinite(pos).all(axis=2).sum(axis=0)
    usable = seen >= min_pair_frames
    # the raw mean distances: the model's leave a pair at distance 0 unknown (one point under
    # two names), which is a split track too
    usable[list(split_tracks(D_raw, seen))] = False
    bodies = select_bodies(
        D,
        A,
        usable,
        tolerance_mm=tolerance_mm,
        distance_weight=distance_weight,
        min_size=min_size,
        max_size=max_size,
        all_seeds=all_seeds,
    )
    if not bodies:
        raise LabelerError(
            f"subject {name!r}: no marker is seen in {min_pair_frames} or more of its "
            f"{pos.shape[0]} labeled training frames, so it has no rigid body to label with: "
            "give more labeled frames in which the subject is visible (more init frames, or "
            "start where the subject is in the volume)"
        )
    spread = body_link_spread(A, bodies)
    if spread > LABELS_OFF_MM:
        raise LabelerError(
            f"subject {name!r}: its labels do not stay on their markers in the labeled frames: "
            f"the distances inside its most rigid groups of markers vary by {spread:.0f} mm "
            f"(median standard deviation; a labeled take gives under 5, at most "
            f"{LABELS_OFF_MM:g} is accepted): are the training frames' labels right?"
        )
    if glimpsed:
        thin = (seen >= 1) & ~usable
        thin[list(split_tracks(D_raw, seen))] = False
        bodies += glimpse_bodies(pos, D, A, usable, thin, max_size, tolerance_mm)
    shapes = [reference_shape(pos, b, D) for b in bodies]
    q = motion_noise(pos, rate)
    worst = int(np.argmax(q))
    if q[worst] > MOTION_NOISE_RANGE[1]:  # the template would refuse it, in its own words
        raise LabelerError(
            f"subject {name!r}: its markers accelerate beyond any body in the labeled frames "
            f"({markers[worst]}: motion noise {q[worst]:.3g} (mm/s^2)^2, at most "
            f"{MOTION_NOISE_RANGE[1]:g}): is the capture's frame rate ({rate:g} Hz) right, are "
            "its units millimetres, and do its labels stay on their markers?"
        )
    return make_subject(name, markers, D, A, bodies, shapes, q)


def glimpse_bodies(
    pos: np.ndarray,
    D: np.ndarray,
    A: np.ndarray,
    usable: np.ndarray,
    thin: np.ndarray,
    size: int,
    deviation_mm: float,
) -> list[list[int]]:
    """Bodies for markers a labeled window saw in too few frames for pair statistics
    (``thin``): each with the ``size - 1`` usable markers nearest to it in the frames it was
    seen (at least three, else none: on two, a triangle hinged on them, every glimpsed marker
    of a take that showed only two usable ones took wrong points; ``train_subject`` passes
    ``max_size``: with two neighbours the BTS walker's `SCL2` took the point of `SCL1`, a
    marker his window never saw, for 216 frames of holdout07 `ghosts3`), its distances to
    them their mean there and their deviation
    ``deviation_mm`` (the body rule's tolerance: rigid, but at the edge). ``D``/``A`` are
    changed in place. Without them a marker the window glimpsed at its start or end (a BTS
    walker's scapula and bar markers, 1-2 of 40 frames) could never be labeled: no body, no
    trained distance, for the whole stream; with them the fit and the extension place it where
    its neighbours say, and the stream's own motion re-forms the body (``restructure``)."""
    out: list[list[int]] = []
    if not thin.any():
        return out
    d_once, _ = pair_statistics(pos, 1)  # (one frame together is enough here)
    for g in np.flatnonzero(thin):
        near = [int(k) for k in np.argsort(d_once[g]) if usable[k] and np.isfinite(d_once[g, k])]
        near = near[: size - 1]
        if len(near) < 3:
            continue
        for k in near:
            D[g, k] = D[k, g] = d_once[g, k]
            A[g, k] = A[k, g] = min(deviation_mm, 0.999 * d_once[g, k])
        out.append(sorted([int(g), *near]))
    within_model_ranges(D, A)
    return out
