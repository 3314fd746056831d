"""Step 3: skeleton and joint centres (Hong et al. 2009, Sec. 3.3, after [AKP*04] and [OBBH00]).

Structure: the paper's skeleton branches from the spine at the upper chest and is one chain to
the wrist. The root is the segment that rotates least in the world (median rotation angle from
the rest pose). Which segment follows which is decided kinematically: a ball joint is fitted
between every pair of segments (below) and its weighted RMS residual (mm) is the cost of
linking them. The chain is the order from the root with the smallest summed cost; the tree is
the minimum spanning tree over the same costs (the alternative the paper's Sec. 5 suggests,
[OBBH00]). With ``structure="auto"`` (default) the model builds both and keeps the tree only if
it reproduces the training surface (full marker set) more than 1 % better -- which happens when
k-means splits off a patch that is not a link of the arm (a ring of skin near the shoulder): in
a chain every bone below it would hang from that small, noisy bone. The report says which.

Joint centre: a ball joint is a point fixed in both adjacent bones. With each bone's rigid
motion ``(R_p^t, t_p^t)``, ``(R_c^t, t_c^t)`` from the rest pose, find rest-space points
``x_p, x_c`` with ``R_p^t x_p + t_p^t = R_c^t x_c + t_c^t`` for all frames: the weighted linear
least-squares problem ``[R_p^t  -R_c^t] [x_p; x_c] = t_c^t - t_p^t``. Frame weights are
iteratively reweighted (Cauchy, scale = median residual, 3 rounds) so frames where a bone fit
is poor count less. A weak ridge term ``lam (||x_p - x0||^2 + ||x_c - x0||^2)`` (``x0``: centroid
of the markers on the boundary between the two segments; ``lam = 1e-4`` per frame) fixes the
point along the axis of a joint that moves like a hinge in the data. The joint is
``(x_p + x_c) / 2``.
"""

from __future__ import annotations

from itertools import permutations

import numpy as np

from labeler_service.labeling.geometry import rotation_angle


def choose_root(R: np.ndarray) -> int:
    """Segment whose world rotation from the rest pose has the smallest median angle."""
    ang = rotation_angle(R)  # (F, S)
    med = np.array([np.nanmedian(a) if np.isfinite(a).any() else np.inf for a in ang.T])
    return int(np.argmin(med))


#: segments up to which every order is tried (7! = 5,040); up to EXACT_MAX the exact dynamic
#: programme; beyond, a greedy chain improved by 2-opt (the CLI takes k up to markers / 3: a
#: hostile run's --k 20 tried 19! orders and never ended)
PERMUTE_MAX = 8
EXACT_MAX = 14


def best_chain(cost: np.ndarray, root: int) -> tuple[list, float]:
    """The single chain from ``root`` through every segment with the smallest summed joint
    cost: exhaustive over the orders up to :data:`PERMUTE_MAX` segments (ties ->
    lexicographically first; the paper's 3-6), the same minimum by dynamic programming over
    subsets up to :data:`EXACT_MAX` (Held-Karp, ``O(2^k k^2)``), and beyond a greedy chain (the
    cheapest next link) improved by 2-opt reversals until none helps (not always the minimum)."""
    k = cost.shape[0]
    others = [s for s in range(k) if s != root]
    if k > EXACT_MAX:
        return _greedy_chain(cost, root)
    if k > PERMUTE_MAX:
        return _held_karp(cost, root)
    best, best_cost = [root, *others], np.inf
    for perm in permutations(others):
        order = [root, *perm]
        c = _chain_cost(cost, order)
        if c < best_cost:
            best, best_cost = order, c
    return best, best_cost


def _chain_cost(cost: np.ndarray, order: list) -> float:
    return float(sum(cost[order[i], order[i + 1]] for i in range(len(order) - 1)))


def _held_karp(cost: np.ndarray, root: int) -> tuple[list, float]:
    """Shortest path from ``root`` through every segment (bitmask dynamic programme)."""
    k = cost.shape[0]
    c = cost.tolist()
    # best[(mask, last)] = (cost, previous): paths from root over the segments in mask
    best: dict[tuple[int, int], tuple[float, int]] = {(1 << root, root): (0.0, -1)}
    frontier = {(1 << root, root)}
    for _ in range(k - 1):
        nxt = set()
        for mask, last in frontier:
            base = best[(mask, last)][0]
            for s in range(k):
                if mask >> s & 1:
                    continue
                key = (mask | 1 << s, s)
                val = base + c[last][s]
                if key not in best or val < best[key][0]:
                    best[key] = (val, last)
                nxt.add(key)
        frontier = nxt
    full = (1 << k) - 1
    last = min(range(k), key=lambda s: (best.get((full, s), (np.inf, -1))[0], s))
    total = best[(full, last)][0]
    order, mask = [], full
    while last >= 0:
        order.append(last)
        prev = best[(mask, last)][1]
        mask &= ~(1 << last)
        last = prev
    return order[::-1], float(total)


