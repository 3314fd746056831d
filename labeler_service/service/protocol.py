"""Wire protocol v1: msgpack maps, one frame per UDP datagram or MQTT message.

Every message is a map with ``v`` (= 1) and ``type``. Arrays travel as raw little-endian bytes
(``ndarray.tobytes()``), so encoding and decoding never loop over markers in Python.

=============  =========  ==================================================================
type           direction  keys (besides ``v``, ``type``)
=============  =========  ==================================================================
``frame``      in         ``stream``, ``seq`` (uint), ``t`` (s), ``points`` (N*3 float32),
                          optional ``labels`` (N x str|nil), optional ``sent`` (ns, sender)
``subscribe``  in (UDP)   ``stream`` (name or ``*``) — registers/renews a UDP subscriber;
                          optional ``token`` (bin, echoed challenge), ``pad`` (bin, ignored)
``challenge``  out (UDP)  ``stream``, ``token`` (bin 8) — sent to an unconfirmed subscriber,
                          never larger than its request; it echoes ``token`` to confirm
``model``      out        ``stream``, ``model`` (id), ``names`` (M), ``subjects``
                          ([name, start, count]...), ``rate``, optional ``bodies``
                          (rigid bodies: lists of marker indices into ``names``)
``labeled``    out        ``stream``, ``model``, ``seq``, ``t``, ``positions`` (M*3 float32),
                          ``state`` (M uint8), ``unlabeled`` (K*3 float32), ``src`` (input
                          ``sent`` or nil), ``recv``, ``sent`` (ns), ``proc_us``
``status``     out        ``stream``, ``state`` (starting/online/offline), ``time`` (s)
=============  =========  ==================================================================

``type`` may be omitted on input frames (DESIGN.md's minimal frame). Validation happens here,
once: :func:`decode` either returns a typed message with finite, correctly shaped arrays or
raises :class:`~labeler_service.errors.ProtocolError` whose ``reason`` tags the drop metric.
``docs/protocol.md`` has a byte-level example.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass

import msgpack
import numpy as np

from labeler_service.capture.model import MAX_COORD_MM
from labeler_service.errors import ProtocolError

VERSION = 1
#: Stream names become MQTT topic levels: letters, digits, ``_ . -``; 1-64 characters.
STREAM_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,64}\Z")
_F32 = np.dtype("<f4")
#: longest label a frame may carry (``subject:marker``)
MAX_LABEL = 128
#: characters a label may not hold: C0/C1 controls, and the format characters that reorder or
#: hide text (bidirectional overrides and isolates, zero-width ones, the BOM)
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u200b-\u200f\u202a-\u202e\u2060-\u2069\ufeff]")
_U8 = np.dtype("u1")
_U64_MAX = 2**64 - 1

#: The reasons a message is rejected (drop-metric label values).
REJECT_REASONS = (
    "oversize",
    "not_msgpack",
    "not_map",
    "version",
    "type",
    "stream",
    "seq",
    "time",
    "points",
    "non_finite",
    "out_of_range",
    "too_many_points",
    "labels",
    "field",
)


@dataclass(slots=True)
class FrameMsg:
    """An unlabeled (or, in the training window, labeled) input frame."""

    stream: str
    seq: int
    t: float
    points: np.ndarray  # (N, 3) float32, finite
    labels: tuple[str | None, ...] | None = None
    sent: int | None = None  # sender wall clock, ns since the epoch
    #: the sender's own ``t`` when the service labels the frame at another ``t`` (a jittered
    #: clock's step back, re-timed by the restart rule): the labeled frame carries this one
    t_sent: float | None = None


@dataclass(slots=True)
class SubscribeMsg:
    stream: str  # a name or "*"
    token: bytes | None = None  # the echoed challenge token (confirms the address)


@dataclass(slots=True)
class ChallengeMsg:
    stream: str  # a name or "*"
    token: bytes


@dataclass(slots=True)
class ModelMsg:
    stream: str
    model: int
    names: tuple[str, ...]
    subjects: tuple[tuple[str, int, int], ...]
    rate: float
    bodies: tuple[tuple[int, ...], ...] = ()  # optional key: marker indices per rigid body


@dataclass(slots=True)
class LabeledMsg:
    stream: str
    model: int
    seq: int
    t: float
    positions: np.ndarray  # (M, 3) float32, NaN = missing
    state: np.ndarray  # (M,) uint8 MarkerState
    unlabeled: np.ndarray  # (K, 3) float32
    src: int | None
    recv: int
    sent: int
    proc_us: float


@dataclass(slots=True)
class StatusMsg:
    stream: str
    state: str
    time: float


Message = FrameMsg | SubscribeMsg | ChallengeMsg | ModelMsg | LabeledMsg | StatusMsg
_STATUS_STATES = (
    "starting",
    "online",
    "offline",
    "degraded",
    "lost",
    "training_failed",
    "booting",
    "idle",
)


# ----------------------------------------------------------------------------- encoding


def _pack(obj: dict) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def encode_frame(
    stream: str,
    seq: int,
    t: float,
    points: np.ndarray,
    labels: list[str | None] | tuple[str | None, ...] | None = None,
    sent: int | None = None,
) -> bytes:
    """An input frame. ``sent`` defaults to now (``time.time_ns()``) for latency measurement."""
    msg: dict = {
        "v": VERSION,
        "type": "frame",
        "stream": stream,
        "seq": int(seq),
        "t": float(t),
        "points": np.ascontiguousarray(points, dtype=_F32).tobytes(),
        "sent": time.time_ns() if sent is None else int(sent),
    }
    if labels is not None:
        msg["labels"] = list(labels)
    return _pack(msg)


#: Bytes of a challenge token.
TOKEN_BYTES = 8


def encode_subscribe(stream: str = "*", token: bytes | None = None) -> bytes:
    """A subscribe request, padded to at least the size of the service's challenge (the
    service never answers an unconfirmed address with more bytes than it received)."""
    msg: dict = {"v": VERSION, "type": "subscribe", "stream": stream}
    if token is not None:
        msg["token"] = bytes(token)
    need = len(encode_challenge(stream, bytes(TOKEN_BYTES)))
    base = len(_pack(msg))
    if base < need:
        msg["pad"] = bytes(max(0, need - base - 6))  # "pad" key + bin header: 6 bytes
        while len(_pack(msg)) < need:
            msg["pad"] += b"\0"
    return _pack(msg)


def encode_challenge(stream: str, token: bytes) -> bytes:
    return _pack({"v": VERSION, "type": "challenge", "stream": stream, "token": bytes(token)})


def encode_model(
    stream: str,
    model: int,
    names: tuple[str, ...],
    subjects: tuple[tuple[str, int, int], ...],
    rate: float,
    *,
    bodies: tuple[tuple[int, ...], ...] | list[list[int]] | None = None,
) -> bytes:
    """The model message; ``bodies`` (optional key, omitted when ``None``) lists each rigid
    body's marker indices into ``names`` (the live view draws them as sticks)."""
    msg: dict = {
        "v": VERSION,
        "type": "model",
        "stream": stream,
        "model": int(model),
        "names": list(names),
        "subjects": [list(s) for s in subjects],
        "rate": float(rate),
    }
    if bodies is not None:
        msg["bodies"] = [[int(i) for i in b] for b in bodies]
    return _pack(msg)


