"""A stream whose points are not in millimetres: said in the log, not left to look like a boot
that waits for its performers.

The wire unit is the millimetre (docs/protocol.md). A sender that streams metres (a capture
SDK's default) gives points a thousand times closer together than the model's subjects: no
template distance matches, nothing is ever labeled, and a booting stream reads ``booting``
for good, as if nobody were in the volume. :class:`UnitCheck` compares, while a stream labels
nothing, the largest extent of its frames' points over ``WINDOW_S`` of stream with the size of
its model's subjects (their longest trained marker-pair distance) and returns a warning when
they differ by more than a person can (``SMALL``, ``LARGE``). A stream whose points are in
millimetres but whose model is of other performers (another marker set: a 31-marker model fed
a 39-marker take) read ``booting`` for good too: after ``MATCH_S`` of points with nothing
labeled the check says how many points its frames carry beside the model's markers, and the
fix. It never changes a frame.
"""

from __future__ import annotations

import math

import numpy as np

from labeler_service.capture.model import subject_groups
from labeler_service.labeling.templates import LabelerModel
from labeler_service.wording import plural

#: seconds of stream (frame ``t``) with nothing labeled before the extents are compared
WINDOW_S = 2.0
#: points spanning less than this fraction of a subject of the model: another unit (metres
#: give 1/1000, centimetres 1/10; a person seen whole spans about their height, a hand alone
#: still a tenth of it)
SMALL = 1 / 20
#: points spanning more than this multiple of a subject: another unit (micrometres)
LARGE = 1000.0
#: seconds of stream with points but nothing labeled before the points per frame are compared
#: with the model's markers (a model of another marker set, or performers the boot cannot
#: place: either way the log says it, where the stream only read ``booting``)
MATCH_S = 10.0
#: frames with fewer points than this are an empty volume, not a mismatch
MIN_POINTS = 3
#: labeled init frames none of whose subjects spans this many mm are in another unit (no
#: person's markers span less than a head's, ~150 mm); a model trained on them matches their
#: points, so the check above cannot see it
TINY_MM = 50.0


def init_span_warning(
    stream: str, frames: list[np.ndarray], idx: list[np.ndarray], names: list[str]
) -> str | None:
    """A warning when the labeled init frames' subjects all span less than ``TINY_MM``: the
    largest extent, over the frames, of one subject's labeled points in one frame."""
    codes = np.full(len(names) + 1, -1, dtype=np.int64)  # idx -1 (unlabeled point): none
    for c, members in enumerate(subject_groups(names).values()):
        codes[members] = c
    span = 0.0
    for pts, ix in zip(frames, idx, strict=True):
        if len(pts) < 2:
            continue
        sub = codes[np.asarray(ix, dtype=np.int64)]
        for c in np.unique(sub[sub >= 0]):
            p = pts[sub == c]
            if len(p) >= 2:
                span = max(span, float(np.max(np.ptp(p, axis=0))))
    if not 0.0 < span < TINY_MM:
        return None
    return (
        f"stream {stream}: the subjects of its labeled init frames span at most {span:.4g}: if "
        "they are people, their points are in another unit, metres (x 1000) or centimetres "
        "(x 10)? Points travel in millimetres (docs/protocol.md)"
    )


def model_scale(model: LabelerModel) -> float:
    """The longest trained marker-pair distance of the model's subjects (mm); 0 when none."""
    best = 0.0
    for s in model.subjects:
        for row in s.D:
            for d in row:
                if d is not None and math.isfinite(d) and d > best:
                    best = float(d)
    return best


def _points_and_markers(model: LabelerModel, counts: list[int]) -> tuple[int, int]:
    """The median points per frame of ``counts`` and the markers of ``model``."""
    return int(np.median(counts)), sum(len(s.markers) for s in model.subjects)


