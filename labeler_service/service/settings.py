"""Service settings: a TOML/JSON file, overridden by ``MOCAP_`` environment variables.

Precedence, highest first: environment (``MOCAP_UDP__PORT=9999``, nested fields joined with
``__``), the file given to ``serve --config``, then the defaults below. Everything is validated
once at start-up; an invalid value raises :class:`~labeler_service.errors.ConfigError` naming the
field and the problem (the CLI prints it and exits 2).

Example (``docker/service.toml`` is a short one; docs/service.md lists every key)::

    queue_size = 64
    [udp]
    host = "127.0.0.1"
    port = 9870
    [mqtt]
    enabled = true
    host = "mosquitto"
    [[streams]]
    name = "volume1"
    model = "models/volume1.json"  # else: trained from labeled init frames in the stream
"""

from __future__ import annotations

import difflib
import json
import os
import re
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from labeler_service.capture.model import rate_problem
from labeler_service.errors import ConfigError
from labeler_service.labeling.boot_config import WINDOW_RELEARN_S, BootConfig
from labeler_service.labeling.config import LabelerConfig
from labeler_service.service.protocol import STREAM_NAME

#: Largest UDP payload over IPv4 (65 535 - 8 UDP header - 20 IP header).
UDP_MAX_PAYLOAD = 65_507


#: ``MOCAP_`` environment variables that are not service settings (read elsewhere); any other
#: ``MOCAP_`` name must be a settings field, else it is a typo and an error.
NON_SETTING_ENV = frozenset({"MOCAP_DATA_DIR", "MOCAP_MAX_NPZ_BYTES"})

#: Hosts that listen on every interface (a warning at start-up: UDP has no authentication).
WILDCARD_HOSTS = frozenset({"0.0.0.0", "::", "", "*"})


def check_stream_name(name: str) -> str:
    """Stream names become MQTT topic levels: letters, digits, ``_ . -``; 1-64 characters."""
    if not isinstance(name, str) or not STREAM_NAME.fullmatch(name):
        raise ValueError(
            f"stream name {name!r} must be 1-64 characters of letters, digits, '_', '.', '-'"
        )
    return name


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class UdpSettings(_Section):
    """Loopback by default; bind ``0.0.0.0`` deliberately to listen on the network."""

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = Field(9870, ge=0, le=65535)
    #: Fixed destinations (``host:port``) that receive every labeled/model/status datagram,
    #: in addition to subscribers that registered with a ``subscribe`` datagram.
    publish_to: list[str] = Field(default_factory=list)
    #: A registered subscriber that has not renewed within this many seconds is dropped.
    subscriber_ttl_s: float = Field(5.0, gt=0)
    max_subscribers: int = Field(64, ge=1)
    #: Confirmed subscribers per source host (IP) at most (``subscribe_host_limit``). 16: on one
    #: machine every client shares the loopback address, and 4 refused the fifth (a viewer, a
    #: demo and three subscribers); 4 hosts still cannot take all of ``max_subscribers``' 64.
    max_subscribers_per_host: int = Field(16, ge=1)
    #: Kernel receive/send buffer sizes requested. Linux caps them at net.core.rmem_max /
    #: wmem_max unless the process has CAP_NET_ADMIN (then SO_RCVBUFFORCE is used); a clamped
    #: buffer is logged at start-up and the granted size is the gauge
    #: ``mocap_udp_receive_buffer_bytes``. 16 MiB holds a burst of ~2,000 datagrams of 5 kB.
    socket_buffer_bytes: int = Field(16 * 1024 * 1024, ge=65536)

    @field_validator("publish_to")
    @classmethod
    def _check_destinations(cls, v: list[str]) -> list[str]:
        for dest in v:
            host, sep, port = dest.rpartition(":")
            if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise ValueError(f"destination {dest!r} must be host:port")
        return v


