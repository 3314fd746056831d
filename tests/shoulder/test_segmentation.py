"""Restart k-means: batched Lloyd vs the loop twin, recovery, reproducibility, validation."""

from __future__ import annotations

import numpy as np
import pytest
from shoulder.reference import lloyd_reference

from offline.shoulder.segmentation import RestartKMeans, _lloyd_batch, reduce_features


def _blobs(rng, k=4, n=30, d=12, spread=0.3):
    centres = rng.normal(scale=5.0, size=(k, d))
    X = np.concatenate([c + rng.normal(scale=spread, size=(n, d)) for c in centres])
    return X, np.repeat(np.arange(k), n)


def test_batched_lloyd_matches_loop_twin(rng):
    X, _ = _blobs(rng, k=3, n=20, d=5, spread=2.0)
    inits = np.stack([rng.choice(len(X), 3, replace=False) for _ in range(6)])
    labels, centres, inertia, _ = _lloyd_batch(X, X[inits], max_iter=100)
    for r, init in enumerate(inits):
        lab, cen, ine = lloyd_reference(X, init)
        np.testing.assert_array_equal(labels[r], lab)
        np.testing.assert_allclose(centres[r], cen, atol=1e-9)
        assert inertia[r] == pytest.approx(ine, rel=1e-9)


def test_reduce_features_preserves_distances(rng):
    X = rng.normal(size=(15, 200))
    Z = reduce_features(X, keep_variance=1.0)
    assert Z.shape[1] <= 14
    d_x = np.linalg.norm(X[:, None] - X[None], axis=2)
    d_z = np.linalg.norm(Z[:, None] - Z[None], axis=2)
    np.testing.assert_allclose(d_z, d_x, atol=1e-8)


def test_restarts_find_the_blobs_and_are_reproducible(rng):
    X, truth = _blobs(rng)
    km = RestartKMeans(n_clusters=4, n_restarts=20, batch_size=7, random_state=5).fit(X)
    # every true blob maps to exactly one cluster
    for c in range(4):
        assert np.unique(km.labels_[truth == c]).size == 1
    assert np.unique(km.labels_).size == 4
    again = RestartKMeans(n_clusters=4, n_restarts=20, batch_size=7, random_state=5).fit(X)
    np.testing.assert_array_equal(km.labels_, again.labels_)
    assert km.inertia_ == again.inertia_
    assert km.inertias_.shape == (20,)
    assert km.inertia_ == pytest.approx(
        ((X - km.cluster_centers_[km.labels_]) ** 2).sum(), rel=1e-12
    )


def test_more_restarts_never_worse(rng):
    X, _ = _blobs(rng, k=6, n=10, d=6, spread=1.5)
    few = RestartKMeans(6, n_restarts=1, random_state=3).fit(X)
    many = RestartKMeans(6, n_restarts=200, random_state=3).fit(X)
    # the first restart of ``many`` is ``few``'s run, so the best can only improve
    assert many.inertias_.min() <= few.inertias_.min() + 1e-9


def test_progress_is_reported_per_batch(rng):
    X, _ = _blobs(rng)
    seen = []
    RestartKMeans(4, n_restarts=10, batch_size=4, random_state=0).fit(X, progress=seen.append)
    assert seen == [4, 8, 10]


def test_validation(rng):
    X, _ = _blobs(rng)
    with pytest.raises(ValueError, match="n_clusters"):
        RestartKMeans(n_clusters=0).fit(X)
    with pytest.raises(ValueError, match="NaN"):
        RestartKMeans(2).fit(np.full((4, 2), np.nan))
    with pytest.raises(ValueError, match="samples, features"):
        RestartKMeans(2).fit(np.zeros(5))
    with pytest.raises(ValueError, match="keep_variance"):
        RestartKMeans(2, keep_variance=0.0).fit(X)


def test_precomputed_reduction_gives_the_same_fit(rng):
    X, _ = _blobs(rng, k=4, n=15, d=40, spread=1.0)
    Z = reduce_features(X, 0.999)
    own = RestartKMeans(4, n_restarts=30, keep_variance=0.999, random_state=2).fit(X)
    given = RestartKMeans(4, n_restarts=30, keep_variance=0.999, random_state=2).fit(X, reduced=Z)
    np.testing.assert_array_equal(own.labels_, given.labels_)
    np.testing.assert_array_equal(own.inertias_, given.inertias_)
    assert own.inertia_ == given.inertia_
    with pytest.raises(ValueError, match="reduced"):
        RestartKMeans(4).fit(X, reduced=Z[:-1])
