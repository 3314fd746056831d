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
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Verdict:
    """What to do with one frame: drop it (``reason``) or process it (``reason`` None)."""

    reason: str | None = None
    gap: int = 0  # frames missing before this one (forward seq gap), at most max_seq_step
    new_run: bool = False
    time_jumped: bool = False


ACCEPT = Verdict()


@dataclass(slots=True)
class _Candidate:
    seq: int
    t: float
    count: int
    reason: str
    time_jumped: bool
    seqs: list[int]  # its frames' seq (the new run's first ones, when adopted)


class Continuity:
    """The restart rule of the module docstring for one stream (not thread-safe)."""

    def __init__(self, *, max_seq_step: int = 100, max_time_step_s: float = 1.0,
                 confirm: int = 3) -> None:  # fmt: skip
        if max_seq_step < 1 or not max_time_step_s > 0 or confirm < 1:
            raise ValueError("max_seq_step >= 1, max_time_step_s > 0 and confirm >= 1 needed")
        self.max_seq_step = max_seq_step
        self.max_time_step_s = max_time_step_s
        self.confirm = confirm
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
        self._seen.add(seq)
        if len(self._seen) > 2 * self.max_seq_step:
            low = seq - self.max_seq_step
            self._seen = {s for s in self._seen if s >= low}

    def _plausible_seq(self, ds: int) -> bool:
        return 1 <= ds <= self.max_seq_step

    def _plausible_t(self, dt: float) -> bool:
        return 0.0 < dt <= self.max_time_step_s

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
            self._accept(seq, t)
            self._cand = None
            return ACCEPT if ds == 1 else Verdict(None, ds - 1)
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
