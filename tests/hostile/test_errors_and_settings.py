"""Class 6 and 7 of issue 12: one line instead of a traceback; settings and secrets.

Every command given a broken input ends with ``error: <file>: <field> ...`` and exit 2; the
service checks what can fail (ports, model files) before its warm-up; unknown ``MOCAP_``
variables, MQTT wildcards in the topic prefix and stream names with a trailing newline are
rejected; a wildcard bind logs a warning; the replay tool never prints a password.
"""

from __future__ import annotations

import logging
import socket

import numpy as np
import pytest
from hostile.helpers import run, settings

from labeler_service.cli.main import main
from labeler_service.errors import ConfigError, ModelError, ProtocolError
from labeler_service.labeling.templates import load_model
from labeler_service.service.protocol import decode, encode_frame
from labeler_service.service.server import Server
from labeler_service.service.settings import exposure_warnings, load_settings
from labeler_service.service.transports.memory import MemoryTransport
from labeler_service.service.transports.url import parse_endpoint, redact_url


def _one_line_error(capsys, *must):
    err = capsys.readouterr().err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("error: ")
    for m in must:
        assert m in err
    return err


@pytest.mark.parametrize(
    "argv",
    [
        ["info", "{bad}"],
        ["label", "{bad}", "{out}"],
        ["replay", "{bad}", "--to", "udp://127.0.0.1:9", "--speed", "0"],
        ["train", "structure", "{bad}", "--out", "{out_json}"],
    ],
    ids=["info", "label", "replay", "train-structure"],
)
def test_a_non_utf8_c3d_label_is_one_line_naming_file_and_field(
    argv, bad_label_c3d, tmp_path, capsys
):
    fill = {"bad": str(bad_label_c3d), "out": str(tmp_path / "o.c3d"),
            "out_json": str(tmp_path / "m.json")}  # fmt: skip
    assert main([a.format(**fill) for a in argv]) == 2
    _one_line_error(capsys, "bad_label.c3d", "POINT:LABELS", "UTF-8")


def _nested(depth: int) -> bytes:
    return b"[" * depth + b"]" * depth


@pytest.mark.parametrize(
    ("content", "what"),
    [
        (b'{"version": 1, "rate": 100, "source": "\xff\xfe"}', "UTF-8"),
        (_nested(100_000), "nested"),
        (b'{"version": 1, "rate": 100, "subjects": ' + _nested(50_000) + b"}", "nested"),
    ],
    ids=["non-utf8", "deep-list", "deep-in-field"],
)
def test_a_broken_model_file_is_one_line_for_label_and_serve(
    content, what, tmp_path, ok_c3d, capsys
):
    bad = tmp_path / "bad_model.json"
    bad.write_bytes(content)
    with pytest.raises(ModelError, match="bad_model.json"):
        load_model(bad)
    assert main(["label", str(ok_c3d), str(tmp_path / "o.c3d"), "--model", str(bad)]) == 2
    _one_line_error(capsys, "bad_model.json")
    warmed = []

    def factory(*a, **k):
        warmed.append(1)
        raise AssertionError("the warm-up must not run with a broken model file")

    async def go():
        cfg = settings(streams=[{"name": "s", "model": str(bad)}], warmup=True)
        async with Server(cfg, [MemoryTransport()], factory=factory):
            pass

    with pytest.raises(ModelError, match="bad_model.json"):
        run(go())
    assert not warmed


def test_mocap_streams_with_bad_json_is_a_config_error(monkeypatch, capsys):
    monkeypatch.setenv("MOCAP_STREAMS", '[{"name": "a"')
    with pytest.raises(ConfigError, match="environment"):
        load_settings()
    assert main(["serve"]) == 2
    _one_line_error(capsys, "invalid service settings")


@pytest.mark.parametrize(
    ("var", "value", "field"),
    [
        ("MOCAP_STREAMS", '[{"name": "a"', "streams"),
        ("MOCAP_BOOT_CONFIG", "{bad", "boot_config"),
        ("MOCAP_UDP__PUBLISH_TO", "notalist", "udp"),
    ],
)
def test_bad_json_in_the_environment_names_the_variable(monkeypatch, var, value, field):
    # it said 'error parsing value for field "udp" from source "EnvSettingsSource"'
    monkeypatch.setenv(var, value)
    with pytest.raises(ConfigError) as err:
        load_settings()
    assert f"{var} (setting {field}): not valid JSON (" in str(err.value)