def encode_labeled(
    stream: str,
    model: int,
    seq: int,
    t: float,
    positions: np.ndarray,
    state: np.ndarray,
    unlabeled: np.ndarray,
    src: int | None,
    recv: int,
    proc_us: float,
    sent: int | None = None,
) -> bytes:
    """A labeled frame; ``sent`` defaults to now, stamped just before packing."""
    return _pack(
        {
            "v": VERSION,
            "type": "labeled",
            "stream": stream,
            "model": int(model),
            "seq": int(seq),
            "t": float(t),
            "positions": np.ascontiguousarray(positions, dtype=_F32).tobytes(),
            "state": np.ascontiguousarray(state, dtype=_U8).tobytes(),
            "unlabeled": np.ascontiguousarray(unlabeled, dtype=_F32).tobytes(),
            "src": src,
            "recv": int(recv),
            "sent": time.time_ns() if sent is None else int(sent),
            "proc_us": float(proc_us),
        }
    )


def encode_status(stream: str, state: str, when: float | None = None) -> bytes:
    if state not in _STATUS_STATES:
        raise ValueError(f"status state must be one of {_STATUS_STATES}, got {state!r}")
    return _pack(
        {
            "v": VERSION,
            "type": "status",
            "stream": stream,
            "state": state,
            "time": time.time() if when is None else float(when),
        }
    )