def _greedy_chain(cost: np.ndarray, root: int) -> tuple[list, float]:
    """The cheapest next link from ``root`` on, then 2-opt reversals of the tail while one
    lowers the summed cost."""
    k = cost.shape[0]
    order, left = [root], set(range(k)) - {root}
    while left:
        nxt = min(left, key=lambda s: (cost[order[-1], s], s))
        order.append(nxt)
        left.remove(nxt)
    total = _chain_cost(cost, order)
    improved = True
    while improved:
        improved = False
        for i in range(1, k - 1):
            for j in range(i + 1, k):
                cand = order[:i] + order[i : j + 1][::-1] + order[j + 1 :]
                c = _chain_cost(cost, cand)
                if c < total - 1e-12:
                    order, total, improved = cand, c, True
    return order, total


def spanning_tree(cost: np.ndarray, root: int) -> tuple[list, np.ndarray]:
    """Minimum spanning tree from ``root`` (Prim) over joint costs: ``(order, parent)`` with
    ``order`` parents first and ``parent[root] = -1`` ([OBBH00])."""
    k = cost.shape[0]
    parent = -np.ones(k, dtype=np.intp)
    order = [root]
    while len(order) < k:
        best = None
        for a in order:
            for b in range(k):
                if b not in order and (best is None or (cost[a, b], b, a) < best):
                    best = (float(cost[a, b]), b, a)
        assert best is not None
        parent[best[1]] = best[2]
        order.append(best[1])
    return order, parent


def skeleton_structure(
    cost: np.ndarray, root: int, structure: str = "chain"
) -> tuple[list, np.ndarray]:
    """``(order, parent)`` of the skeleton: ``"chain"`` (the paper's, :func:`best_chain`) or
    ``"tree"`` ([OBBH00], :func:`spanning_tree`). ``"auto"`` is decided by the model, which
    builds both and keeps the one that reproduces the training surface best."""
    if structure == "tree":
        return spanning_tree(cost, root)
    if structure != "chain":
        raise ValueError(f"structure must be chain or tree, got {structure!r}")
    chain, _ = best_chain(cost, root)
    parent = -np.ones(cost.shape[0], dtype=np.intp)
    for a, b in zip(chain[:-1], chain[1:], strict=True):
        parent[b] = a
    return chain, parent


def is_chain(parent: np.ndarray) -> bool:
    """True when no segment has two children (a single chain from the root)."""
    p = parent[parent >= 0]
    return bool(p.size == np.unique(p).size)


def joint_centre(
    Rp: np.ndarray,
    tp: np.ndarray,
    Rc: np.ndarray,
    tc: np.ndarray,
    x0: np.ndarray,
    ridge: float = 1e-4,
    n_reweight: int = 3,
) -> tuple[np.ndarray, float]:
    """Rest-space joint centre between a parent and a child bone (module doc).

    ``Rp, Rc`` (F, 3, 3), ``tp, tc`` (F, 3); NaN frames are skipped. Returns the centre and the
    weighted RMS residual (mm) of the fixed-point equations.
    """
    ok = (
        np.isfinite(Rp).all(axis=(1, 2))
        & np.isfinite(Rc).all(axis=(1, 2))
        & np.isfinite(tp).all(axis=1)
        & np.isfinite(tc).all(axis=1)
    )
    if ok.sum() < 2:
        return np.asarray(x0, dtype=np.float64), float("nan")
    A = np.concatenate([Rp[ok], -Rc[ok]], axis=2)  # (F, 3, 6)
    b = tc[ok] - tp[ok]  # (F, 3)
    n = A.shape[0]
    lam = ridge * n
    prior = np.concatenate([x0, x0])
    w = np.ones(n)
    x = prior
    for _ in range(n_reweight + 1):
        AtA = np.einsum("f,fij,fik->jk", w, A, A) + lam * np.eye(6)
        Atb = np.einsum("f,fij,fi->j", w, A, b) + lam * prior
        x = np.linalg.solve(AtA, Atb)
        r = np.linalg.norm(np.einsum("fij,j->fi", A, x) - b, axis=1)
        scale = max(float(np.median(r)), 1e-6)
        w = 1.0 / (1.0 + (r / (2.0 * scale)) ** 2)
    rms = float(np.sqrt(np.sum(w * r**2) / np.sum(w)))
    return 0.5 * (x[:3] + x[3:]), rms


def boundary_centroid(
    rest: np.ndarray, labels: np.ndarray, faces: np.ndarray, a: int, b: int
) -> np.ndarray:
    """Rest centroid of markers of ``a`` or ``b`` on an edge joining the two (else of the two
    markers, one per segment, closest to each other)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [0, 2]]])
    la, lb = labels[e[:, 0]], labels[e[:, 1]]
    cross = ((la == a) & (lb == b)) | ((la == b) & (lb == a))
    if cross.any():
        return rest[np.unique(e[cross])].mean(axis=0)
    ia, ib = np.flatnonzero(labels == a), np.flatnonzero(labels == b)
    d = np.linalg.norm(rest[ia][:, None] - rest[ib][None], axis=2)
    i, j = np.unravel_index(np.argmin(d), d.shape)
    return 0.5 * (rest[ia[i]] + rest[ib[j]])
