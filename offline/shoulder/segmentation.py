"""Step 2b: rigid segmentation by k-means with many random restarts (Hong et al. 2009, Sec. 3.2).

Triangles whose log-map feature vectors ``F_i`` (:func:`~offline.shoulder.rotations.
triangle_features`) are close rotate together. The paper runs standard k-means 1000 times from
random initial centres and keeps the run with the smallest sum of distances between feature
vectors and their cluster centre; :class:`RestartKMeans` does the same (criterion: the k-means
objective, the sum of *squared* distances, "inertia").

Speed (the paper needed 30 minutes; we want seconds):

* the ``T`` feature vectors live in ``R^{3F}`` with ``3F`` in the thousands but span at most
  ``T - 1`` dimensions. They are first mapped, exactly, to coordinates in that span (eigen-
  decomposition of the centred Gram matrix), then truncated to the leading components holding
  ``keep_variance`` (default 0.999) of the variance -- squared distances change by at most that
  fraction of the total spread (the discarded directions are mostly per-triangle noise);
* Lloyd iterations run for a whole batch of restarts at once: one matrix product gives every
  point-centre distance of every restart, a batched product of one-hot assignments updates every
  centre. No Python loop over restarts or points.

Initial centres are ``k`` distinct data points drawn uniformly (Forgy), one draw per restart from
``random_state``; an emptied cluster is re-seeded with the point farthest from its centre.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def reduce_features(X: np.ndarray, keep_variance: float = 1.0 - 1e-6) -> np.ndarray:
    """Coordinates ``(n, d)`` of the rows of ``X`` in their principal subspace.

    Pairwise distances are preserved exactly when ``keep_variance`` is 1 and up to the discarded
    variance otherwise. ``d <= n - 1``.
    """
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[0] < 1:
        raise ValueError(f"X must be (samples, features), got {X.shape}")
    Xc = X - X.mean(axis=0)
    G = Xc @ Xc.T
    w, V = np.linalg.eigh(G)
    w, V = w[::-1], V[:, ::-1]
    w = np.clip(w, 0.0, None)
    total = w.sum()
    if total <= 0:
        return np.zeros((X.shape[0], 1))
    d = int(np.searchsorted(np.cumsum(w) / total, keep_variance) + 1)
    d = max(1, min(d, int((w > total * 1e-15).sum()) or 1))
    return V[:, :d] * np.sqrt(w[:d])


def _sq_dist(X: np.ndarray, xx: np.ndarray, centres: np.ndarray, cc: np.ndarray) -> np.ndarray:
    """Squared distances ``(R, n, k)`` of every point to every centre of every restart (BLAS)."""
    R, k, d = centres.shape
    cross = (X @ centres.reshape(R * k, d).T).reshape(X.shape[0], R, k).transpose(1, 0, 2)
    return xx[None, :, None] - 2.0 * cross + cc[:, None, :]


def _lloyd_batch(
    X: np.ndarray, centres: np.ndarray, max_iter: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Lloyd's k-means for ``R`` restarts at once.

    ``X`` (n, d), ``centres`` (R, k, d) initial. Returns labels (R, n), centres (R, k, d),
    inertia (R,), iterations run.
    """
    R, k, _ = centres.shape
    n = X.shape[0]
    xx = np.einsum("nd,nd->n", X, X)
    labels = np.full((R, n), -1, dtype=np.intp)
    eye = np.eye(k)
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (returned)
        cc = np.einsum("rkd,rkd->rk", centres, centres)
        d2 = _sq_dist(X, xx, centres, cc)
        new = np.argmin(d2, axis=2)
        if np.array_equal(new, labels):
            break
        labels = new
        onehot = eye[labels]  # (R, n, k)
        counts = onehot.sum(axis=1)  # (R, k)
        sums = np.matmul(onehot.transpose(0, 2, 1), X)  # (R, k, d)
        empty = counts == 0
        counts[empty] = 1.0
        centres = sums / counts[:, :, None]
        if empty.any():  # re-seed an empty cluster with the point farthest from its centre
            own = np.take_along_axis(d2, labels[:, :, None], axis=2)[:, :, 0]
            for r, c in zip(*np.nonzero(empty), strict=True):
                far = int(np.argmax(own[r]))
                centres[r, c] = X[far]
                own[r, far] = -np.inf
    cc = np.einsum("rkd,rkd->rk", centres, centres)
    d2 = _sq_dist(X, xx, centres, cc)
    labels = np.argmin(d2, axis=2)
    inertia = np.maximum(np.take_along_axis(d2, labels[:, :, None], axis=2)[:, :, 0], 0).sum(1)
    return labels, centres, inertia, it


