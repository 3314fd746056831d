"""A performer walking out of the volume takes ghosts (issue 10, ``ghosts3``; an open problem).

Two articulated performers (tests/labeling/scene.py) are labeled at 120 Hz. From a third of
the way in, the second one walks out: his markers vanish one by one, every 6 frames, until
three of his eight are left (one segment's three markers, enough for the presence check to
count him present). Ghost points, each living a few frames, appear 20-100 mm from the visible
markers and where his vanished markers were - the ``ghosts3`` cells where the BTS gait take
walks out of its volume (holdout10: 135 of its 140 ghost labels are his, in his last 60 frames).
His vanished markers have no rigid neighbourhood left to vouch for a ghost, so none should take
one, and the markers that stay should keep their labels. Today the leaver's labels take about
30 % of the ghosts (the presence check sees three markers and counts him present); the test is
a strict xfail until a mechanism removes the class.
"""

from __future__ import annotations

import numpy as np
import pytest
from labeling.scene import GhostScore, articulated

from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.labeler import Labeler

RATE = 120.0
INIT = 30
FRAMES = 420
LEAVE = 120
STEP = 6  # frames between two of the leaver's markers vanishing
VANISH = (15, 14, 13, 12, 11)  # the order his markers leave in (8, 9, 10 stay)


def _run(config: LabelerConfig, seed: int = 5) -> tuple[int, int, float]:
    """(ghosts given a label of the leaver, ghosts, accuracy over the visible markers)."""
    rng = np.random.default_rng(seed)
    pos, names = articulated(rng, subjects=2, frames=FRAMES, rate=RATE)
    lab = Labeler(names, RATE, config)
    gone_at = {m: LEAVE + k * STEP for k, m in enumerate(VANISH)}
    ghosts_alive: list[list] = []  # [position, velocity, frames left]
    score = GhostScore(first=8, start=max(INIT, LEAVE))
    for f in range(FRAMES):
        frame = pos[f].copy()
        for m, g in gone_at.items():
            if f >= g:
                frame[m] = np.nan
        vis = np.flatnonzero(np.isfinite(frame[:, 0]))
        pts = frame[vis]
        truth = vis.astype(np.int32)
        if f >= LEAVE:
            ghosts_alive = [[p + v, v, n - 1] for p, v, n in ghosts_alive if n > 0]
            for _ in range(rng.poisson(0.6)):  # about 3 alive at a time
                if rng.random() < 0.5:
                    src = pos[f, vis[rng.integers(vis.size)]]
                else:  # where one of the leaver's vanished markers was
                    left = [m for m, g in gone_at.items() if f >= g]
                    src = (
                        pos[gone_at[left[0]] - 1, left[rng.integers(len(left))]]
                        if left
                        else pos[f, 8]
                    )
                d = rng.normal(size=3)
                p = src + d / np.linalg.norm(d) * rng.uniform(20.0, 100.0)
                ghosts_alive.append([p, rng.normal(0.0, 2.0, 3), int(rng.geometric(0.2))])
            if ghosts_alive:
                g = np.array([p for p, _, _ in ghosts_alive], dtype=np.float32)
                pts = np.vstack([pts, g])
                truth = np.append(truth, np.full(len(g), -1)).astype(np.int32)
        score.feed(lab, rng, f, RATE, pts, truth, INIT)
    return score.result()


@pytest.mark.xfail(
    strict=True,
    reason="issue 10, ghosts3 class D': a performer walking out of the volume takes ghosts "
    "(docs/algorithm.md, 'A performer walking out'); no mechanism tried removed it without "
    "losing accuracy on the cross-take matrix",
)
def test_a_performer_walking_out_takes_no_ghost():
    taken, ghosts, acc = _run(LabelerConfig())
    assert ghosts > 500  # the scene has the ghosts (this holds today)
    assert taken <= 0.005 * ghosts
    assert acc >= 0.995


def test_the_walking_out_scene_has_its_ghosts():
    """The xfail above fails on its bar, not on the scene: the ghosts are there, and the
    presence check does not apply (three of the leaver's markers stay visible)."""
    _, ghosts, _ = _run(LabelerConfig())
    assert ghosts > 500