class MqttSettings(_Section):
    """Broker connection; one client per configured stream (each with its own last will)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(1883, ge=1, le=65535)
    username: str | None = None
    password: SecretStr | None = None
    tls: bool = False
    ca_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None
    tls_insecure: bool = False
    keepalive_s: int = Field(10, ge=2, le=3600)
    client_id_prefix: str = "mocap-labeler"
    topic_prefix: str = "mocap"
    #: Re-publish our retained model/status when the broker holds a different one (another
    #: client published it): the service subscribes to its own retained topics.
    reassert_retained: bool = True
    #: Reconnect backoff: starts at ``reconnect_min_s``, doubles, capped at ``reconnect_max_s``.
    reconnect_min_s: float = Field(0.2, gt=0)
    reconnect_max_s: float = Field(2.0, gt=0)

    @field_validator("topic_prefix")
    @classmethod
    def _check_prefix(cls, v: str) -> str:
        if not v or any(c in v for c in "+#\0") or v.startswith("/") or v.endswith("/"):
            raise ValueError(
                f"topic prefix {v!r} must be a non-empty topic without MQTT wildcards (+ #), "
                "NUL or a leading/trailing '/'"
            )
        if any(not level for level in v.split("/")):
            raise ValueError(f"topic prefix {v!r} has an empty level ('//')")
        return v

    @field_validator("ca_file", "cert_file", "key_file")
    @classmethod
    def _file_exists(cls, v: Path | None) -> Path | None:
        v = None if v is None else Path(v).expanduser()
        if v is not None and not Path(v).is_file():
            raise ValueError(f"file {v} does not exist")
        return v


class StreamSettings(_Section):
    """One capture volume. Start-up: from ``model`` when given, else from labeled init frames."""

    name: str = "default"
    #: Subject model file (``train structure`` output). None: train from labeled init frames.
    model: Path | None = None
    #: Capture rate in Hz. None: estimated from the init frames' times (model: its rate).
    rate: float | None = None  # (checked by _plausible_rate: 0 and NaN said as such)
    #: How a start from labeled init frames runs (no ``model``): ``labeler`` trains the online
    #: labeler in place; ``model`` trains subject templates on the init window (as ``train
    #: structure`` does) and runs the booting labeler from them, fed the window's labels,
    #: which re-finds markers the labeler loses at low rates (``evaluate --labeled-start
    #: model``; docs/service.md "The labeled start through a window model"); ``auto``:
    #: ``model`` where it applies (the online labeler, 3 or more init frames, subject:marker
    #: labels), else ``labeler`` (logged). The window start trains the plain labeler first and
    #: hands over to the window labeler once it is trained and caught up off the loop
    #: (``service/handover.py``). The default is ``labeler``, unlike ``evaluate``'s ``auto``:
    #: on a loaded machine the window labeler still costs latency (docs/service.md).
    labeled_start: Literal["auto", "labeler", "model"] = "labeler"
    #: The window start's booter learns again from the stream this often (s; 0 = never), as
    #: ``evaluate`` does (``BootConfig.relearn_every_s``): a performer who left is read again
    #: with what the stream showed of him. Its Python shares the process with the frame path
    #: (labeling p99 1 -> 3 ms for three performers at 120 Hz; docs/service.md).
    relearn_every_s: float = Field(WINDOW_RELEARN_S, ge=0, allow_inf_nan=False)

    @field_validator("name")
    @classmethod
    def _check_name(cls, v: str) -> str:
        return check_stream_name(v)

    @field_validator("rate")
    @classmethod
    def _plausible_rate(cls, v: float | None) -> float | None:
        why = None if v is None else rate_problem(v)  # (inf and 1e7 passed gt=0)
        if why is not None:
            raise ValueError(f"rate {why}")
        return v

    @field_validator("model")
    @classmethod
    def _model_exists(cls, v: Path | None) -> Path | None:
        v = None if v is None else Path(v).expanduser()  # (a MOCAP_ variable's ~ too)
        if v is not None and Path(v).is_dir():
            raise ValueError(f"model {v} is a folder, not a model file (train structure's JSON)")
        if v is not None and not Path(v).is_file():
            raise ValueError(f"model file {v} does not exist")
        return v

    @model_validator(mode="after")
    def _start(self) -> StreamSettings:
        if self.labeled_start == "model" and self.model is not None:
            raise ValueError(
                f"stream {self.name}: labeled_start = 'model' trains its model on the labeled "
                "init frames; a stream with a model file starts from that model: drop one "
                "of model and labeled_start on this stream"
            )
        return self


class ServiceSettings(BaseSettings):
    """Everything ``serve`` needs. See the module docstring for sources and precedence."""

    model_config = SettingsConfigDict(
        env_prefix="MOCAP_", env_nested_delimiter="__", extra="forbid", case_sensitive=False
    )

    udp: UdpSettings = Field(default_factory=UdpSettings)
    mqtt: MqttSettings = Field(default_factory=MqttSettings)
    streams: list[StreamSettings] = Field(default_factory=lambda: [StreamSettings()])
    #: Accept frames for streams not listed above (UDP; they start from labeled init frames).
    allow_new_streams: bool = True
    max_streams: int = Field(16, ge=1)
    #: Labeler: ``online`` (seed 003 Algorithm 1) or ``baseline`` (closest point).
    labeler: Literal["online", "baseline"] = "online"
    #: The online labeler's tunables (``labeler_service.labeling.config.LabelerConfig``).
    labeler_config: LabelerConfig = Field(default_factory=LabelerConfig)
    #: Init frames buffered at most while waiting for the first unlabeled frame.
    max_init_frames: int = Field(2000, ge=1)
    #: Bytes of init frames (points + labels) buffered at most per stream (``init_overflow``).
    max_init_bytes: int = Field(8 * 1024 * 1024, ge=1024)
    #: Distinct marker labels a stream may define in its init frames (``marker_cap``).
    max_markers: int = Field(1000, ge=1)
    #: Distinct markers one subject (the label's part before ``:``) may have (``marker_cap``).
    #: Training keeps pair matrices per subject, so its time and memory grow with the square
    #: of a subject's markers: this bounds them by ``max_markers x max_markers_per_subject``
    #: (a 1,000-marker subject took 10-60 s and ~300 MB; a body suit has 40-150 markers).
    max_markers_per_subject: int = Field(256, ge=3)
    #: Seconds in-stream training may take (off the event loop); over it the stream reports
    #: ``training_failed`` and waits for new labeled init frames.
    train_budget_s: float = Field(60.0, gt=0)
    #: True: a stream with a ``model`` boots its subjects from anonymous points (no labeled
    #: frame needed; docs/service.md "Starting from a model"). False (default): its first
    #: frame must carry labels (the initial assignment). Off by default because the booting
    #: labeler's tracking and extension attempts cost a labeled stream too (10 x 360 Hz: UDP
    #: p99 1.2 -> 17 ms) and boot is not yet reliable in close contact (BENCHMARKS.md).
    boot: bool = False
    #: Seconds one boot attempt may take off the event loop (the background mechanism that
    #: trains in-stream); over it the attempt is abandoned (``boot_failed``), the next one
    #: waits longer (the boot's back-off). 10 performers at 360 Hz take ~1.4 s alone and
    #: over 2 s beside the live stream (the boot shares the GIL with it), hence 10 s.
    boot_budget_s: float = Field(10.0, gt=0)
    #: Where a boot attempt's step runs: ``process`` (default: one worker process,
    #: ``service/boot_worker.py``; the attempt's Python no longer holds the frame path's GIL)
    #: or ``thread`` (a background thread of the service, as before; no extra process).
    boot_worker: Literal["process", "thread"] = "process"
    #: Helper processes of that worker (0 or 1): with 1 the worker and its helper share an
    #: attempt's per-subject hypotheses (the same labels as alone). Alone on a quiet 2-core
    #: machine a 10-performer attempt took ~0.39 s instead of ~0.63 s, but beside a 10 x 360 Hz
    #: stream on the same 2 cores it gained nothing, and on a machine loaded by other jobs it was
    #: slower (BENCHMARKS.md): worth 1 where cores are free while a stream runs.
    boot_helpers: int = Field(0, ge=0, le=1)
    #: Where the window start's handover trains its window model (``labeled_start``):
    #: ``process`` (default: a ``spawn`` child per handover, which costs its imports, a few
    #: seconds, but holds none of the frame path's GIL) or ``thread`` (the handover's job).
    window_worker: Literal["process", "thread"] = "process"
    #: The boot's tunables (``labeler_service.labeling.boot_config.BootConfig``).
    boot_config: BootConfig = Field(default_factory=BootConfig)
    #: Restart rule (docs/service.md): a seq step beyond this, forward or back, is a jump.
    max_seq_step: int = Field(100, ge=1)
    #: A t step of 0, negative or beyond this many seconds is a jump.
    max_time_step_s: float = Field(1.0, gt=0)
    #: Consecutive frames that must continue a jump before it is adopted as a new run.
    run_confirm_frames: int = Field(3, ge=1, le=100)
    #: A frame this many seconds of stream after the last one labeled (frames the service
    #: dropped meanwhile: a training stall, a busy machine) starts a recovery: the performers
    #: moved where the tracks cannot follow, so they are booted from the stream's model
    #: (0 = off).
    recover_gap_s: float = Field(0.25, ge=0)
    #: A stream not listed in ``streams`` that received nothing for this long is removed
    #: (its trained labeler is kept in a small cache so it resumes without labels).
    stream_idle_s: float = Field(60.0, gt=0)
    #: Trained labelers of removed streams kept (least recently used evicted first).
    stream_cache_size: int = Field(4, ge=0, le=64)
    #: Stream health: labeled fraction (observed markers / model markers, an exponential
    #: average with the time constant ``health_window_s``) below which the status is
    #: ``degraded`` / ``lost``.
    degraded_below: float = Field(0.5, ge=0, le=1)
    lost_below: float = Field(0.1, ge=0, le=1)
    health_window_s: float = Field(1.0, gt=0)
    #: A stream that has had frames and gets none for this long (or three of its usual gaps
    #: between frames, when longer) reads ``idle`` (its labeler kept; the next frame gives the
    #: status back).
    silent_after_s: float = Field(1.0, gt=0)
    #: A frame published this long after it arrived says the stream is falling behind: a
    #: rate-limited warning names its labeling time, points and queue (drops, when the queue
    #: is full, are counted as ``queue_full`` as before; this is said before any is).
    behind_warn_s: float = Field(0.25, gt=0)
    #: Input validation caps (checked once, at decode).
    max_points: int = Field(2000, ge=1)
    max_message_bytes: int = Field(UDP_MAX_PAYLOAD, ge=64)
    #: Per-stream frame queue; when full the oldest frame is dropped (counted).
    queue_size: int = Field(32, ge=1)
    #: Model message repeat period (UDP; MQTT keeps it retained too).
    model_repeat_s: float = Field(1.0, gt=0, le=1.0)
    #: Prometheus text endpoint; port 0 picks a free one, None disables it.
    metrics_host: str = "127.0.0.1"
    metrics_port: int | None = Field(9108, ge=0, le=65535)
    log_interval_s: float = Field(10.0, gt=0)
    #: Run every kernel on a synthetic frame before reporting ready.
    warmup: bool = True
    #: Label in one worker thread per stream (numba kernels release the GIL). Measured slower
    #: on 2 cores (GIL hand-offs between the loop and the labeling thread; docs/service.md),
    #: so off by default: labeling runs inline on the event loop.
    labeling_thread: bool = False

    @field_validator("streams")
    @classmethod
    def _unique_streams(cls, v: list[StreamSettings]) -> list[StreamSettings]:
        names = [s.name for s in v]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"stream names must be unique, repeated: {', '.join(dupes)}")
        return v

    @field_validator("lost_below")
    @classmethod
    def _health_order(cls, v: float, info) -> float:
        degraded = info.data.get("degraded_below")
        if degraded is not None and v > degraded:
            raise ValueError(f"lost_below ({v}) must not exceed degraded_below ({degraded})")
        return v

    @model_validator(mode="after")
    def _model_start_is_online(self) -> ServiceSettings:
        model = [s.name for s in self.streams if s.labeled_start == "model"]
        if model and self.labeler != "online":
            raise ValueError(
                f"streams {', '.join(model)}: labeled_start = 'model' runs the online labeler's "
                f"booting labeler; labeler is {self.labeler!r}: set labeler = 'online', or "
                "labeled_start = 'labeler' on these streams"
            )
        if self.boot and self.labeler != "online":
            # (a baseline stream with a model and no labels started, said `ready` and
            # "re-booting from the model", and labeled nothing: the baseline has no templates)
            raise ValueError(
                f"boot = true boots performers from the online labeler's subject templates; "
                f"labeler is {self.labeler!r}: set labeler = 'online', or boot = false (the "
                "baseline then starts from labeled frames)"
            )
        return self

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # environment beats the file (passed as init kwargs), which beats the defaults
        return env_settings, init_settings


#: The settings tables below the top level, by key (``streams``: each stream's table).
_TABLES: dict[str, type[BaseModel]] = {
    "udp": UdpSettings,
    "mqtt": MqttSettings,
    "streams": StreamSettings,
    "boot_config": BootConfig,
    "labeler_config": LabelerConfig,
}


def _section_keys(loc: tuple[Any, ...]) -> list[str]:
    """The keys allowed in the table that holds ``loc`` (list indices skipped: ``streams.0``
    is a stream's table); empty when ``loc`` is in no table this module knows."""
    parent = tuple(str(p) for p in loc[:-1] if not isinstance(p, int))
    model = ServiceSettings if not parent else _TABLES.get(parent[0]) if len(parent) == 1 else None
    return [] if model is None else list(model.model_fields)


def _did_you_mean(name: str, known: list[str], prefix: str = "") -> str:
    """`` (did you mean X?)`` for a name a typo or two from a known key (``prefix`` + the key:
    ``MOCAP_`` for a variable), else ``""``."""
    close = difflib.get_close_matches(name.lower(), known, n=1, cutoff=0.75)
    return f" (did you mean {prefix}{close[0].upper() if prefix else close[0]}?)" if close else ""


def _env_names(loc: tuple[Any, ...], environ: Any) -> list[str]:
    """The ``MOCAP_`` variables that set the value at ``loc`` of a validation error: the value
    itself, one that holds it (``MOCAP_STREAMS`` for ``streams.0.rate``) or a part of it
    (``MOCAP_STREAMS__0__RATE`` for ``streams``)."""
    path = ["MOCAP_" + "__".join(str(p) for p in loc[:i]).upper() for i in range(1, len(loc) + 1)]
    return sorted(
        k for k in environ if k.upper() in path or (path and k.upper().startswith(path[-1] + "__"))
    )


def _format_errors(exc: ValidationError, environ: Any = None) -> str:
    env = os.environ if environ is None else environ
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(settings)"
        msg = err["msg"]
        if err["type"] == "value_error":
            msg = msg.removeprefix("Value error, ")  # our validators' messages say it all
        key = str(err["loc"][-1]) if err["loc"] else ""
        if err["type"] == "extra_forbidden":
            msg = "not a setting"  # pydantic's "Extra inputs are not permitted"
        if (
            err["type"] == "extra_forbidden"
            and len(err["loc"]) == 3
            and err["loc"][0] == "streams"
            and key in ServiceSettings.model_fields
        ):
            # TOML: a key written below [[streams]] belongs to that stream's table
            msg += (
                f" ({key} is a setting of the whole service, not of one stream: in TOML, "
                "write it above the first [[streams]] or [section])"
            )
        elif (
            err["type"] == "extra_forbidden"
            and len(err["loc"]) == 1
            and key in StreamSettings.model_fields
            and key not in ServiceSettings.model_fields
        ):
            # the mirror case: a stream's key written at the top of the file
            msg += (
                f" ({key} is a setting of one stream: in TOML, write it below that stream's "
                '[[streams]] name = "..."; in the environment, in MOCAP_STREAMS)'
            )
        elif (
            err["type"] == "extra_forbidden"
            and len(err["loc"]) == 2
            and err["loc"][0] != "streams"
            and key in ServiceSettings.model_fields
        ):
            # TOML: a key written below [udp] or [mqtt] belongs to that section's table
            msg += (
                f" ({key} is a setting of the whole service, not of [{err['loc'][0]}]: in "
                "TOML, write it above the first [section] or [[streams]])"
            )
        elif err["type"] == "extra_forbidden" and err["loc"]:
            msg += _did_you_mean(key, _section_keys(tuple(err["loc"])))
        names = _env_names(tuple(err["loc"]), env) if err["loc"] else []
        if names:
            # the environment wins over the file: say which variable the value came from
            msg += f" (from the environment: {', '.join(names)})"
            if err["loc"][0] == "streams" and any("__" in n[len("MOCAP_") :] for n in names):
                msg += (
                    "; streams is a list, set whole as JSON: "
                    """MOCAP_STREAMS='[{"name": "volume1", "labeled_start": "model"}]'"""
                )
        lines.append(f"  {loc}: {msg}")
    return "\n".join(lines)


def check_env(environ: dict[str, str] | None = None) -> None:
    """Rejects ``MOCAP_`` environment variables that name no setting (a typo would otherwise be
    ignored silently); :data:`NON_SETTING_ENV` are allowed."""
    env = os.environ if environ is None else environ
    fields = {f.upper() for f in ServiceSettings.model_fields}
    bad = []
    for key in env:
        k = key.upper()
        if not k.startswith("MOCAP_") or k in NON_SETTING_ENV:
            continue
        top = k[len("MOCAP_") :].split("__", 1)[0]
        if top not in fields:
            bad.append(key)
    if bad:
        allowed = ", ".join(sorted(NON_SETTING_ENV))
        stream_keys = {f.upper() for f in StreamSettings.model_fields} - fields

        def line(b: str) -> str:
            top = b.upper()[len("MOCAP_") :].split("__", 1)[0]
            if top not in stream_keys:
                nested = [f for f in _TABLES if top.startswith(f.upper() + "_")]
                if nested:  # MOCAP_UDP_PORT for MOCAP_UDP__PORT
                    inner = top[len(nested[0]) + 1 :]
                    where = f"MOCAP_{nested[0].upper()}__{inner}"
                    return f"  {b} (nested keys are joined with '__': {where})"
                return f"  {b}" + _did_you_mean(top, list(ServiceSettings.model_fields), "MOCAP_")
            return (
                f"  {b} ({top.lower()} is a setting of one stream: set it in MOCAP_STREAMS, "
                f"""e.g. MOCAP_STREAMS='[{{"name": "volume1", "{top.lower()}": ...}}]')"""
            )

        raise ConfigError(
            "unknown MOCAP_ environment variable(s) (not a setting; other allowed names: "
            f"{allowed}):\n" + "\n".join(line(b) for b in sorted(bad))
        )


def exposure_warnings(settings: ServiceSettings) -> list[str]:
    """Lines to log at start-up for listeners bound to every interface."""
    out = []
    if settings.udp.enabled and settings.udp.host in WILDCARD_HOSTS:
        out.append(
            f"udp.host = {settings.udp.host!r} listens on every interface: UDP frames and "
            "subscriptions are not authenticated; bind to loopback or a trusted network"
        )
    if settings.metrics_port is not None and settings.metrics_host in WILDCARD_HOSTS:
        out.append(f"metrics_host = {settings.metrics_host!r} exposes /metrics on every interface")
    return out


def read_settings_file(path: str | Path) -> dict[str, Any]:
    """Reads a ``.toml`` or ``.json`` settings file into a dict (no validation yet)."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"settings file {p} is a folder: give a .toml or .json file")
    if not p.is_file():
        raise ConfigError(f"settings file {p} does not exist")
    try:
        if p.suffix.lower() == ".toml":
            with p.open("rb") as f:
                data = tomllib.load(f)
        elif p.suffix.lower() == ".json":
            data = json.loads(p.read_text(encoding="utf-8"))
        else:
            raise ConfigError(f"settings file {p}: use .toml or .json, not {p.suffix or 'none'}")
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"settings file {p} cannot be parsed: {exc}") from exc
    except (RecursionError, OSError) as exc:
        raise ConfigError(f"settings file {p} cannot be read: {type(exc).__name__}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"settings file {p} must hold a table/object at the top level")
    resolve_file_paths(data, p.resolve().parent)
    return data


#: Settings naming files, per table (``streams`` is a list of tables): a relative path in a
#: settings file is read from the file's folder, as users write them (it was read from the
#: service's working folder: ``model = "../models/m.json"`` beside the config "did not exist").
FILE_SETTINGS = {"streams": ("model",), "mqtt": ("ca_file", "cert_file", "key_file")}


def resolve_file_paths(data: dict[str, Any], base: Path) -> None:
    """Makes the relative file paths of ``data`` (:data:`FILE_SETTINGS`) relative to ``base``
    in place (a settings file's folder; a tool writing settings for a service, its own working
    folder); values of other types are left for validation to refuse."""
    for table, keys in FILE_SETTINGS.items():
        sections = data.get(table)
        for sec in sections if isinstance(sections, list) else [sections]:
            if not isinstance(sec, dict):
                continue
            for key in keys:
                v = sec.get(key)
                if isinstance(v, str | os.PathLike) and str(v):
                    path = Path(v).expanduser()  # (~ is the user's home, as in a shell)
                    sec[key] = str(path if path.is_absolute() else base / path)


def load_settings(path: str | Path | None = None, **overrides: Any) -> ServiceSettings:
    """Settings from ``path`` (optional), ``MOCAP_`` env vars and ``overrides`` (tests, tools).

    ``overrides`` merge over the file's top-level keys. Raises :class:`ConfigError` listing
    every invalid field.
    """
    data = read_settings_file(path) if path is not None else {}
    data.update(overrides)
    where = f" in {path}" if path is not None else ""
    check_env()
    try:
        return ServiceSettings(**data)
    except ValidationError as exc:
        raise ConfigError(f"invalid service settings{where}:\n{_format_errors(exc)}") from exc
    except (ValueError, RecursionError) as exc:
        # pydantic-settings parses complex env values (MOCAP_STREAMS) as JSON before validation
        raise ConfigError(
            f"invalid service settings{where} (environment): {_env_reason(exc)}"
        ) from exc


def _env_reason(exc: BaseException) -> str:
    """What pydantic-settings' ``error parsing value for field "udp" from source
    "EnvSettingsSource"`` means, naming the variable(s) and the JSON error (a hostile run:
    ``MOCAP_UDP__PUBLISH_TO=notalist`` said only that)."""
    found = re.search(r'field "([^"]+)"', str(exc))
    if found is None:
        return str(exc)
    field = found.group(1)
    prefix = f"MOCAP_{field.upper()}"
    names = sorted(
        k for k in os.environ if k.upper() == prefix or k.upper().startswith(prefix + "__")
    )
    cause = exc.__cause__ or exc.__context__
    why = f"not valid JSON ({cause})" if cause is not None else "cannot be read"
    return f"{', '.join(names) or prefix} (setting {field}): {why}"