def match_warning(stream: str, model: LabelerModel, counts: list[int], seconds: float) -> str:
    """The points per frame of a stream that labeled nothing for ``seconds``, beside its model's
    subjects and markers, and what to do about each reading."""
    points, total = _points_and_markers(model, counts)
    sizes = ", ".join(f"{s.name} {len(s.markers)}" for s in model.subjects)
    head = (
        f"stream {stream}: nothing labeled for {seconds:.1f} s of stream; its frames carry "
        f"{plural(points, 'point')} (median) where its model has {plural(total, 'marker')} "
        f"({sizes})"
    )
    if points > total:
        why = (
            "more points than the model has markers: if they are not all ghosts, the model is "
            "not of these performers or marker set;"
        )
    else:
        why = (
            "if the model is of these performers and marker set, the boot has not placed them "
            "yet (docs/algorithm.md, boot limits); otherwise"
        )
    return (
        f"{head}: {why} train a model on a labeled take of these performers "
        "(mocap-labeler train structure TAKE... --out MODEL), set it as the stream's model and "
        "restart"
    )


class UnitCheck:
    """Per stream: fed every published frame (points, ``t``, markers observed, the labeler's
    model); returns a warning line when the points look like another unit than the model's,
    or, after ``MATCH_S`` of points with nothing labeled, one comparing the points per frame
    with the model's markers (:func:`match_warning`)."""

    def __init__(self) -> None:
        self._since: float | None = None
        self._span = 0.0
        self._model_id: int | None = None
        self._scale = 0.0
        self._quiet_since: float | None = None  # the nothing-labeled run, for the match check
        self._counts: list[int] = []
        self._units_off = False  # a unit warning was given in this run: it says it better
        #: match warnings given in this nothing-labeled stretch: each waits twice as long as
        #: the one before (MATCH_S, 2 MATCH_S, 4 MATCH_S...; it came every 10 s for as long
        #: as a stream of other performers ran)
        self._repeats = 0
        self.warnings = 0  # warnings returned (tests, the log line)

    def reset(self) -> None:
        self._since, self._span = None, 0.0

    def new_run(self) -> None:
        """Both checks start over, and the match warning's repeats with them: a new run
        (another sender, or one back after a pause: the nothing-labeled time and points per
        frame were theirs; a warning at the new run's first frame gave the previous run's
        counts and the jump in ``t`` as its duration), a label, a labeler without a model."""
        self.reset()
        self._reset_match()
        self._repeats = 0

    def _reset_match(self) -> None:
        self._quiet_since, self._counts, self._units_off = None, [], False

    def _match(self, stream: str, points: np.ndarray, t: float, model: LabelerModel) -> str | None:
        if len(points) < MIN_POINTS:
            return None  # an empty volume says nothing about the model
        if self._quiet_since is None or t < self._quiet_since:
            self._quiet_since, self._counts = t, []
        self._counts.append(len(points))
        dt = t - self._quiet_since
        if dt < MATCH_S * 2**self._repeats:
            return None
        counts, units_off = self._counts, self._units_off
        self._reset_match()
        self._units_off = units_off
        if units_off:
            return None
        self.warnings += 1
        self._repeats += 1
        again = f" (said again after {MATCH_S * 2**self._repeats:g} s of the same)"
        return match_warning(stream, model, counts, dt) + again

    def model_doubt(self, model: object) -> str:
        """While the stream has labeled nothing: its points per frame so far beside its
        model's markers, as a clause for the rate warning (:class:`RateCheck`), which comes
        before :func:`match_warning` does (``WINDOW_S`` against ``MATCH_S``): a model of
        other performers, whose rate the stream then runs at, was told to set a rate 8 s
        before it heard that the model may not be theirs. Empty once anything is labeled."""
        if not isinstance(model, LabelerModel) or self._quiet_since is None or not self._counts:
            return ""
        points, total = _points_and_markers(model, self._counts)
        return (
            f"; nothing is labeled yet and its frames carry {plural(points, 'point')} (median) "
            f"where its model has {plural(total, 'marker')}: if the model is not of these "
            "performers and marker set, train one on a labeled take of theirs (its rate is "
            "theirs) instead"
        )

    def update(
        self, stream: str, points: np.ndarray, t: float, observed: int, model: object
    ) -> str | None:
        if not isinstance(model, LabelerModel):
            self.new_run()
            return None
        if id(model) != self._model_id:
            self._model_id, self._scale = id(model), model_scale(model)
        if self._scale <= 0.0 or observed > 0:
            self.new_run()
            return None
        match = self._match(stream, points, t, model)
        if match is not None:
            return match
        if self._since is None or t < self._since:
            self._since, self._span = t, 0.0
        if len(points) >= 2:
            self._span = max(self._span, float(np.max(np.ptp(points, axis=0))))
        dt = t - self._since
        if dt < WINDOW_S or self._span <= 0.0:
            return None
        span, ratio = self._span, self._span / self._scale
        self.reset()
        if SMALL <= ratio <= LARGE:
            return None
        self.warnings += 1
        self._units_off = True
        if ratio < SMALL:
            hint = (
                f"{1 / ratio:.0f} times smaller: are they in metres (x 1000) or centimetres (x 10)?"
            )
        else:
            hint = f"{ratio:.0f} times larger: are they in micrometres?"
        return (
            f"stream {stream}: nothing labeled for {dt:.1f} s of stream; its points span at most "
            f"{span:.4g} where a subject of its model spans {self._scale:.0f} mm, {hint} "
            "Points travel in millimetres (docs/protocol.md)"
        )


