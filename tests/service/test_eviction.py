"""Slots of streams not in the settings under a flood of names: a stream that shows sequential
progress keeps its slot; names that appear with one or two packets, or the many names of one
sender, are evicted first (or refused); stream churn logs are rate-limited, counted exactly."""

from __future__ import annotations

import asyncio
import logging
import socket
import time

import numpy as np
from service.helpers import moving_clusters, run, stream_payloads

from labeler_service.service.protocol import encode_frame
from labeler_service.service.server import Server
from labeler_service.service.settings import load_settings
from labeler_service.service.transports.memory import MemoryTransport


def _settings(**over):
    base = {"labeler": "baseline", "metrics_port": None, "warmup": False, "queue_size": 4096}
    base.update(over)
    return load_settings(**base)


def _junk(name: str, seq: int, n: int = 8) -> bytes:
    pts = np.full((n, 3), 100.0, np.float32)
    return encode_frame(name, seq, seq / 100, pts, [f"S:M{i}" for i in range(n)])


def test_a_stream_making_progress_is_not_evicted_by_one_packet_names():
    async def go():
        mem = MemoryTransport()
        async with Server(_settings(max_streams=3, streams=[]), [mem]) as srv:
            for seq in range(4):  # "real" shows sequential progress in its start-up window
                mem.inject(_junk("real", seq), reply_to=("10.0.0.1", 1))
            await asyncio.sleep(0.05)
            for k in range(50):  # one labeled packet per name, each from its own sender
                mem.inject(_junk(f"j{k}", 0), reply_to=("10.0.0.2", 1000 + k))
            await asyncio.sleep(0.1)
            return sorted(srv.streams), srv.metrics.value("mocap_streams_expired_total")

    streams, expired = run(go())
    assert "real" in streams and len(streams) == 3
    assert expired == 50 - 2  # the one-packet names evicted each other, exactly counted


def test_one_senders_many_names_give_way_to_another_sender_and_are_refused_more():
    async def go():
        mem = MemoryTransport()
        flood = ("10.0.0.9", 5)
        async with Server(_settings(max_streams=4, streams=[]), [mem]) as srv:
            for seq in range(5):  # four names of one sender with progress fill the table
                for k in range(4):
                    mem.inject(_junk(f"f{k}", seq), reply_to=flood)
            await asyncio.sleep(0.05)
            mem.inject(_junk("legit", 0), reply_to=("10.0.0.1", 7))  # takes one of theirs
            await asyncio.sleep(0.05)
            after_legit = sorted(srv.streams)
            for seq in range(5, 40):  # the flooder's other names are refused, legit stays
                for k in range(10):
                    mem.inject(_junk(f"f{k}", seq), reply_to=flood)
                mem.inject(_junk("legit", seq - 4), reply_to=("10.0.0.1", 7))
            await asyncio.sleep(0.1)
            return after_legit, sorted(srv.streams), srv.streams["legit"].progress

    after_legit, streams, progress = run(go())
    assert "legit" in after_legit and len(after_legit) == 4
    assert "legit" in streams and len(streams) == 4
    assert progress == 36  # never evicted: its progress was never reset


def test_udp_flood_of_labeled_names_does_not_starve_a_new_stream(caplog):
    """flood.py of the hostile review, bounded: 40 labeled names from one socket with random
    datagrams, beside a real stream starting from labeled init frames from another socket."""
    cap = moving_clusters(np.random.default_rng(3), subjects=2, markers=6, frames=200)
    legit = stream_payloads(cap, np.random.default_rng(4), 20, stream="legit")
    cfg = _settings(udp={"port": 0}, streams=[], stream_idle_s=60.0)
    rng = np.random.default_rng(5)

    async def go():
        async with Server(cfg) as srv:
            udp = srv.transports[0]
            flood = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            real = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            for seq in range(5):  # the flooder first holds every slot
                for k in range(40):
                    flood.sendto(_junk(f"squat{k}", seq), udp.address)
            await asyncio.sleep(0.05)
            for i, p in enumerate(legit):
                for k in range(40):
                    flood.sendto(_junk(f"squat{k}", 5 + i), udp.address)
                for _ in range(10):
                    flood.sendto(rng.bytes(1400), udp.address)
                real.sendto(p, udp.address)
                await asyncio.sleep(0.002)
            flood.close()
            real.close()
            deadline = time.monotonic() + 20
            out = 0
            while time.monotonic() < deadline:
                out = srv.metrics.snapshot()["streams"].get("legit", {}).get("frames_out", 0)
                if out >= len(legit) - 20 - 5:
                    break
                await asyncio.sleep(0.05)
            return out, len(srv.streams), srv.metrics.value("mocap_streams_expired_total")

    with caplog.at_level(logging.INFO, logger="labeler_service.service.server"):
        out, n_streams, expired = run(go())
    assert out > (len(legit) - 20) // 2  # labeled frames (a few may go to rx_overflow)
    assert n_streams <= 16
    churn = [r for r in caplog.records if "removed (idle or evicted)" in r.getMessage()]
    assert len(churn) <= 2 and len(churn) <= max(expired, 1)  # rate-limited, not per stream


def test_a_removed_streams_background_jobs_are_cancelled():
    """Its queued boot (and handover) leave the background queue with it: expired streams'
    boots ran their whole budget one after another, long after their senders stopped."""

    async def go():
        mem = MemoryTransport()
        async with Server(_settings(streams=[]), [mem]) as srv:
            for seq in range(4):
                mem.inject(_junk("gone", seq), reply_to=("10.0.0.1", 1))
            await asyncio.sleep(0.05)
            assert "gone" in srv.streams
            boot = srv._spawn(asyncio.sleep(60), "boot-gone")
            other = srv._spawn(asyncio.sleep(60), "boot-other")
            srv._remove_stream("gone")
            await asyncio.sleep(0.01)
            cancelled = boot.cancelled(), other.cancelled()
            other.cancel()
            return cancelled

    assert run(go()) == (True, False)
