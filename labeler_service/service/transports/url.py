"""Endpoint URLs of the tools: ``udp://host:port[/stream]``, ``mqtt://[user:pass@]host:port/stream``
(``mqtts://`` for TLS)."""

from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import unquote, urlsplit

from labeler_service.errors import ConfigError
from labeler_service.service.protocol import STREAM_NAME


@dataclass(frozen=True)
class Endpoint:
    scheme: str  # "udp" | "mqtt"
    host: str
    port: int
    stream: str | None  # None: not given (UDP: every stream for a subscriber)
    username: str | None = None
    password: str | None = None
    tls: bool = False


_DEFAULT_PORTS = {"udp": 9870, "mqtt": 1883, "mqtts": 8883}


def redact_url(url: str) -> str:
    """``url`` with the password of its ``user:pass@`` part replaced by ``***`` (for printing)."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    user = parts.username or ""
    host = parts.netloc.rpartition("@")[2]
    return parts._replace(netloc=f"{user}:***@{host}").geturl()


def parse_endpoint(url: str) -> Endpoint:
    """Parses a tool URL; raises :class:`ConfigError` saying what is wrong (never showing
    the password)."""
    shown = redact_url(url)
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme not in _DEFAULT_PORTS:
        raise ConfigError(
            f"URL {shown!r}: scheme must be udp://, mqtt:// or mqtts://, got {scheme or 'none'}"
        )
    if not parts.hostname:
        raise ConfigError(f"URL {shown!r} has no host")
    try:
        port = parts.port
    except ValueError:
        raise ConfigError(f"URL {shown!r}: bad port") from None
    if port == 0:  # (it became the default port: a replay went to a live service's 9870)
        raise ConfigError(f"URL {shown!r}: port 0 names no endpoint (1-65535, or leave it out)")
    port = port or _DEFAULT_PORTS[scheme]
    stream = parts.path.strip("/") or None
    if stream is not None and not STREAM_NAME.match(stream):
        raise ConfigError(f"URL {shown!r}: bad stream name {stream!r} (letters, digits, _ . -)")
    return Endpoint(
        scheme="mqtt" if scheme == "mqtts" else scheme,
        host=parts.hostname,
        port=port,
        stream=stream,
        username=unquote(parts.username) if parts.username else None,
        password=unquote(parts.password) if parts.password else None,
        tls=scheme == "mqtts",
    )