#: seconds of stream (frame ``t``) whose frame steps give the measured rate
RATE_WINDOW_S = 2.0
#: frame steps needed at least before the rates are compared
RATE_MIN_STEPS = 20
#: measured / stream rate outside [1 / RATE_OFF, RATE_OFF]: said in the log
RATE_OFF = 1.1
#: frame steps whose interquartile range exceeds this fraction of their median are irregular,
#: and a measured rate outside this range (Hz) is no capture's: the log then asks about the
#: sender's ``t`` instead of advising a rate setting
RATE_IRREGULAR = 0.25
RATE_PLAUSIBLE = (10.0, 10_000.0)


class RateCheck:
    """Per stream: the rate its frames come at (the median step of their ``t`` over
    ``RATE_WINDOW_S``) against the rate the stream runs at (``streams[].rate``, else its
    model's: a model trained at 240 Hz fed a 48 Hz stream sized its boot window and point
    tracker for 240 Hz, and labeled 0.76 of the markers where ``rate = 48`` labeled all).
    Returns one warning per stream rate that does not match, with the setting to change."""

    def __init__(self) -> None:
        self._steps: list[float] = []
        self._since: float | None = None
        self._t_last: float | None = None
        self._warned: float | None = None  # the stream rate already warned about

    def update(self, stream: str, t: float, rate: float | None) -> str | None:
        if rate is None or not math.isfinite(t) or rate == self._warned:
            return None
        last, self._t_last = self._t_last, t
        if last is None or not t > last:
            self._steps, self._since = [], None  # a restart or a time jump: measure again
            return None
        if self._since is None:
            self._since = last
        self._steps.append(t - last)
        if t - self._since < RATE_WINDOW_S or len(self._steps) < RATE_MIN_STEPS:
            return None
        steps = np.asarray(self._steps)
        step = float(np.median(steps))
        measured = 1.0 / step
        self._steps, self._since = [], None
        if 1.0 / RATE_OFF <= measured / rate <= RATE_OFF:
            return None
        self._warned = rate
        q1, q3 = np.percentile(steps, [25, 75])
        if (
            q3 - q1 > RATE_IRREGULAR * step
            or not RATE_PLAUSIBLE[0] <= measured <= RATE_PLAUSIBLE[1]
        ):
            # no capture rate to advise (a hostile or broken sender was told "set rate = 1")
            how = "irregularly" if q3 - q1 > RATE_IRREGULAR * step else "steadily"
            return (
                f"stream {stream}: its frames' t step {step:.4g} s apart ({how}; median) where "
                f"the stream runs at {rate:.4g} Hz: no capture rate - is the sender's t the "
                "capture time in seconds? (docs/protocol.md)"
            )
        return (
            f"stream {stream}: its frames come at {measured:.4g} Hz (the steps of their t) where "
            f"the stream runs at {rate:.4g} Hz (streams[].rate, else its model's rate): the boot "
            f"and its point tracks are sized for {rate:.4g} Hz; set rate = {measured:.4g} in "
            "this stream's [[streams]] table"
        )