def labeled_size_bound(n_markers: int, n_unlabeled: int, stream: str = "x" * 64) -> int:
    """Upper bound of an encoded labeled frame's size in bytes (docs/protocol.md, UDP cap)."""
    # 13 bytes per marker (12 position + 1 state), 12 per unlabeled point; fixed keys and
    # scalars stay under 200 bytes, plus the stream name and three bin headers (5 bytes each).
    return 13 * n_markers + 12 * n_unlabeled + len(stream.encode()) + 200 + 15


# ----------------------------------------------------------------------------- decoding
def _reject(reason: str, message: str) -> ProtocolError:
    return ProtocolError(message, reason=reason)


def _get_stream(m: dict, wildcard: bool = False) -> str:
    s = m.get("stream", "default")
    if wildcard and s == "*":
        return s
    if not isinstance(s, str) or not STREAM_NAME.match(s):
        raise _reject("stream", f"bad stream name {s!r}")
    return s


def _get_uint(m: dict, key: str, reason: str) -> int:
    v = m.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= _U64_MAX:
        raise _reject(reason, f"{key} must be an unsigned integer, got {v!r}")
    return v


def _get_float(m: dict, key: str, reason: str) -> float:
    v = m.get(key)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise _reject(reason, f"{key} must be a finite number, got {v!r}")
    return float(v)


def _get_array(m: dict, key: str, dtype: np.dtype, width: int, max_rows: int) -> np.ndarray:
    b = m.get(key)
    if not isinstance(b, bytes):
        raise _reject("points", f"{key} must be raw bytes, got {type(b).__name__}")
    item = dtype.itemsize * width
    if len(b) % item:
        raise _reject("points", f"{key}: {len(b)} bytes is not a multiple of {item}")
    n = len(b) // item
    if n > max_rows:
        raise _reject("too_many_points", f"{key}: {n} rows exceeds the cap of {max_rows}")
    a = np.frombuffer(b, dtype=dtype)
    return a.reshape(n, width) if width > 1 else a


def _decode_frame(m: dict, max_points: int) -> FrameMsg:
    stream = _get_stream(m)
    seq = _get_uint(m, "seq", "seq")
    t = _get_float(m, "t", "time")
    points = _get_array(m, "points", _F32, 3, max_points)
    if not np.isfinite(points).all():
        raise _reject("non_finite", "points contain NaN or infinity")
    far = float(np.abs(points).max()) if points.size else 0.0
    if far > MAX_COORD_MM:
        raise _reject(
            "out_of_range",
            f"a coordinate is {far:.3g} mm from the origin, beyond {MAX_COORD_MM:g} mm (no "
            "capture volume is that large)",
        )
    labels = m.get("labels")
    if labels is not None:
        if not isinstance(labels, list) or len(labels) != len(points):
            raise _reject("labels", f"labels must be a list of {len(points)} entries")
        for lab in labels:
            if lab is not None and not (isinstance(lab, str) and 0 < len(lab) <= MAX_LABEL):
                shown = (
                    repr(lab)
                    if not isinstance(lab, str) or len(lab) <= 40
                    else (f"{lab[:40]!r}... ({len(lab)} characters)")
                )
                raise _reject(
                    "labels", f"label {shown} must be nil or a string of 1-{MAX_LABEL} characters"
                )
            if lab is not None and _CONTROL.search(lab):
                # a newline forged log lines, a right-to-left override reversed them, and C3D
                # drops a NUL: no capture system names a marker so
                raise _reject(
                    "labels",
                    f"label {lab!r} holds a control or format character (newline, NUL, "
                    "direction override): not a marker name",
                )
        labels = tuple(labels)
    sent = m.get("sent")
    if sent is not None:
        sent = _get_uint(m, "sent", "field")
    # a writeable native copy: frombuffer's array is read-only, and numba would compile a
    # second specialization of every kernel for read-only arrays
    return FrameMsg(stream, seq, t, points.astype(np.float32), labels, sent)


def _decode_model(m: dict) -> ModelMsg:
    names = m.get("names")
    subjects = m.get("subjects")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise _reject("field", "model names must be a list of strings")
    if not isinstance(subjects, list):
        raise _reject("field", "model subjects must be a list")
    subj: list[tuple[str, int, int]] = []
    for s in subjects:
        ok = isinstance(s, list) and len(s) == 3 and isinstance(s[0], str)
        if not ok or not all(isinstance(x, int) and x >= 0 for x in s[1:]):
            raise _reject("field", f"model subject entry {s!r} must be [name, start, count]")
        if s[1] + s[2] > len(names):
            raise _reject("field", f"model subject {s[0]!r} runs past the marker list")
        subj.append((s[0], s[1], s[2]))
    return ModelMsg(
        _get_stream(m),
        _get_uint(m, "model", "field"),
        tuple(names),
        tuple(subj),
        _get_float(m, "rate", "field"),
        _get_bodies(m, len(names)),
    )


