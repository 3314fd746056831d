"""The body step's scores of the boot's greedy selection (``boot_match._body_scores``) against
their numpy twin (``tests/reference.py:body_scores``): the same arrays to the bit, so the
``argmax`` that picks the next segment breaks ties the same way."""

from __future__ import annotations

import numpy as np
import pytest

from labeler_service.labeling.boot_match import _body_scores
from tests.reference import body_scores


def _inputs(rng, n, c, m, k=8):
    bodies = np.full((c, k), -1, dtype=np.int64)
    for i in range(c):
        size = int(rng.integers(1, min(k, n) + 1))
        bodies[i, :size] = rng.choice(n, size, replace=False)
    chosen = rng.random(n) < 0.3
    blocked = chosen | (rng.random(n) < 0.2)
    links = rng.integers(0, 6, n).astype(np.int64)
    lerr = rng.random(n) * links  # sums of per-link |d - D| / tolerance
    possible = links + rng.integers(0, 4, n)
    support = rng.integers(0, 4, n).astype(np.int64)
    against = rng.integers(0, 3, n).astype(np.int64)
    near = rng.random((c, m)) < 0.2
    M = rng.integers(0, m, n).astype(np.int64)
    refused = rng.random(c) < 0.1
    return bodies, chosen, blocked, links, lerr, possible, support, against, near, M, refused


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize("complete", [False, True])
def test_body_scores_match_twin(seed, complete):
    rng = np.random.default_rng(seed)
    n, c, m = int(rng.integers(2, 300)), int(rng.integers(1, 60)), int(rng.integers(3, 60))
    args = _inputs(rng, n, c, m)
    got = _body_scores(*args, complete, 0.5)
    want = body_scores(*args, complete, 0.5)
    for g, w in zip(got, want, strict=True):
        assert g.dtype.kind == w.dtype.kind
        np.testing.assert_array_equal(g, w)  # exact: argmax ties break the same


def test_body_scores_degenerate():
    rng = np.random.default_rng(3)
    args = list(_inputs(rng, 5, 3, 4))
    args[0][:] = -1  # candidates with no node at all are never free
    total, rsum, count, fb, bb = _body_scores(*args, True, 0.5)
    assert (total == -1.0).all() and (rsum == 0).all() and not fb.any() and not bb.any()
    args = list(_inputs(rng, 6, 2, 4, k=5))  # rows narrower than 8 sum in order
    for g, w in zip(_body_scores(*args, False, 0.0), body_scores(*args, False, 0.0), strict=True):
        np.testing.assert_array_equal(g, w)
