"""``BootVerifier.idle``: with no subject verified (the labeled start: its subjects come from
the stream's labels) a frame only counts, as :meth:`BootVerifier.update` would count it, and
the booting labeler skips building the update's arguments."""

from __future__ import annotations

import numpy as np

from labeler_service.capture import Capture
from labeler_service.labeling.boot import BootConfig, Booter
from labeler_service.labeling.boot_verify import BootVerifier
from labeler_service.labeling.structure import window_model


def test_idle_counts_the_frame_only_while_nothing_is_verified(rng):
    pos = rng.normal(scale=80.0, size=(1, 6, 3)) + rng.normal(size=(20, 6, 3))
    model = window_model(Capture(pos.astype("float32"), tuple(f"s:m{i}" for i in range(6)), 50.0))
    a = BootVerifier(Booter(model), 50.0, BootConfig())
    b = BootVerifier(Booter(model), 50.0, BootConfig())
    m = len(model.marker_names)
    for _ in range(7):
        assert a.idle()
        assert b.update(np.zeros((m, 3)), np.ones(m, dtype=bool), np.arange(m)) is None
    assert a._frame == b._frame == 7  # (the tick phase of a later subject is the same)
    a.start(0)
    assert not a.idle() and a._frame == 7
    a.stop(0)
    assert a.idle()
