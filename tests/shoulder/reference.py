"""Plain-numpy twins of the shoulder kernels (compared in tests; slow but obviously right).

* :func:`horn_reference` -- Horn's quaternion via ``numpy.linalg.eigh`` of the 4x4 ``N`` matrix
  (twin of the numba ``offline.shoulder.rotations._horn_kernel``);
* :func:`lloyd_reference` -- one k-means run with explicit Python loops (twin of the batched
  ``offline.shoulder.segmentation._lloyd_batch``).
"""

from __future__ import annotations

import numpy as np


def horn_reference(ref: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """``(F, T, 4)`` quaternions (w >= 0), NaN where a vertex is missing."""
    out = np.full((cur.shape[0], cur.shape[1], 4), np.nan)
    for f in range(cur.shape[0]):
        for i in range(cur.shape[1]):
            b = cur[f, i]
            if np.isnan(b).any():
                continue
            a = ref[i] - ref[i].mean(axis=0)
            b = b - b.mean(axis=0)
            S = a.T @ b
            (sxx, sxy, sxz), (syx, syy, syz), (szx, szy, szz) = S
            N = np.array(
                [
                    [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
                    [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
                    [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
                    [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
                ]
            )
            _, V = np.linalg.eigh(N)
            q = V[:, -1]
            out[f, i] = q if q[0] >= 0 else -q
    return out


def lloyd_reference(X: np.ndarray, init: np.ndarray, max_iter: int = 100):
    """One Lloyd run from the rows ``init`` of ``X``: ``(labels, centres, inertia)``.

    Empty clusters keep their old centre (the batched version re-seeds them; tests avoid it).
    """
    centres = X[init].copy()
    labels = np.full(X.shape[0], -1)
    for _ in range(max_iter):
        new = np.empty(X.shape[0], dtype=int)
        for n in range(X.shape[0]):
            d = [float(((X[n] - c) ** 2).sum()) for c in centres]
            new[n] = int(np.argmin(d))
        if np.array_equal(new, labels):
            break
        labels = new
        for c in range(len(centres)):
            if (labels == c).any():
                centres[c] = X[labels == c].mean(axis=0)
    inertia = float(sum(((X[n] - centres[labels[n]]) ** 2).sum() for n in range(X.shape[0])))
    return labels, centres, inertia
