"""``boot._nearest_within`` (the acquisition's neighbours) against ``cKDTree.query``."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from labeler_service.labeling import boot


@pytest.mark.parametrize("block", [True, False])
@pytest.mark.parametrize("seed", range(4))
def test_same_neighbours_as_the_tree(seed, block, monkeypatch):
    if not block:  # the KD-tree path for large blocks
        monkeypatch.setattr(boot, "NEAREST_BLOCK", 0)
    rng = np.random.default_rng(seed)
    for _ in range(40):
        q = rng.uniform(-1000, 1000, (int(rng.integers(1, 40)), 3))
        p = rng.uniform(-1000, 1000, (int(rng.integers(1, 500)), 3))
        k, reach = min(8, p.shape[0]), float(rng.uniform(50, 800))
        dist, near = boot._nearest_within(q, p, k, reach)
        d2, n2 = cKDTree(p).query(q, k=k, distance_upper_bound=reach)
        d2, n2 = d2.reshape(q.shape[0], k), n2.reshape(q.shape[0], k)
        assert dist.shape == near.shape == (q.shape[0], k)
        for i in range(q.shape[0]):
            ok = np.isfinite(dist[i])
            assert set(near[i][ok].tolist()) == set(n2[i][np.isfinite(d2[i])].tolist())
            np.testing.assert_allclose(np.sort(dist[i][ok]), np.sort(d2[i][np.isfinite(d2[i])]))
