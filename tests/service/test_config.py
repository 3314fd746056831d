"""Settings: file + MOCAP_ environment precedence, and clear errors."""

from __future__ import annotations

import json
import os

import pytest

from labeler_service.errors import ConfigError
from labeler_service.service.settings import load_settings


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    """No ``MOCAP_`` variables from the caller's environment (they beat files and overrides)."""
    for k in list(os.environ):
        if k.startswith("MOCAP_"):
            monkeypatch.delenv(k)


def test_defaults_bind_udp_to_loopback_and_use_the_online_labeler():
    s = load_settings()
    assert s.udp.host == "127.0.0.1" and s.udp.enabled and not s.mqtt.enabled
    assert s.labeler == "online"
    assert [x.name for x in s.streams] == ["default"]


def test_environment_overrides_the_file(tmp_path, monkeypatch):
    f = tmp_path / "s.toml"
    f.write_text('queue_size = 8\n[udp]\nport = 1111\n[mqtt]\nhost = "broker"\n'
                 '[[streams]]\nname = "vol1"\nrate = 240\n')  # fmt: skip
    monkeypatch.setenv("MOCAP_UDP__PORT", "2222")
    monkeypatch.setenv("MOCAP_MQTT__ENABLED", "true")
    s = load_settings(f)
    assert s.udp.port == 2222 and s.mqtt.enabled and s.mqtt.host == "broker"
    assert s.queue_size == 8 and s.streams[0].name == "vol1" and s.streams[0].rate == 240


def test_json_file_and_labeler_config_embedding(tmp_path):
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"labeler_config": {"K": 3}, "labeler": "baseline"}))
    s = load_settings(f)
    assert s.labeler_config.K == 3 and s.labeler == "baseline"


@pytest.mark.parametrize(
    ("overrides", "needle"),
    [
        ({"queue_size": 0}, "queue_size"),
        ({"udp": {"port": 70000}}, "udp.port"),
        ({"udp": {"publish_to": ["nohost"]}}, "host:port"),
        ({"streams": [{"name": "a/b"}]}, "streams.0.name"),
        ({"streams": [{"name": "a"}, {"name": "a"}]}, "repeated: a"),
        ({"streams": [{"name": "a", "model": "/nonexistent.json"}]}, "does not exist"),
        ({"labeler": "magic"}, "labeler"),
        ({"labeler_config": {"K": 0}}, "labeler_config.K"),
        ({"mqtt": {"ca_file": "/nonexistent.pem"}}, "mqtt.ca_file"),
        ({"bogus": 1}, "bogus"),
        # a rate of 0 or NaN said as the README promises (pydantic's "greater than 0" before)
        ({"streams": [{"name": "a", "rate": 0}]}, "rate is 0 Hz: expected 1 to 10000 Hz"),
        ({"streams": [{"name": "a", "rate": float("nan")}]}, "rate is nan Hz: expected 1 to"),
        ({"streams": [{"name": "a", "rate": 1e7}]}, "rate is 1e+07 Hz: expected 1 to"),
    ],
)
def test_invalid_settings_raise_config_error_naming_the_field(overrides, needle):
    with pytest.raises(ConfigError, match="invalid service settings") as info:
        load_settings(**overrides)
    assert needle in str(info.value)