class RestartKMeans:
    """k-means keeping the best of ``n_restarts`` random initialisations (Hong et al., Sec. 3.2).

    Parameters follow scikit-learn: ``n_clusters``, ``n_restarts`` (paper: 1000), ``max_iter``
    per run, ``batch_size`` restarts per vectorised batch, ``keep_variance`` of the exact
    subspace reduction (module doc; 1.0 = exact), ``random_state``.

    Fitted attributes: ``labels_`` (n,), ``cluster_centers_`` (k, D) in the input space,
    ``inertia_`` (sum of squared distances of the best run, input space), ``inertias_``
    (n_restarts,) of every run (reduced space), ``n_iter_`` (max iterations over batches),
    ``n_components_`` (dimensions after reduction).
    """

    def __init__(
        self,
        n_clusters: int = 4,
        n_restarts: int = 1000,
        max_iter: int = 100,
        batch_size: int = 250,
        keep_variance: float = 0.999,
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.n_clusters = n_clusters
        self.n_restarts = n_restarts
        self.max_iter = max_iter
        self.batch_size = batch_size
        self.keep_variance = keep_variance
        self.random_state = random_state

    def fit(
        self,
        X: np.ndarray,
        progress: Callable[[int], None] | None = None,
        reduced: np.ndarray | None = None,
    ) -> RestartKMeans:
        """Clusters the rows of ``X`` (n, D). ``progress(n_done)`` is called after each batch.

        ``reduced``: ``reduce_features(X, keep_variance)`` when the caller already has it (the
        same features clustered for several ``k``); computed here otherwise.
        """
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2:
            raise ValueError(f"X must be (samples, features), got shape {X.shape}")
        if not np.isfinite(X).all():
            raise ValueError("X contains NaN or inf (fill gaps first)")
        n, k = X.shape[0], int(self.n_clusters)
        if not 1 <= k <= n:
            raise ValueError(f"n_clusters must be in 1..{n} (samples), got {self.n_clusters}")
        if self.n_restarts < 1 or self.max_iter < 1 or self.batch_size < 1:
            raise ValueError("n_restarts, max_iter and batch_size must be >= 1")
        if not 0.0 < self.keep_variance <= 1.0:
            raise ValueError(f"keep_variance must be in (0, 1], got {self.keep_variance}")
        rng = np.random.default_rng(self.random_state)  # a Generator is used as is
        if reduced is None:
            Z = reduce_features(X, self.keep_variance)
        else:
            Z = np.asarray(reduced, dtype=np.float64)
            if Z.ndim != 2 or Z.shape[0] != n:
                raise ValueError(f"reduced must be ({n}, d), got shape {Z.shape}")
        best_labels, best_inertia = None, np.inf
        inertias = np.empty(self.n_restarts)
        n_iter = 0
        done = 0
        while done < self.n_restarts:
            r = min(self.batch_size, self.n_restarts - done)
            # k distinct random points per restart (Forgy initialisation)
            init = np.argpartition(rng.random((r, n)), k - 1, axis=1)[:, :k]
            labels, _, inertia, it = _lloyd_batch(Z, Z[init], self.max_iter)
            inertias[done : done + r] = inertia
            n_iter = max(n_iter, it)
            j = int(np.argmin(inertia))
            if inertia[j] < best_inertia:
                best_inertia, best_labels = float(inertia[j]), labels[j].copy()
            done += r
            if progress is not None:
                progress(done)
        assert best_labels is not None
        # relabel clusters by first appearance: equal partitions give equal labels
        _, first = np.unique(best_labels, return_index=True)
        order = np.argsort(first)
        remap = np.empty(k, dtype=np.intp)
        remap[np.unique(best_labels)[order]] = np.arange(order.size)
        self.labels_ = remap[best_labels]
        self.cluster_centers_ = np.stack(
            [X[self.labels_ == c].mean(axis=0) for c in range(order.size)]
        )
        self.inertia_ = float(((X - self.cluster_centers_[self.labels_]) ** 2).sum())
        self.inertias_ = inertias
        self.n_iter_ = n_iter
        self.n_components_ = int(Z.shape[1])
        return self
