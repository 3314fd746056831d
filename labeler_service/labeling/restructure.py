"""Structure re-formed from the stream's own motion (ours, issue 10; docs/algorithm.md).

A labeler trained on its labeled first frames learns its rigid bodies and recovery sets from
0.4 s (5 frames at 12.5 Hz): pairs across a joint held still look rigid there (a tennis hand
glued to the pelvis), and 5 samples of a moving segment may not look rigid at all. This module
keeps the evidence of the labeler's own confident output and re-forms the structure from it:

- **Evidence** (:func:`_accumulate`, once per frame, at most ``restructure_sample_hz``): for
  every pair of markers of one subject that are both *confident* - observed now, observed for
  ``restructure_age`` frames in a row, and every body holding them passes the 3D template check
  (``bodies.ok``) - the running sums of the pair distance and its square and the count
  (Eq. 1-2 over the whole stream rather than a sliding window, all pairs rather than body
  links). A fresh or doubted assignment is never learned. The sums start with the labeled
  training window (the same samples the structure was trained on); a labeler from a model
  starts them with the model's ``D``, ``A`` counted as ``restructure_prior_s`` seconds of
  samples, so the trained model is the anchor the stream relaxes.
- **Re-forming** (:meth:`Labeler.restructure`, every ``restructure_s``, only for a structure
  learned from fewer than ``restructure_max_train_frames`` samples): ``D``, ``A`` of every pair
  from the sums (:func:`pair_model`); the trained bodies stay (they link limbs to the trunk, and
  a lost limb is re-acquired through them), and every body the body rule of training
  (:func:`~labeler_service.labeling.training.select_bodies`) finds on the evidence that no kept
  body shown rigid contains is added (:func:`reform_bodies`). A body whose members are
  unchanged keeps its whole state (window, motion, reference shape); new bodies start with an
  empty window, their trained ``D``, ``A`` from the evidence. The Kalman tracks are not
  touched. Measured on the cross-take matrix: docs/algorithm.md.
"""

from __future__ import annotations

import numpy as np

from labeler_service._numba import njit
from labeler_service.labeling.frame import OBSERVED


@njit
def _add_pairs(pos, use, subj_ptr, subj_idx, s1, s2, n):
    """Adds one frame's distances between the markers ``use (M,)`` of each subject to ``s1``,
    ``s2`` (sums of the distance and its square) and ``n`` (count), ``(M, M)``, upper triangle
    in the labeler's marker order; ``pos (M, 3)``."""
    for s in range(subj_ptr.shape[0] - 1):
        for e in range(subj_ptr[s], subj_ptr[s + 1]):
            i = subj_idx[e]
            if not use[i]:
                continue
            for f in range(e + 1, subj_ptr[s + 1]):
                j = subj_idx[f]
                if not use[j]:
                    continue
                d2 = 0.0
                for a in range(3):
                    d = np.float64(pos[i, a]) - np.float64(pos[j, a])
                    d2 += d * d
                d = np.sqrt(d2)
                lo, hi = (i, j) if i < j else (j, i)
                s1[lo, hi] += d
                s2[lo, hi] += d2
                n[lo, hi] += 1


@njit
def _accumulate(state, age, pos, ok, mb_ptr, mb_idx, subj_ptr, subj_idx, min_age, conf, s1, s2, n):
    """Adds this frame's distances between confident markers of one subject to the sums
    (:func:`_add_pairs`). ``conf (M,)`` bool: scratch (the confident markers)."""
    for m in range(state.shape[0]):
        c = state[m] == OBSERVED and age[m] >= min_age
        if c:
            for q in range(mb_ptr[m], mb_ptr[m + 1]):
                if not ok[mb_idx[q]]:
                    c = False
                    break
        conf[m] = c
    _add_pairs(pos, conf, subj_ptr, subj_idx, s1, s2, n)


@njit
def add_samples(pos, subj_ptr, subj_idx, s1, s2, n):
    """Adds the labeled frames ``pos (F, M, 3)`` (NaN = not labeled) to the sums, every pair of
    markers of one subject (the training window: the samples the first structure was trained
    on). A kernel over each subject's pairs: all ``M x M`` pairs in numpy cost 1.8 s of a
    1,000-marker stream's training, holding the interpreter that other streams need."""
    use = np.empty(pos.shape[1], dtype=np.bool_)
    for k in range(pos.shape[0]):
        for m in range(pos.shape[1]):
            use[m] = pos[k, m, 0] == pos[k, m, 0]
        _add_pairs(pos[k], use, subj_ptr, subj_idx, s1, s2, n)


