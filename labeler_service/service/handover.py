"""The window start's handover: frames flow from the plain labeler while the window model trains.

A stream whose labeled start runs through a window model (``labeled_start = "auto"`` where it
applies, or ``"model"``; :meth:`~labeler_service.service.stream.StreamState.train`) trained
the window model and warmed the booting labeler up while its worker awaited the training job:
at 10 performers and 360 Hz about a second more than the plain start, during which the frames
were dropped (270 -> ~700), the stream jumped and the booting labeler dropped 8 of 10 subjects
as vanished (steady p99 8 -> ~100 ms). The service now starts such a stream in two steps::

    first unlabeled frame --train (off the loop, as the "labeler" start)--> plain labeler
        |  frames labeled by the plain labeler; each recorded here (points, t)
        v
    handover job (Background, budget train_budget_s):  window model (in a spawn child,
        window_worker = "process") -> window labeler
        -> fed the init window with its labels (as train does) -> caught up on the recorded
           frames (unlabeled, every stride-th while far behind, then at the full rate)
        v
    next frame (frame boundary): the frames recorded since the job ended (0-2) are fed to
    the window labeler, which replaces the plain one (StreamState._install_handover)

The plain labeler's start costs the stall of the ``labeler`` start; the window model, the
booting labeler's warm-up and the catch-up run off the event loop. More than
:data:`HANDOVER_LEFT_MAX` frames left at the frame boundary (a busy worker) send the window
labeler back for another round off the loop rather than make the frame wait. The recorded
frames are bounded (:data:`HANDOVER_MAX_S` of stream); a job that falls further behind, a new
run, a recovery, an expired or removed stream abandon the handover (the plain labeler stays).

The catch-up feeds the recorded frames **unlabeled**: the window labeler labels them itself, as
``evaluate`` runs it from the init window on. Fed the plain labeler's labels instead (labeled
frames, then its inner labeler rebuilt from the last of them; a variant measured before it was
removed), it started from the plain labeler's mistakes: on 19 two-take scenes of the cross-take
matrix (``benchmarks/handover_delay.py --every 3`` for the other columns), handed over
after 1 s, ``quarter`` mean 93.70 % (tune) / 97.12 % (holdout) against 94.83 / 97.16 %
unlabeled, and one ``rate`` cell 99.78 -> 92.87 %; the unlabeled catch-up stays within a few
tenths of a handover after one frame (94.47 / 97.60 %; the labeler trained in place 91.09 /
96.84 %).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from labeler_service.labeling.frame import FrameLabeler
    from labeler_service.service.stream import InitWindow

#: Seconds of stream the handover records at most (10 performers at 360 Hz: ~6 kB a frame,
#: ~20 MB); a window labeler further behind than that is abandoned.
HANDOVER_MAX_S = 10.0
#: Frames the frame path feeds the window labeler at the swap at most; more go back off the
#: loop for another catch-up round (each costs a frame's labeling on the frame path).
HANDOVER_LEFT_MAX = 2
#: The catch-up labels at least this rate while far behind (every ``rate // CATCH_UP_HZ``-th
#: frame), as the boot's catch-up does (``booting.CATCH_UP_HZ``).
CATCH_UP_HZ = 60.0
#: The last this many seconds of the recorded frames are fed at the full rate (the window
#: labeler's point tracks and boot window read them)...
TAIL_S = 0.1
#: ... in the first this many rounds; later rounds stride to the newest frame (a loaded
#: machine, where a frame costs more than a period, never catches up at the full rate).
TAIL_ROUNDS = 4
#: Seconds of catch-up one job runs at most: it then gives the background slot up (other
#: streams' trainings and boots take it first, :data:`YIELD_S`) and goes on in a new job.
SLICE_S = 0.25
#: The wait between two catch-up jobs: longer than a waiting job's poll for the slot
#: (``Background.run``, 0.05 s), so such a job runs first.
YIELD_S = 0.06
#: Rounds of one job at most before it hands the window labeler over as it is (the frame
#: boundary then feeds the few frames left or sends it back).
MAX_ROUNDS = 64


@dataclass(eq=False)
class Handover:
    """One window start in progress (see the module docstring). The frame thread records
    frames and installs; the job thread trains and catches up; ``lock`` guards the record."""

    init: InitWindow | None  # the labeled init window (dropped once the labeler is fed it)
    names: tuple[str, ...]  # the plain labeler's markers (the recorded labels index them)
    rate: float
    plain: FrameLabeler | None = None  # the labeler it replaces (set when installed)
    labeler: FrameLabeler | None = None  # the window labeler, once trained
    model: object | None = None  # the window model, when trained before the first job
    #: frames the window labeler has been fed (absolute: 0 = the first recorded frame)
    done: int = 0
    #: frames recorded in all; ``base`` the absolute index of ``frames[0]``
    received: int = 0
    base: int = 0
    frames: deque = field(default_factory=deque)
    ready: bool = False  # a job finished: the next frame installs (or sends it back)
    again: bool = False  # the next frame found too many frames left: another round is due
    more: bool = False  # the last job ended its time slice behind: another job follows
    inflight: bool = False  # a job runs
    rounds: int = 0  # jobs run (the training's included)
    cancel: threading.Event = field(default_factory=threading.Event)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        self.frames = deque(maxlen=max(1, int(HANDOVER_MAX_S * self.rate)))

    @property
    def abandoned(self) -> bool:
        return self.cancel.is_set()

    def record(self, points: np.ndarray, t: float) -> None:
        """Frame thread: one frame the plain labeler labeled (its points, re-based time)."""
        with self.lock:
            if len(self.frames) == self.frames.maxlen:
                self.base += 1  # (the deque drops its oldest)
            self.frames.append((points, t))
            self.received += 1

    def pending(self) -> list[tuple[np.ndarray, float]] | None:
        """The recorded frames the window labeler has not been fed (oldest first); None when
        some were dropped from the record before it got to them."""
        with self.lock:
            if self.done < self.base:
                return None
            while self.base < self.done:  # fed already: no longer needed
                self.frames.popleft()
                self.base += 1
            return list(self.frames)

    def wait_for_frame(self, timeout_s: float) -> bool:
        """Job thread: waits (polling, at most ``timeout_s``) for a frame not fed yet."""
        deadline = time.perf_counter() + timeout_s
        while self.received <= self.done:
            if time.perf_counter() >= deadline or self.cancel.is_set():
                return False
            time.sleep(0.0002)
        return True


class AnyOf:
    """Set when any of its events is: what
    :func:`~labeler_service.service.background.run_in_process` watches (``is_set``) for "stop".
    The handover's job stops on its budget
    (the :class:`~labeler_service.service.background.Background` job's event) *or* on the
    handover's abandonment (:attr:`Handover.cancel`: the stream removed or expired, a new run,
    a recovery); watching only the first left a window model's child process running on after
    its stream was gone."""

    def __init__(self, *events: threading.Event | None) -> None:
        self.events = tuple(e for e in events if e is not None)

    def is_set(self) -> bool:
        return any(e.is_set() for e in self.events)


def catch_up_plan(n: int, stride: int, tail: int) -> list[int]:
    """Which of ``n`` pending frames a round feeds: every ``stride``-th, then the last ``tail``
    (0: none at the full rate) all; the newest always."""
    if n <= 0:
        return []
    cut = max(0, n - tail)
    idx = list(range(0, cut, max(1, stride)))
    idx += range(cut, n)
    if idx[-1] != n - 1:
        idx.append(n - 1)
    return idx
