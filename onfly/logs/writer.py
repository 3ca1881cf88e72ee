"""Streaming writer of OnFly logs (format: :mod:`onfly.logs.format`).

Every frame is one record appended with a single ``write`` and flushed, every event one
flushed JSON line, so a crash loses at most the frame being written and a reader can follow
the log while it grows.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from onfly.logs.format import (
    ENCODINGS,
    EVENTS_FILE,
    FILE_MAGIC,
    FORMAT_NAME,
    FORMAT_VERSION,
    FRAMES_FILE,
    META_FILE,
    LogError,
    LogExistsError,
    encode_record,
)
from onfly.observation import Observation

__all__ = ["LogWriterConfig", "LogWriter", "to_jsonable"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LogWriterConfig:
    """How a log is written.

    Attributes
    ----------
    encoding : ``"zlib"`` (default, lossless) or ``"raw"`` for the frame arrays
    zlib_level : 0..9; 1 keeps writing fast enough for onboard use
    fsync_each_frame : also ``os.fsync`` after every frame and event (survives a power cut,
        not only a process crash; costs a disk round trip per frame)
    """

    encoding: str = "zlib"
    zlib_level: int = 1
    fsync_each_frame: bool = False

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise ValueError(f"LogWriterConfig.encoding must be one of {ENCODINGS}, got {self.encoding!r}")
        if not (0 <= int(self.zlib_level) <= 9):
            raise ValueError(f"LogWriterConfig.zlib_level must be in 0..9, got {self.zlib_level}")


def to_jsonable(value: Any) -> Any:
    """Convert event data to JSON-compatible values.

    numpy arrays become nested lists, numpy scalars Python numbers, enums their value,
    dataclasses dicts, tuples/sets lists, Paths strings. Anything else that JSON cannot
    hold raises :class:`LogError` naming its type.
    """
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, enum.Enum):
        return to_jsonable(value.value)
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    raise LogError(f"event data of type {type(value).__name__} cannot be written as JSON")


def _write_json_atomic(path: Path, obj: Mapping[str, Any]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=2)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class LogWriter:
    """Append observations and events to a new log directory.

    Parameters
    ----------
    path : directory to create (it may exist only if empty)
    config : :class:`LogWriterConfig`
    meta : free JSON-compatible mapping stored under ``"user"`` in ``meta.json``
        (e.g. the config of the run)

    Use as a context manager; :meth:`write` returns the frame index, :meth:`event` the
    event's sequence number.
    """

    def __init__(self, path, config: LogWriterConfig = LogWriterConfig(), *, meta: Mapping[str, Any] | None = None) -> None:
        self.path = Path(path)
        self.config = config
        if self.path.exists():
            if not self.path.is_dir():
                raise LogExistsError(f"{self.path}: exists and is not a directory")
            if any(self.path.iterdir()):
                raise LogExistsError(f"{self.path}: directory is not empty; a log is never overwritten")
        self.path.mkdir(parents=True, exist_ok=True)
        self._meta = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "created_unix_s": time.time(),
            "closed": False,
            "user": to_jsonable(dict(meta or {})),
        }
        _write_json_atomic(self.path / META_FILE, self._meta)
        self._frames = open(self.path / FRAMES_FILE, "xb")
        self._frames.write(FILE_MAGIC)
        self._frames.flush()
        self._events = open(self.path / EVENTS_FILE, "x", encoding="utf-8")
        self._n_frames = 0
        self._n_events = 0
        self._last_t_s = -np.inf
        self._closed = False

    # -- context manager ----------------------------------------------------------------------
    def __enter__(self) -> "LogWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    @property
    def frames_written(self) -> int:
        return self._n_frames

    @property
    def events_written(self) -> int:
        return self._n_events

    def _check_open(self) -> None:
        if self._closed:
            raise LogError(f"{self.path}: log writer is closed")

    def _sync(self, f) -> None:
        f.flush()
        if self.config.fsync_each_frame:
            os.fsync(f.fileno())

    def write(self, obs: Observation) -> int:
        """Append one observation as a frame record; returns its frame index.

        Timestamps should not go backwards; if they do the frame is still written and a
        warning logged (readers keep file order).
        """
        self._check_open()
        if obs.t_s < self._last_t_s:
            log.warning("%s: frame %d goes back in time (%.6f < %.6f)", self.path, self._n_frames, obs.t_s, self._last_t_s)
        cam = obs.camera
        header: dict[str, Any] = {
            "index": self._n_frames,
            "t_s": float(obs.t_s),
            "frame_id": str(obs.frame_id),
            "camera": {"width": cam.width, "height": cam.height, "fx": float(cam.fx), "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy)},
            "T_world_cam": np.asarray(obs.T_world_cam, dtype=float).tolist(),
            "T_body_cam": np.asarray(obs.T_body_cam, dtype=float).tolist(),
            "annotation": None,
        }
        arrays: dict[str, np.ndarray] = {"rgb": obs.rgb, "depth_m": obs.depth_m}
        ann = obs.annotation
        if ann is not None:
            header["annotation"] = {
                "objects": [
                    o.to_dict() for o in ann.objects.values()
                ]
            }
            arrays["annotation.instance_ids"] = np.asarray(ann.instance_ids)
            arrays["annotation.depth_m"] = np.asarray(ann.depth_m)
            if ann.semantic_ids is not None:
                arrays["annotation.semantic_ids"] = np.asarray(ann.semantic_ids)
        record = encode_record(header, arrays, encoding=self.config.encoding, zlib_level=self.config.zlib_level)
        self._frames.write(record)
        self._sync(self._frames)
        self._last_t_s = max(self._last_t_s, obs.t_s)
        self._n_frames += 1
        return self._n_frames - 1

    def event(self, kind: str, data: Mapping[str, Any] | None = None, *, t_s: float | None = None, frame_index: int | None = None) -> int:
        """Append one event (an agent's input or output, a status change...).

        Parameters
        ----------
        kind : short name, e.g. ``"decision"``
        data : JSON-compatible mapping (numpy values and dataclasses are converted)
        t_s : seconds on the log's clock; defaults to the last frame's time (0 before any)
        frame_index : the frame it belongs to; defaults to the last frame written (None
            before any)
        """
        self._check_open()
        if not isinstance(kind, str) or not kind:
            raise LogError(f"event kind must be a non-empty string, got {kind!r}")
        if t_s is None:
            t_s = float(self._last_t_s) if self._n_frames else 0.0
        if frame_index is None and self._n_frames:
            frame_index = self._n_frames - 1
        line = json.dumps(
            {"seq": self._n_events, "t_s": float(t_s), "kind": kind, "frame_index": frame_index, "data": to_jsonable(dict(data or {}))},
            separators=(",", ":"),
        )
        self._events.write(line + "\n")
        self._sync(self._events)
        self._n_events += 1
        return self._n_events - 1

    def close(self) -> None:
        """Flush, close the files and mark ``meta.json`` closed. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for f in (self._frames, self._events):
            f.flush()
            os.fsync(f.fileno())
            f.close()
        self._meta.update({"closed": True, "frames": self._n_frames, "events": self._n_events})
        _write_json_atomic(self.path / META_FILE, self._meta)
