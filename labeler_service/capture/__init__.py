"""Capture values and file I/O (C3D, TRC, NPZ)."""

from labeler_service.capture.io import (
    SUFFIXES,
    c3d_frames_fit,
    check_writable,
    read_capture,
    read_segment,
    write_capture,
)
from labeler_service.capture.model import (
    Capture,
    is_ghost,
    join_label,
    side_pairs,
    split_label,
    subject_groups,
)

__all__ = [
    "SUFFIXES",
    "Capture",
    "c3d_frames_fit",
    "check_writable",
    "is_ghost",
    "join_label",
    "read_capture",
    "read_segment",
    "side_pairs",
    "split_label",
    "subject_groups",
    "write_capture",
]