def add_prior(cols: np.ndarray, D: np.ndarray, A: np.ndarray, weight: float, s1, s2, n) -> None:
    """Adds a model's ``D``, ``A`` of the markers ``cols`` (subject order) as ``weight`` samples
    per known pair (a mean of ``D`` and a deviation of ``A``)."""
    if weight <= 0:
        return
    for a in range(len(cols)):
        for b in range(a + 1, len(cols)):
            d, s = D[a, b], A[a, b]
            if not (np.isfinite(d) and np.isfinite(s)):
                continue
            i, j = (cols[a], cols[b]) if cols[a] < cols[b] else (cols[b], cols[a])
            s1[i, j] += weight * d
            s2[i, j] += weight * (s * s + d * d)
            n[i, j] += weight


def pair_model(
    cols: np.ndarray, s1: np.ndarray, s2: np.ndarray, n: np.ndarray, min_samples: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """``D``, ``A`` of the markers ``cols`` (a subject, its order) from the sums; NaN where a
    pair has fewer than ``min_samples`` samples; sanitised as a trained model is
    (:func:`~labeler_service.labeling.training.model_pair_statistics`)."""
    lo = np.minimum.outer(cols, cols)
    hi = np.maximum.outer(cols, cols)
    from labeler_service.labeling.training import stats_from_sums, within_model_ranges

    c = n[lo, hi].astype(np.float64)
    return within_model_ranges(*stats_from_sums(s1[lo, hi], s2[lo, hi], c, min_samples))


def _cost(D: np.ndarray, A: np.ndarray, w: float) -> np.ndarray:
    c = A + w * D
    return np.where(np.isfinite(c), c, np.inf)


def reform_bodies(
    D: np.ndarray, A: np.ndarray, usable: np.ndarray, old: list[list[int]], config
) -> tuple[list[list[int]], list[list[int]]]:
    """One subject's bodies re-formed on the evidence ``D``, ``A`` (subject order).

    Returns ``(kept, added)``: the bodies ``old`` (the trained ones) whose every link costs at
    most ``restructure_break_mm`` (``A + w D``; all of them when it is 0, the default: bodies
    trained across a joint are the links a lost limb is re-acquired through), and new bodies -
    the body rule of training (:func:`~labeler_service.labeling.training.select_bodies`, tolerance
    ``restructure_tolerance_mm``) on the evidence - that no kept body contains
    (``restructure_add``), or only those holding a usable marker no kept body holds."""

    from labeler_service.labeling.training import select_bodies

    cost = _cost(D, A, config.body_distance_weight)
    kept = []
    for body in old:
        sub = cost[np.ix_(body, body)]
        np.fill_diagonal(sub, 0.0)
        if config.restructure_break_mm == 0 or sub.max() <= config.restructure_break_mm:
            kept.append(body)
    covered = np.zeros(len(usable), dtype=bool)
    for body in kept:
        covered[body] = True
    need = usable & ~covered
    add_all = config.restructure_add
    if not need.any() and not add_all:
        return kept, []
    chosen = select_bodies(D, A, usable, **config.body_rule(config.restructure_tolerance_mm))
    have = {tuple(sorted(b)) for b in kept}
    rigid = []  # kept bodies the evidence shows rigid: a rigid part of a bending one is added
    for body in kept:
        sub = cost[np.ix_(body, body)]
        np.fill_diagonal(sub, 0.0)
        if sub.max() <= config.restructure_tolerance_mm:
            rigid.append(body)
    added = [
        b
        for b in chosen
        if (need[b].any() or (add_all and not any(set(b) <= set(k) for k in rigid)))
        and tuple(sorted(b)) not in have
    ]
    return kept, added


def recovery_sets(D: np.ndarray, A: np.ndarray, usable: np.ndarray, config) -> dict:
    """Each usable marker's recovery set on the evidence: itself and its
    ``recovery_set_size`` lowest-cost usable neighbours (subject order)."""
    cost = _cost(D, A, config.body_distance_weight)
    np.fill_diagonal(cost, np.inf)
    cost[:, ~usable] = np.inf
    k = min(7, config.recovery_set_size)
    out = {}
    for i in np.flatnonzero(usable):
        order = [int(j) for j in np.argsort(cost[i], kind="stable")[:k] if np.isfinite(cost[i, j])]
        out[int(i)] = [int(i), *order]
    return out


def better_set(D, A, i, new, old, config) -> bool:
    """The set ``new`` of marker ``i`` is clearly more rigid than ``old``: its worst link to
    ``i`` costs less than the old one's by ``restructure_margin_mm`` (hysteresis: sets of equal
    neighbours do not flip, each flip waits for a new snapshot)."""
    cost = _cost(D, A, config.body_distance_weight)
    worst_new = max((cost[i, j] for j in new if j != i), default=np.inf)
    worst_old = max((cost[i, j] for j in old if j != i), default=np.inf)
    return worst_new + config.restructure_margin_mm < worst_old
