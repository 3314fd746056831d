"""The periodic log line reads the metrics registry once, whatever the number of streams.

Each ``ServiceMetrics.value`` is ``registry.get_sample_value``, which walks the whole
registry; the log line read ~14 of them per stream, on the event loop: 0.5 s at 16 streams
(the ``max_streams`` default), frames dropped at every line (a hostile run: 92 per line at 10
streams and a 5 s interval). Counted by registry walks, not timed.
"""

from __future__ import annotations

import re

from labeler_service.service.metrics import ServiceMetrics


def test_the_log_line_walks_the_registry_once_and_says_what_value_says(monkeypatch):
    m = ServiceMetrics()
    names = [f"s{i}" for i in range(16)]
    for k, n in enumerate(names):
        for _ in range(k + 1):
            m.frame_in(n)
            m.frame_out(n, 0.001, 0.002, 40, k, 2, 3)
        m.drop("queue_full", n)
    walks = []
    collect = m.registry.collect
    monkeypatch.setattr(m.registry, "collect", lambda: walks.append(1) or collect())
    snap = m.snapshot()
    assert len(walks) == 1
    line = m.log_line({n: ("online", 2) for n in names})
    assert len(walks) == 2
    monkeypatch.setattr(m.registry, "collect", collect)
    for k, n in enumerate(names):
        v = snap["streams"][n]
        assert v["frames_in"] == m.value("mocap_frames_in_total", stream=n) == k + 1
        assert v["recovered"] == m.value("mocap_markers_total", stream=n, state="recovered")
        assert v["recovered"] == k * (k + 1)
        assert v["unlabeled"] == 3 * (k + 1) and v["handovers"] == 0
        assert f"[{n}] in={k + 1} out={k + 1} " in line
    assert snap["drops"]["queue_full"] == 16


def test_a_stream_with_no_labeled_frame_logs_no_nan():
    """Frames in, none labeled (all dropped: no model yet): the line says ``-``, not nan."""
    m = ServiceMetrics()
    for _ in range(3):
        m.frame_in("plain")
        m.drop("no_model", "plain")
    line = m.log_line({"plain": ("idle", 0)})
    assert "[plain] in=3 out=0 label p50/p99=-/- ms latency p99=- ms" in line
    assert "nan" not in line


def test_each_stream_part_says_its_own_drops():
    """Two streams, drops on one: the other's part says none; the end says the service's."""
    m = ServiceMetrics()
    for n in ("quiet", "busy"):
        m.frame_in(n)
        m.frame_out(n, 0.001, 0.002, 40, 0, 2, 3)
    m.drop("queue_full", "busy", 3)
    m.drop("stale", "busy")
    m.drop("malformed", "")  # (a datagram that names no stream)
    line = m.log_line({"quiet": ("online", 0), "busy": ("online", 0)})
    head, _, _ = line.partition(" | service drops: ")
    part = dict(re.findall(r"\[(\w+)\] ([^[]*)", head))
    assert part["quiet"].rstrip().endswith(" drops=none"), line
    assert part["busy"].rstrip().endswith(" drops=queue_full:3,stale:1"), line
    assert line.endswith(" | service drops: malformed=1, queue_full=3, stale=1"), line
