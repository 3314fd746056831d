"""The restart rule's two habits of real senders (``service/continuity.py``): a jittered clock
whose ``t`` steps back a little is no jump, and a ``seq`` counting in steps of 2 counts its
gaps in its own step. What stays a jump (a frozen ``t``, one that keeps running back, a
real jump) is checked beside them; the spoofed-frame and restart cases are in
``tests/hostile/``."""

from __future__ import annotations

import numpy as np

from labeler_service.service.continuity import JITTER_MIN_STEPS, Continuity

RATE = 120.0


def _jittered(n: int, sigma_s: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.arange(n) / RATE + rng.normal(scale=sigma_s, size=n)


def test_a_jittered_clock_loses_no_frame_and_labels_in_order():
    """3 ms of jitter at 120 Hz: about 2.5 % of the steps go back (each a ``time_jump`` drop
    before); they continue the run, re-timed, and the times frames are labeled at increase.
    Only a step back of more than half a frame (a 3.8-sigma pair here) is still a jump."""
    t = _jittered(3000, 0.003)
    back = np.diff(t) <= 0
    assert np.count_nonzero(back) > 60  # (the clock does step back)
    c = Continuity()
    used = []
    dropped = retimed = 0
    for k, tk in enumerate(t):
        v = c.check(1000 + k, float(tk))
        if v.reason is not None:
            assert v.reason == "time_jump"
            dropped += 1
            continue
        assert not v.new_run
        used.append(tk if v.t is None else v.t)
        if v.t is not None:
            retimed += 1
            assert 0 < v.t - tk < 1.1 / RATE  # (at most one frame ahead of its own t)
    assert dropped <= 2
    assert np.all(np.diff(used) > 0)
    assert retimed >= np.count_nonzero(back) - dropped
    assert c.last_seq == 1000 + len(t) - 1


def test_a_step_back_before_the_step_is_known_is_a_jump():
    c = Continuity()
    for k in range(JITTER_MIN_STEPS - 1):
        assert c.check(k, k / RATE).reason is None
    k = JITTER_MIN_STEPS - 1
    assert c.check(k, (k - 1) / RATE - 0.001).reason == "time_jump"


def _steady(c: Continuity, n: int = 40) -> int:
    for k in range(n):
        assert c.check(k, k / RATE).reason is None
    return n


def test_a_frozen_or_backward_running_clock_is_still_dropped():
    c = Continuity()
    n = _steady(c)
    last = (n - 1) / RATE
    # frozen: the same t again with seq + 1
    assert c.check(n, last).reason == "time_jump"
    c = Continuity()
    n = _steady(c)
    # running back 1 ms a frame: at most the first such frame is re-timed, none after it
    verdicts = [c.check(n + k, last - 0.001 * (k + 1)) for k in range(6)]
    assert sum(v.reason is None for v in verdicts) <= 1
    assert all(v.reason == "time_jump" for v in verdicts[1:])
    # a step back of more than half a frame is a jump
    c = Continuity()
    n = _steady(c)
    assert c.check(n, last - 0.6 / RATE).reason == "time_jump"


def test_a_seq_counting_by_two_counts_only_lost_frames_as_gaps():
    """Frame numbers of every other capture frame: each frame continues the run with no gap
    (before: one lost frame counted per frame); a lost frame is one gap frame."""
    c = Continuity()
    gaps = []
    k = 0
    for f in range(200):
        if f in (100, 150, 151):
            continue  # lost in the network
        v = c.check(2 * f, f / RATE)
        assert v.reason is None
        gaps.append(v.gap)
        k += 1
    assert sum(gaps) == 3
    assert gaps.count(1) == 1 and gaps.count(2) == 1


def test_a_restarted_sender_counting_by_one_counts_its_gaps_by_one():
    c = Continuity(confirm=3)
    for f in range(50):
        c.check(2 * f, f / RATE)
    # another sender takes the stream (seq and t elsewhere), counting by 1; it loses a frame
    verdicts = [c.check(s, s / RATE) for s in (10_000, 10_001, 10_002, 10_003, 10_005, 10_006)]
    assert [v.reason for v in verdicts[:2]] == ["seq_jump", "seq_jump"]
    assert verdicts[2].new_run
    assert [v.gap for v in verdicts[3:]] == [0, 1, 0]
