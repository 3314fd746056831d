"""Every exception the project raises on purpose.

::

    MocapError                      base; the CLI prints its message and exits 2
    ├── CaptureError                a capture file cannot be read or written
    │   └── CaptureFormatError      the file is readable but its content is wrong
    ├── SceneError                  compose / simulate / corrupt got impossible parameters
    ├── ModelError                  a subject model (template) file is invalid or mismatched
    ├── LabelerError                the labeler was used out of order (e.g. no training window)
    ├── InitBufferFullError         a stream's buffer of labeled init frames is full (frame dropped)
    ├── ProtocolError               a wire message is malformed (counted, never fatal)
    │   (attribute ``reason``: a short machine-readable tag used in drop metrics)
    ├── TransportError              a transport cannot deliver now (broker down, link disabled)
    └── ConfigError                 service settings are invalid

Chain with ``raise ... from exc`` so the original cause stays visible in logs.
"""

from __future__ import annotations


class MocapError(Exception):
    """Base of every deliberate error; its message is meant for a person."""


class CaptureError(MocapError):
    """A capture file could not be read or written (names the file)."""


class CaptureFormatError(CaptureError):
    """A capture file was read but its content is unusable (names the file and the problem)."""


class SceneError(MocapError):
    """Scene composition, simulation or corruption got parameters it cannot satisfy."""


class ModelError(MocapError):
    """A subject model file is invalid or does not match the data."""


class LabelerError(MocapError):
    """The labeler was used out of order or with inconsistent input."""


class InitBufferFullError(MocapError):
    """A stream already holds ``max_init_frames`` labeled init frames; the new one is dropped
    (counted as ``init_overflow``)."""


class ProtocolError(MocapError):
    """A wire message is malformed. ``reason`` is a short tag for drop metrics."""

    def __init__(self, message: str, reason: str = "malformed") -> None:
        super().__init__(message)
        self.reason = reason


class TransportError(MocapError):
    """A transport could not deliver a message now (not connected, sends disabled); the server
    counts it as ``send_error`` and carries on."""


class ConfigError(MocapError):
    """Service settings are invalid."""


class BudgetExceeded(MocapError):
    """A background job (in-stream training, boot) ran over its time budget or was refused."""


class LimitExceeded(MocapError):
    """A per-stream limit of the service was hit (``reason``: the drop-metric tag)."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason
