"""Online labeling of optical motion-capture markers for multiple interacting performers.

The online labeler of Yu, Li and Deng (2007) as a library, a streaming service and the tools
around it. Layers (each a folder; a layer imports only the ones above it in this list):

- ``capture`` (C3D/TRC/NPZ I/O), ``labeling`` (frame types, config, templates, training, the
  labeler, the closest-point baseline, the registry, numba kernels);
- ``scenes`` (compose, corrupt, simulate), ``evaluation`` (the scorer);
- ``service`` (settings, wire protocol, server, transports), ``tools`` (replay, subscribe),
  ``testing`` (local broker, pipeline harness, real-data discovery), ``cli``.

The offline package (``offline``: structure training, the shoulder pipeline of Hong, Park and
Hodgins 2009) may import from here; never the reverse.

The names in ``__all__`` are imported on first use (module ``__getattr__``), so
``import labeler_service`` and ``mocap-labeler --help`` do not load numba or matplotlib.
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

try:
    __version__ = version("mocap-labeler")  # the one place: pyproject.toml's ``version``
except PackageNotFoundError:  # pragma: no cover - running from a source tree, not installed
    __version__ = "0+unknown"

#: public name -> the module that defines it
_EXPORTS: dict[str, str] = {
    # errors
    "MocapError": "labeler_service.errors",
    "CaptureError": "labeler_service.errors",
    "CaptureFormatError": "labeler_service.errors",
    "ConfigError": "labeler_service.errors",
    "LabelerError": "labeler_service.errors",
    "ModelError": "labeler_service.errors",
    "ProtocolError": "labeler_service.errors",
    "SceneError": "labeler_service.errors",
    "TransportError": "labeler_service.errors",
    # capture
    "Capture": "labeler_service.capture",
    "read_capture": "labeler_service.capture",
    "write_capture": "labeler_service.capture",
    "split_label": "labeler_service.capture",
    "subject_groups": "labeler_service.capture",
    # labeling
    "FrameLabeler": "labeler_service.labeling.frame",
    "LabeledFrame": "labeler_service.labeling.frame",
    "MarkerState": "labeler_service.labeling.frame",
    "LabelerConfig": "labeler_service.labeling.config",
    "LabelerModel": "labeler_service.labeling.templates",
    "load_model": "labeler_service.labeling.templates",
    "save_model": "labeler_service.labeling.templates",
    "Labeler": "labeler_service.labeling.labeler",
    "ClosestPointLabeler": "labeler_service.labeling.baseline",
    "make_labeler": "labeler_service.labeling.registry",
    # service
    "ServiceSettings": "labeler_service.service.settings",
    "load_settings": "labeler_service.service.settings",
    "Server": "labeler_service.service.server",
}

#: the public names (kept equal to ``_EXPORTS`` by tests/test_package.py)
__all__ = [
    "__version__",
    "MocapError",
    "CaptureError",
    "CaptureFormatError",
    "ConfigError",
    "LabelerError",
    "ModelError",
    "ProtocolError",
    "SceneError",
    "TransportError",
    "Capture",
    "read_capture",
    "write_capture",
    "split_label",
    "subject_groups",
    "FrameLabeler",
    "LabeledFrame",
    "MarkerState",
    "LabelerConfig",
    "LabelerModel",
    "load_model",
    "save_model",
    "Labeler",
    "ClosestPointLabeler",
    "make_labeler",
    "ServiceSettings",
    "load_settings",
    "Server",
]

if TYPE_CHECKING:
    from labeler_service.capture import (
        Capture,
        read_capture,
        split_label,
        subject_groups,
        write_capture,
    )
    from labeler_service.errors import (
        CaptureError,
        CaptureFormatError,
        ConfigError,
        LabelerError,
        MocapError,
        ModelError,
        ProtocolError,
        SceneError,
        TransportError,
    )
    from labeler_service.labeling.baseline import ClosestPointLabeler
    from labeler_service.labeling.config import LabelerConfig
    from labeler_service.labeling.frame import FrameLabeler, LabeledFrame, MarkerState
    from labeler_service.labeling.labeler import Labeler
    from labeler_service.labeling.registry import make_labeler
    from labeler_service.labeling.templates import LabelerModel, load_model, save_model
    from labeler_service.service.server import Server
    from labeler_service.service.settings import ServiceSettings, load_settings


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'labeler_service' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # next access skips this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