def test_unknown_mocap_variables_are_rejected_documented_ones_allowed(monkeypatch):
    monkeypatch.setenv("MOCAP_DATA_DIR", "/nowhere")
    monkeypatch.setenv("MOCAP_UDP__PORT", "9999")
    assert load_settings().udp.port == 9999
    monkeypatch.setenv("MOCAP_MAX_STREAM", "3")  # typo of MOCAP_MAX_STREAMS
    with pytest.raises(ConfigError, match="MOCAP_MAX_STREAM"):
        load_settings()


@pytest.mark.parametrize("prefix", ["mocap/+", "mocap/#", "+", "a//b", "/mocap", ""])
def test_topic_prefix_with_wildcards_is_rejected(prefix):
    with pytest.raises(ConfigError, match="topic_prefix"):
        load_settings(mqtt={"topic_prefix": prefix})


def test_stream_names_must_fully_match():
    with pytest.raises(ConfigError, match="stream name"):
        load_settings(streams=[{"name": "vol1\n"}])
    with pytest.raises(ProtocolError):
        decode(encode_frame("vol1\n", 0, 0.0, np.zeros((1, 3), np.float32)))
    with pytest.raises(ConfigError):
        parse_endpoint("udp://127.0.0.1:9870/vol1%0A")


def test_wildcard_binds_log_a_warning(caplog):
    cfg = settings(udp={"host": "0.0.0.0", "port": 0})
    lines = exposure_warnings(cfg)
    assert len(lines) == 1 and "not authenticated" in lines[0]
    assert len(exposure_warnings(settings(metrics_host="0.0.0.0", metrics_port=0))) == 1
    assert exposure_warnings(settings()) == []

    async def go():
        async with Server(cfg, [MemoryTransport()]):
            pass

    with caplog.at_level(logging.WARNING):
        run(go())
    assert any("every interface" in r.getMessage() for r in caplog.records)


def test_metrics_port_in_use_fails_before_the_warm_up():
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    port = busy.getsockname()[1]
    warmed = []

    def factory(*a, **k):
        warmed.append(1)
        raise AssertionError("warm-up ran before the port check")

    async def go():
        cfg = settings(metrics_port=port, warmup=True)
        async with Server(cfg, [MemoryTransport()], factory=factory):
            pass

    try:
        with pytest.raises(ConfigError, match=f"metrics_port.*{port}"):
            run(go())
    finally:
        busy.close()
    assert not warmed


def test_replay_never_prints_the_password(ok_c3d, capsys):
    url = "mqtt://user:s3cret@127.0.0.1:1/vol1"
    assert redact_url(url) == "mqtt://user:***@127.0.0.1:1/vol1"
    assert "s3cret" not in redact_url("mqtt://user:s3cret@host/x%0A")
    # a bad URL: the error shows it redacted
    rc = main(["replay", str(ok_c3d), "--to", "mqtt://user:s3cret@127.0.0.1:1/a/b"])
    out = capsys.readouterr()
    assert rc == 2
    assert "s3cret" not in out.out + out.err
    assert "user:***@" in out.err


def test_settings_file_nested_too_deeply_is_a_config_error(tmp_path):
    p = tmp_path / "deep.json"
    p.write_bytes(b'{"streams": ' + _nested(100_000) + b"}")
    with pytest.raises(ConfigError, match="deep.json"):
        load_settings(p)


def test_serve_metrics_port_in_use_exits_2(capsys, monkeypatch):
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen()
    try:
        monkeypatch.setenv("MOCAP_METRICS_PORT", str(busy.getsockname()[1]))
        monkeypatch.setenv("MOCAP_UDP__PORT", "0")
        assert main(["serve"]) == 2
    finally:
        busy.close()
    _one_line_error(capsys, "metrics_port")
