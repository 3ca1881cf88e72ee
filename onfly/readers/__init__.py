"""Readers of recorded observations behind one interface (:func:`open_source`).

OnFly logs, TUM RGB-D folders, ROS 1 and ROS 2 bags; :class:`RealtimeSource` plays any of
them at the recorded pace.
"""

from onfly.readers.base import SOURCE_KINDS, ObservationSource, SourceKindError, detect_kind, known_length, open_source
from onfly.readers.realtime import MonotonicClock, PlaybackClock, RealtimeConfig, RealtimeSource
from onfly.readers.rosbag import BagConfig, BagFormatError, BagReader, BagSummary, bag_summary
from onfly.readers.tum import TUM_DEFAULT_INTRINSICS, TumConfig, TumFormatError, TumReader

__all__ = [
    "SOURCE_KINDS",
    "ObservationSource",
    "SourceKindError",
    "detect_kind",
    "known_length",
    "open_source",
    "MonotonicClock",
    "PlaybackClock",
    "RealtimeConfig",
    "RealtimeSource",
    "BagConfig",
    "BagFormatError",
    "BagReader",
    "BagSummary",
    "bag_summary",
    "TUM_DEFAULT_INTRINSICS",
    "TumConfig",
    "TumFormatError",
    "TumReader",
]