def _get_bodies(m: dict, n_markers: int) -> tuple[tuple[int, ...], ...]:
    """The optional ``bodies`` key of a model message: ``()`` when absent."""
    bodies = m.get("bodies")
    if bodies is None:
        return ()
    if not isinstance(bodies, list):
        raise _reject("field", "model bodies must be a list of marker-index lists")
    out: list[tuple[int, ...]] = []
    for b in bodies:
        ok = isinstance(b, list) and len(b) > 0
        if not ok or not all(isinstance(i, int) and not isinstance(i, bool) for i in b):
            raise _reject("field", f"model body {b!r} must be a non-empty list of marker indices")
        if not all(0 <= i < n_markers for i in b):
            raise _reject("field", f"model body {b!r} indexes past the {n_markers} markers")
        out.append(tuple(b))
    return tuple(out)


def _decode_labeled(m: dict, max_points: int) -> LabeledMsg:
    positions = _get_array(m, "positions", _F32, 3, 1 << 20)
    state = _get_array(m, "state", _U8, 1, 1 << 20)
    if len(state) != len(positions):
        raise _reject("points", f"{len(state)} states for {len(positions)} markers")
    src = m.get("src")
    if src is not None:
        src = _get_uint(m, "src", "field")
    return LabeledMsg(
        _get_stream(m),
        _get_uint(m, "model", "field"),
        _get_uint(m, "seq", "seq"),
        _get_float(m, "t", "time"),
        positions,
        state,
        _get_array(m, "unlabeled", _F32, 3, max_points),
        src,
        _get_uint(m, "recv", "field"),
        _get_uint(m, "sent", "field"),
        _get_float(m, "proc_us", "field"),
    )


def _decode_status(m: dict) -> StatusMsg:
    state = m.get("state")
    if state not in _STATUS_STATES:
        raise _reject("field", f"status state must be one of {_STATUS_STATES}, got {state!r}")
    return StatusMsg(_get_stream(m), state, _get_float(m, "time", "time"))


def _skip(b: bytes, i: int) -> int:
    """The offset after the msgpack scalar, string or bin at ``b[i]``; -1 for anything else
    (an array, a map, an extension) or a truncated value: :func:`peek_frame_stream` then
    gives up."""
    c = b[i]
    if c <= 0x7F or c >= 0xE0 or c in (0xC0, 0xC2, 0xC3):  # fixint, nil, bool
        return i + 1
    if 0xA0 <= c <= 0xBF:  # fixstr
        return i + 1 + (c & 0x1F)
    fixed = _FIXED.get(c)
    if fixed is not None:
        return i + 1 + fixed
    var = _VAR.get(c)
    if var is not None:
        n = int.from_bytes(b[i + 1 : i + 1 + var], "big")
        return i + 1 + var + n
    return -1


# type byte -> payload bytes (ints, floats) / length-field bytes (str8-32, bin8-32)
_FIXED = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8, 0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8, 0xCA: 4, 0xCB: 8}
_FRAME_HEAD = b"\xa1v\x01\xa4type\xa5frame\xa6stream"
_VAR = {0xD9: 1, 0xDA: 2, 0xDB: 4, 0xC4: 1, 0xC5: 2, 0xC6: 4}


