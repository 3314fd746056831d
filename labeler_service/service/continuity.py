"""Per-stream continuity of ``seq`` and ``t``: one restart rule for both, in both directions.

A frame continues the current run when its step from the last accepted frame is plausible:

- ``seq`` advances by 1 to ``max_seq_step`` (a forward gap of lost frames, counted, clipped to
  ``max_seq_step``);
- ``t`` advances by more than 0 and at most ``max_time_step_s`` (``t`` is finite: the decoder
  checked it).

``seq`` equal to the last one is a ``duplicate``; lower by at most ``max_seq_step`` it is
``late`` — unless the run accepted that ``seq`` already: a late frame fills a hole, while a
``seq`` seen twice is a ``duplicate`` that may start a new run like a jump (a sender started
again after a short run: every frame of its new run read ``late`` and was dropped, for as long
as it kept restarting, a hostile run). Anything else (a jump forward or back of ``seq`` or
``t``, a frozen or reversed ``t``) makes the frame **suspect**: it is dropped (``seq_jump`` or
``time_jump``) and remembered as the start of a candidate run. Only when ``confirm``
consecutive frames (the suspect one included) continue each other plausibly, with no frame of
the current run in between, is the candidate adopted as a **new run**: the verdict of its last
frame says ``new_run`` and the frame is processed. So one spoofed or broken frame changes
nothing (the next genuine frame continues the current run and forgets the candidate), while a
restarted sender (a second ``replay`` of the same file) or a sender back after a long pause
costs ``confirm - 1`` dropped frames.

``time_jumped`` on a new-run verdict tells whether ``t`` jumped too (the stream then re-bases
time so the labeler sees one frame period, not the jump).

Two habits of real senders are no jump:

- **A jittered clock.** A sender that stamps ``t`` from a host clock rather than the capture's
  steps back now and then (3 ms of jitter at 120 Hz: ``t`` back about 1 ms with ``seq`` + 1 in
  2 % of the frames, each dropped as a ``time_jump`` before). A frame whose ``seq`` continues
  the run and whose ``t`` lies less than ``jitter`` of the run's frame step behind the last
  accepted one continues the run, re-timed: its verdict's ``t`` is the last accepted time plus
  ``jitter`` of its ``seq`` steps at the run's step (half a frame; the step is learned from the
  accepted frames' own ``t``), so the labeler's times always increase and stay within a frame
  of the sender's. A frozen ``t`` (the
  same ``t`` again) or one running back by more is still a ``time_jump``, and a re-timed frame
  is the last accepted one, so a clock that keeps running back falls behind it and is
  dropped.
- **A ``seq`` counting in steps of 2 or more** (the capture's frame numbers of every other
  frame): a gap is counted in the run's own step, the smallest of its recent steps (before,
  such a stream counted one lost frame per frame and never counted as progressing).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Verdict:
    """What to do with one frame: drop it (``reason``) or process it (``reason`` None)."""

    reason: str | None = None
    gap: int = 0  # frames missing before this one (forward seq gap, in the run's seq step)
    new_run: bool = False
    time_jumped: bool = False
    #: the time to label the frame at when it is not the frame's own ``t`` (a jittered clock's
    #: step back, re-timed: the module docstring)
    t: float | None = None


ACCEPT = Verdict()


@dataclass(slots=True)
class _Candidate:
    seq: int
    t: float
    count: int
    reason: str
    time_jumped: bool
    seqs: list[int]  # its frames' seq (the new run's first ones, when adopted)


#: accepted frame steps before a step back of ``t`` is read as jitter (the run's step is known)
JITTER_MIN_STEPS = 8
#: weight of one frame's step in the run's learned step (an exponential average)
STEP_WEIGHT = 1 / 16
#: accepted ``seq`` steps the run's own step (their smallest) is taken over
SEQ_STEPS_KEPT = 64


class Continuity:
    """The restart rule of the module docstring for one stream (not thread-safe)."""

    def __init__(self, *, max_seq_step: int = 100, max_time_step_s: float = 1.0,
                 confirm: int = 3, jitter: float = 0.5) -> None:  # fmt: skip
        if max_seq_step < 1 or not max_time_step_s > 0 or confirm < 1 or not 0 <= jitter < 1:
            raise ValueError("max_seq_step >= 1, max_time_step_s > 0, confirm >= 1 and "
                             "0 <= jitter < 1 needed")  # fmt: skip
        self.max_seq_step = max_seq_step
        self.max_time_step_s = max_time_step_s
        self.confirm = confirm
        self.jitter = jitter
        self._step: float | None = None  # the run's t per seq step
        self._steps = 0  # accepted steps it was learned from
        self._seq_steps: deque[int] = deque(maxlen=SEQ_STEPS_KEPT)
        self._raw_last: float | None = None  # the last accepted frame's own t
        self.last_seq: int | None = None
        self.last_t: float | None = None
        self._cand: _Candidate | None = None
        # the run's accepted ``seq`` within ``max_seq_step`` of the last (a late one fills a
        # hole; one of these again is a restart)
        self._seen: set[int] = set()

    def _accept(self, seq: int, t: float, run: list[int] | None = None) -> None:
        """``run``: a new run, its seq so far (the candidate's frames, dropped while it was
        confirmed, belong to it: left out, the next restart read them late, and each restart
        lost two frames more than the last)."""
        self.last_seq, self.last_t = seq, t
        if run is not None:
            self._seen = set(run)
            self._seq_steps.clear()  # (a restarted sender may count in other steps)
            self._raw_last = t
        self._seen.add(seq)
        if len(self._seen) > 2 * self.max_seq_step:
            low = seq - self.max_seq_step
            self._seen = {s for s in self._seen if s >= low}

    def _plausible_seq(self, ds: int) -> bool:
        return 1 <= ds <= self.max_seq_step

    def _plausible_t(self, dt: float) -> bool:
        return 0.0 < dt <= self.max_time_step_s

    def _continue(self, seq: int, t: float, ds: int, t_label: float | None = None) -> Verdict:
        """Accepts a frame that continues the run (``t_label``: re-timed), learning the run's
        steps from it (its own ``t``'s step, back steps included: an unbiased average)."""
        self._seq_steps.append(ds)
        if self._raw_last is not None:
            step = (t - self._raw_last) / ds
            self._step = (
                step if self._step is None else self._step + STEP_WEIGHT * (step - self._step)
            )
            self._steps += 1
        self._accept(seq, t if t_label is None else t_label)
        self._raw_last = t
        self._cand = None
        gap = max(0, round(ds / min(self._seq_steps)) - 1)
        return ACCEPT if gap == 0 and t_label is None else Verdict(None, gap, t=t_label)

    def _retimed(self, ds: int, t: float) -> float | None:
        """The time a frame whose ``t`` steps back by jitter is labeled at (half its ``seq``
        steps at the run's step after the last accepted one), else None."""
        if self._step is None or self._steps < JITTER_MIN_STEPS or self.last_t is None:
            return None
        stride = min(self._seq_steps) if self._seq_steps else 1
        half = self.jitter * self._step * ds
        if not 0.0 < self.last_t - t < self.jitter * self._step * stride:
            return None
        return self.last_t + half

    def check(self, seq: int, t: float) -> Verdict:
        """The verdict for an arriving frame; updates the run on acceptance."""
        if self.last_seq is None or self.last_t is None:
            self._accept(seq, t, run=[])
            return ACCEPT
        ds = seq - self.last_seq
        if ds == 0:
            return Verdict("duplicate")
        repeat = -self.max_seq_step <= ds < 0
        if repeat and seq not in self._seen:
            return Verdict("late")
        seq_ok = self._plausible_seq(ds)
        t_ok = self._plausible_t(t - self.last_t)
        if seq_ok and t_ok:
            return self._continue(seq, t, ds)
        if seq_ok and (t_label := self._retimed(ds, t)) is not None:
            return self._continue(seq, t, ds, t_label)
        c = self._cand
        if c is not None and self._plausible_seq(seq - c.seq) and self._plausible_t(t - c.t):
            c.seq, c.t, c.count = seq, t, c.count + 1
            c.seqs.append(seq)
            if c.count >= self.confirm:
                self._cand = None
                self._accept(seq, t, run=c.seqs)
                return Verdict(None, 0, new_run=True, time_jumped=c.time_jumped)
            return Verdict(c.reason)
        reason = "duplicate" if repeat else "time_jump" if seq_ok else "seq_jump"
        self._cand = _Candidate(seq, t, 1, reason, not t_ok, [seq])
        if self.confirm == 1:
            return self.check_adopt()
        return Verdict(reason)

    def check_adopt(self) -> Verdict:
        """Adopts the pending candidate at once (``confirm == 1``)."""
        c = self._cand
        assert c is not None
        self._cand = None
        self._accept(c.seq, c.t, run=c.seqs)
        return Verdict(None, 0, new_run=True, time_jumped=c.time_jumped)
