"""Recordings, the pure part: what a recorded camera frame is, and re-running perception on it.

The file format (MCAP, channels, schemas) and its reading and writing live in
:mod:`hapticloud.hardware.recording`; this package takes what the reader decodes and gives back
results, with no I/O (:mod:`.frames`: the stored region of a depth frame and the robot's shapes
as data; :mod:`.replay`: perception and fusion re-run on recorded frames, compared with what
was recorded).
"""

from .frames import (
    CapturedFrame,
    RecordConfig,
    frame_from_roi,
    primitive_from_dict,
    primitive_to_dict,
    storage_roi,
)
from .replay import ReplayResult, ReplayRow, replay, replay_configs

__all__ = [
    "CapturedFrame",
    "RecordConfig",
    "ReplayResult",
    "ReplayRow",
    "frame_from_roi",
    "primitive_from_dict",
    "primitive_to_dict",
    "replay",
    "replay_configs",
    "storage_roi",
]
