"""A stream whose points are not in millimetres: said in the log, not left to look like a boot
that waits for its performers.

The wire unit is the millimetre (docs/protocol.md). A sender that streams metres (a capture
SDK's default) gives points a thousand times closer together than the model's subjects: no
template distance matches, nothing is ever labeled, and a booting stream reads ``booting``
for good, as if nobody were in the volume. :class:`UnitCheck` compares, while a stream labels
nothing, the largest extent of its frames' points over ``WINDOW_S`` of stream with the size of
its model's subjects (their longest trained marker-pair distance) and returns a warning when
they differ by more than a person can (``SMALL``, ``LARGE``). It never changes a frame.
"""

from __future__ import annotations

import math

import numpy as np

from labeler_service.capture.model import subject_groups
from labeler_service.labeling.templates import LabelerModel

#: seconds of stream (frame ``t``) with nothing labeled before the extents are compared
WINDOW_S = 2.0
#: points spanning less than this fraction of a subject of the model: another unit (metres
#: give 1/1000, centimetres 1/10; a person seen whole spans about their height, a hand alone
#: still a tenth of it)
SMALL = 1 / 20
#: points spanning more than this multiple of a subject: another unit (micrometres)
LARGE = 1000.0
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


class UnitCheck:
    """Per stream: fed every published frame (points, ``t``, markers observed, the labeler's
    model); returns a warning line when the points look like another unit than the model's."""

    def __init__(self) -> None:
        self._since: float | None = None
        self._span = 0.0
        self._model_id: int | None = None
        self._scale = 0.0
        self.warnings = 0  # warnings returned (tests, the log line)

    def reset(self) -> None:
        self._since, self._span = None, 0.0

    def update(
        self, stream: str, points: np.ndarray, t: float, observed: int, model: object
    ) -> str | None:
        if not isinstance(model, LabelerModel):
            self.reset()
            return None
        if id(model) != self._model_id:
            self._model_id, self._scale = id(model), model_scale(model)
        if self._scale <= 0.0 or observed > 0:
            self.reset()
            return None
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