def peek_frame_stream(payload: bytes) -> str | None:
    """The ``stream`` of a frame message read from its header without decoding it (the UDP
    receiver's pre-filter: a flood for unknown streams is dropped at a few microseconds per
    datagram instead of a full :func:`decode`). Walks the map's leading entries (string keys,
    scalar/string/bin values) up to ``stream``; returns ``None`` when the message is not
    recognisably a frame (another ``type`` or protocol version ``v``, not a map, a key order or
    value it does not walk, a name that breaks :data:`STREAM_NAME`): the caller then decodes it
    in full (a ``v`` 2 frame was counted ``unknown_stream``, not ``version``). Never raises.
    A name returned is only a hint: :func:`decode` still validates the whole message.
    """
    b = payload
    try:
        c = b[0]
        # fast path: the header :func:`encode_frame` writes (v, type, stream, in this order)
        if 0x80 <= c <= 0x8F and b.startswith(_FRAME_HEAD, 1):
            j = 1 + len(_FRAME_HEAD)
            c = b[j]
            if 0xA0 <= c <= 0xBF:
                k = j + 1 + (c & 0x1F)
                if k > len(b):  # cut inside the name: decoded in full, refused as such
                    return None
                value = b[j + 1 : k].decode("utf-8")
                return value if STREAM_NAME.match(value) else None
            c = b[0]
        if 0x80 <= c <= 0x8F:
            n, i = c & 0x0F, 1
        elif c == 0xDE:
            n, i = int.from_bytes(b[1:3], "big"), 3
        else:
            return None
        for _ in range(min(n, 16)):
            c = b[i]
            if not 0xA0 <= c <= 0xBF:  # keys of the protocol are short fixstr
                return None
            j = i + 1 + (c & 0x1F)
            key = b[i + 1 : j]
            if key == b"v" and b[j] != VERSION:  # (another version: decoded, refused as such)
                return None
            if key == b"stream" or key == b"type":
                c = b[j]
                if 0xA0 <= c <= 0xBF:
                    k = j + 1 + (c & 0x1F)
                elif c == 0xD9:
                    k = j + 2 + b[j + 1]
                    j += 1
                else:
                    return None
                if k > len(b):
                    return None
                value = b[j + 1 : k].decode("utf-8")
                if key == b"type":
                    if value != "frame":
                        return None
                else:
                    return value if STREAM_NAME.match(value) else None
                i = k
                continue
            i = _skip(b, j)
            if i < 0 or i > len(b):
                return None
        return None
    except (IndexError, UnicodeDecodeError):
        return None


def decode(
    payload: bytes,
    max_points: int = 2000,
    max_bytes: int = 65_507,
    accept: frozenset[str] | None = None,
) -> Message:
    """Decodes and validates one message; raises :class:`ProtocolError` with a ``reason``.

    Checks, in order: size (``oversize``), msgpack (``not_msgpack``), a map (``not_map``),
    ``v == 1`` (``version``), a known ``type`` that is in ``accept`` when given (``type``: the
    service accepts only ``frame`` and ``subscribe``, so a service-output message sent to it is
    refused for its type, not for its fields), then the type's fields: stream name,
    ``seq`` an unsigned int, ``t`` finite, ``points`` a whole number of float32 triples
    (``points``) no more than ``max_points`` (``too_many_points``) all finite (``non_finite``)
    and within :data:`MAX_COORD_MM` of the origin (``out_of_range``),
    ``labels`` one string-or-nil per point (``labels``).
    """
    if len(payload) > max_bytes:
        raise _reject("oversize", f"message of {len(payload)} bytes exceeds {max_bytes}")
    try:
        m = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            max_str_len=1 << 16,
            max_bin_len=max_bytes,
            max_array_len=1 << 16,
            max_map_len=64,
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises several unrelated types for bad input
        raise _reject("not_msgpack", f"not a msgpack message: {exc}") from exc
    if not isinstance(m, dict):
        raise _reject("not_map", f"message must be a map, got {type(m).__name__}")
    if m.get("v") != VERSION or isinstance(m.get("v"), bool):
        raise _reject("version", f"unsupported protocol version {m.get('v')!r}")
    kind = m.get("type", "frame")
    if not isinstance(kind, str):  # (a list or map is unhashable: ``in accept`` raised)
        raise _reject("type", f"message type must be a string, got {type(kind).__name__}")
    if accept is not None and kind not in accept:
        raise _reject("type", f"a {kind!r} message is not accepted here")
    if kind == "frame":
        return _decode_frame(m, max_points)
    if kind == "labeled":
        return _decode_labeled(m, max_points)
    if kind == "model":
        return _decode_model(m)
    if kind == "status":
        return _decode_status(m)
    if kind == "subscribe":
        token = m.get("token")
        if token is not None and not (isinstance(token, bytes) and len(token) == TOKEN_BYTES):
            raise _reject("field", f"subscribe token must be {TOKEN_BYTES} raw bytes")
        return SubscribeMsg(_get_stream(m, wildcard=True), token)
    if kind == "challenge":
        token = m.get("token")
        if not (isinstance(token, bytes) and len(token) == TOKEN_BYTES):
            raise _reject("field", f"challenge token must be {TOKEN_BYTES} raw bytes")
        return ChallengeMsg(_get_stream(m, wildcard=True), token)
    raise _reject("type", f"unknown message type {kind!r}")