def test_unreadable_files_raise_config_error(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_settings(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="is a folder"):  # (it said "does not exist")
        load_settings(tmp_path)
    bad = tmp_path / "bad.toml"
    bad.write_text("[udp\n")
    with pytest.raises(ConfigError, match="cannot be parsed"):
        load_settings(bad)
    other = tmp_path / "s.yaml"
    other.write_text("a: 1")
    with pytest.raises(ConfigError, match="use .toml or .json"):
        load_settings(other)


def test_the_docker_example_settings_are_valid():
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "docker" / "service.toml"
    s = load_settings(path)
    assert s.mqtt.enabled and s.mqtt.host == "mosquitto" and s.udp.host == "0.0.0.0"
    assert [x.name for x in s.streams] == ["volume1"]


def test_a_service_setting_written_under_streams_says_where_it_belongs(tmp_path):
    # TOML: `boot = true` below [[streams]] lands in the stream's table, not the service's
    model = tmp_path / "m.json"
    model.write_text("{}")
    cfg = tmp_path / "s.toml"
    cfg.write_text(f'[[streams]]\nname = "v"\nmodel = "{model}"\nboot = true\nnot_a_key = 1\n')
    with pytest.raises(ConfigError) as err:
        load_settings(cfg)
    text = str(err.value)
    assert "streams.0.boot: not a setting (boot is a setting of the whole " in text
    assert "above the first [[streams]]" in text
    # a key that is no setting at all gets no such hint
    line = next(x for x in text.splitlines() if "not_a_key" in x)
    assert "whole service" not in line


def test_a_service_setting_written_under_a_section_says_where_it_belongs(tmp_path):
    # TOML: `labeler = ...` below [udp] lands in the udp table: "udp.labeler: not a setting"
    cfg = tmp_path / "s.toml"
    cfg.write_text(
        '[udp]\nport = 9870\nlabeler = "online"\n[mqtt]\nenabled = false\nstreams = []\n'
    )
    with pytest.raises(ConfigError) as err:
        load_settings(cfg)
    text = str(err.value)
    assert (
        "udp.labeler: not a setting (labeler is a setting of the whole service, not of [udp]"
        in text
    )
    assert "mqtt.streams: not a setting (streams is a setting of the whole service" in text
    assert "above the first [section]" in text


def test_an_invalid_value_from_the_environment_names_its_variable(tmp_path, monkeypatch):
    """The environment wins over the file, so an error in a value it set names the variable,
    not only the file (``MOCAP_STREAMS__0__LABELED_START=model`` read as 'streams: Input should
    be a valid list' "in s.toml"); a nested variable into the list says how to set a list."""
    f = tmp_path / "s.toml"
    f.write_text('[udp]\nhost = 5\n[[streams]]\nname = "v"\n')
    monkeypatch.setenv("MOCAP_UDP__PORT", "2222")
    monkeypatch.setenv("MOCAP_STREAMS__0__LABELED_START", "model")
    with pytest.raises(ConfigError) as err:
        load_settings(f)
    lines = str(err.value).splitlines()
    streams = next(x for x in lines if x.strip().startswith("streams:"))
    assert "(from the environment: MOCAP_STREAMS__0__LABELED_START)" in streams
    assert "MOCAP_STREAMS='[{" in streams
    # the file's bad udp.host is not blamed on MOCAP_UDP__PORT, which set another field
    host = next(x for x in lines if x.strip().startswith("udp.host:"))
    assert "environment" not in host
    monkeypatch.delenv("MOCAP_STREAMS__0__LABELED_START")
    monkeypatch.setenv("MOCAP_STREAMS", '[{"name": "v", "labeled_start": "window"}]')
    with pytest.raises(
        ConfigError, match=r"labeled_start: .*\(from the environment: MOCAP_STREAMS\)"
    ):
        load_settings(f)


def test_a_stream_setting_as_a_top_level_variable_points_to_mocap_streams(monkeypatch):
    monkeypatch.setenv("MOCAP_LABELED_START", "model")
    with pytest.raises(
        ConfigError,
        match=r"MOCAP_LABELED_START \(labeled_start is a setting of one stream: .*MOCAP_STREAMS",
    ):
        load_settings()


def test_our_validators_messages_come_without_pydantics_prefix():
    """A validator's own sentence is the message ('Value error, ' was pydantic's prefix)."""
    with pytest.raises(ConfigError) as err:
        load_settings(labeler="baseline", streams=[{"name": "v", "labeled_start": "model"}])
    assert "  (settings): streams v: labeled_start = 'model' runs" in str(err.value)
    assert "Value error" not in str(err.value)


def test_a_misspelt_key_names_the_key_it_is_close_to(tmp_path):
    """A typo in a file's key, at the top or in a table, says which key was meant ('Extra
    inputs are not permitted' named no fix)."""
    path = tmp_path / "s.toml"
    path.write_text(
        "queue_sise = 8\n[udp]\nprot = 9870\n[boot_config]\nwindow_ss = 1\n"
        '[[streams]]\nname = "v"\nmodle = "m.json"\n'
    )
    with pytest.raises(ConfigError) as err:
        load_settings(path)
    text = str(err.value)
    assert "  queue_sise: not a setting (did you mean queue_size?)" in text
    assert "  udp.prot: not a setting (did you mean port?)" in text
    assert "  boot_config.window_ss: not a setting (did you mean window_s?)" in text
    assert "  streams.0.modle: not a setting (did you mean model?)" in text
    assert "Extra inputs" not in text


def test_a_misspelt_or_flat_variable_says_what_was_meant(monkeypatch):
    """``MOCAP_QUEUE_SISE`` names ``MOCAP_QUEUE_SIZE``; ``MOCAP_UDP_PORT`` (one underscore)
    and ``MOCAP_BOOT_CONFIG_WINDOW_S`` show the ``__`` spelling of the nested key."""
    monkeypatch.setenv("MOCAP_QUEUE_SISE", "8")
    monkeypatch.setenv("MOCAP_UDP_PORT", "9871")
    monkeypatch.setenv("MOCAP_BOOT_CONFIG_WINDOW_S", "1")
    with pytest.raises(ConfigError) as err:
        load_settings()
    text = str(err.value)
    assert "MOCAP_QUEUE_SISE (did you mean MOCAP_QUEUE_SIZE?)" in text
    assert "MOCAP_UDP_PORT (nested keys are joined with '__': MOCAP_UDP__PORT)" in text
    assert "(nested keys are joined with '__': MOCAP_BOOT_CONFIG__WINDOW_S)" in text


def test_relative_paths_in_a_settings_file_are_read_from_its_folder(tmp_path, monkeypatch):
    """``model = "../models/m.json"`` beside the config: read from the config's folder, not
    the service's working folder (it "did not exist" when the service ran elsewhere)."""
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "m.json").write_text("{}")
    conf = tmp_path / "conf"
    conf.mkdir()
    path = conf / "s.toml"
    path.write_text('[[streams]]\nname = "v"\nmodel = "../models/m.json"\n')
    elsewhere = tmp_path / "run"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    s = load_settings(path)
    assert s.streams[0].model is not None
    assert s.streams[0].model.resolve() == (tmp_path / "models" / "m.json").resolve()
    absolute = conf / "abs.toml"
    absolute.write_text(f'[[streams]]\nname = "v"\nmodel = "{tmp_path / "models" / "m.json"}"\n')
    assert load_settings(absolute).streams[0].model == tmp_path / "models" / "m.json"
    # JSON alike; a MOCAP_ variable's path stays relative to the working folder
    as_json = conf / "s.json"
    as_json.write_text(json.dumps({"streams": [{"name": "v", "model": "../models/m.json"}]}))
    assert load_settings(as_json).streams[0].model.resolve() == s.streams[0].model.resolve()
    (elsewhere / "m.json").write_text("{}")
    monkeypatch.setenv("MOCAP_STREAMS", json.dumps([{"name": "v", "model": "m.json"}]))
    assert load_settings().streams[0].model.resolve() == (elsewhere / "m.json").resolve()
    monkeypatch.delenv("MOCAP_STREAMS")
    # ~ is the user's home
    monkeypatch.setenv("HOME", str(tmp_path))
    home = conf / "home.toml"
    home.write_text('[[streams]]\nname = "v"\nmodel = "~/models/m.json"\n')
    assert load_settings(home).streams[0].model == tmp_path / "models" / "m.json"
    folder = conf / "dir.toml"
    folder.write_text('[[streams]]\nname = "v"\nmodel = "../models"\n')
    with pytest.raises(ConfigError, match="is a folder, not a model file"):
        load_settings(folder)


def test_boot_with_the_baseline_labeler_is_refused():
    """``labeler = "baseline"`` and ``boot = true``: the baseline has no subject templates, so
    a model stream without labels started, said ``ready`` and "re-booting from the model",
    and labeled nothing (a hostile run). Refused at load, saying what to set."""
    with pytest.raises(ConfigError, match=r"boot = true boots .*labeler is 'baseline'"):
        load_settings(labeler="baseline", boot=True)
    assert load_settings(labeler="baseline", boot=False).boot is False
