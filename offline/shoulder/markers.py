"""Step 4: reduced marker set, four markers per segment (Hong et al. 2009, Sec. 3.4, Eq. 1-3).

For each segment independently, greedily pick the marker of lowest energy
``e = omega * e_r + (1 - omega) * e_d`` (``omega = 0.5``):

* Eq. 1, ``e_r = sum_t ||p^t - T^t p_hat||^2``: how far the marker strays from following the
  segment's rigid motion ``T^t`` (fitted to the dense set);
* Eq. 2-3, ``e_d = sum_i d(p_hat, p_hat_i)`` over the markers already chosen, with
  ``d = 1 - ||p_hat - p_hat_i|| / d_t`` when closer than ``d_t`` and 0 beyond; ``d_t`` is a
  quarter of the longest distance between two markers of the segment.

The paper does not say how ``e_r`` (mm^2 summed over frames) and ``e_d`` (unitless, up to 3) are
put on one scale; we divide ``e_r`` by its largest value among the segment's candidates so both
lie in [0, 1] per term. The first marker is chosen by ``e_r`` alone. Candidates are the markers
inside the segment (skin weight 1); if fewer than four, every marker labelled with it.
Missing samples: ``e_r`` is the mean over visible frames times the number of frames.
"""

from __future__ import annotations

import numpy as np


def distance_energy(p: np.ndarray, chosen: np.ndarray, d_t: float) -> np.ndarray:
    """Eq. 2-3: ``e_d`` of candidate positions ``p`` (n, 3) given chosen positions (c, 3)."""
    if chosen.size == 0 or d_t <= 0:
        return np.zeros(p.shape[0])
    d = np.linalg.norm(p[:, None] - chosen[None], axis=2)
    return np.where(d < d_t, 1.0 - d / d_t, 0.0).sum(axis=1)


def select_markers(
    rest: np.ndarray,
    candidates: np.ndarray,
    segment_markers: np.ndarray,
    e_r: np.ndarray,
    n_select: int = 4,
    omega: float = 0.5,
) -> np.ndarray:
    """Greedy choice of ``n_select`` marker indices among ``candidates`` (module doc).

    ``segment_markers`` (all the segment's markers) define ``d_t``; ``e_r`` is Eq. 1 per marker
    (indexed by marker).
    """
    cand = np.asarray(candidates, dtype=np.intp)
    if not 0.0 <= omega <= 1.0:
        raise ValueError(f"omega must be in [0, 1], got {omega}")
    if cand.size == 0:
        return cand
    seg = rest[np.asarray(segment_markers, dtype=np.intp)]
    d_t = 0.25 * float(np.max(np.linalg.norm(seg[:, None] - seg[None], axis=2))) if len(seg) else 0
    er = e_r[cand]
    finite = np.isfinite(er)
    top = er[finite].max() if finite.any() else 1.0
    er_n = np.where(finite, er / max(top, 1e-12), 2.0)
    chosen: list[int] = []
    free = np.ones(cand.size, dtype=bool)
    for step in range(min(n_select, cand.size)):
        if step == 0:
            e = er_n.copy()
        else:
            ed = distance_energy(rest[cand], rest[cand[chosen]], d_t)
            e = omega * er_n + (1.0 - omega) * ed
        e[~free] = np.inf
        j = int(np.argmin(e))
        chosen.append(j)
        free[j] = False
    return cand[chosen]
