"""Reader of OnFly logs (format: :mod:`onfly.logs.format`).

Iterating a :class:`LogReader` yields :class:`onfly.observation.Observation` values in file
order. The file is re-opened for every iteration, so a log that is still being written is
read up to its last whole frame each time. A record the writer has not finished (the file
ends inside it, or in a tail of zero bytes) ends the iteration quietly; a damaged record
raises :class:`LogCorruptError` naming the file, byte offset and frame index.
"""

from __future__ import annotations

import json
import logging
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Iterator

import numpy as np

from onfly.logs.format import (
    EVENTS_FILE,
    FILE_MAGIC,
    FORMAT_NAME,
    FORMAT_VERSION,
    FRAMES_FILE,
    META_FILE,
    PREFIX_SIZE,
    LogCorruptError,
    LogEvent,
    LogFormatError,
    decode_body,
    decode_prefix,
)
from onfly.observation import Observation
from planning.camera import PinholeCamera
from vlm.types import FrameAnnotation, VisibleObject

__all__ = ["LogReader", "LogFrame"]

log = logging.getLogger(__name__)

_ZERO_SCAN_CHUNK = 1 << 20


@dataclass(frozen=True, eq=False)
class LogFrame:
    """One decoded frame record.

    Attributes
    ----------
    index : int, 0-based record index
    offset : int, byte offset of the record in ``frames.bin``
    observation : the frame as an Observation
    header : the record's JSON header (as stored)
    """

    index: int
    offset: int
    observation: Observation
    header: dict


def _rest_is_zero(f: BinaryIO) -> bool:
    while True:
        chunk = f.read(_ZERO_SCAN_CHUNK)
        if not chunk:
            return True
        if chunk.count(0) != len(chunk):
            return False


class LogReader:
    """Read a log directory written by :class:`onfly.logs.writer.LogWriter`.

    Parameters
    ----------
    path : the log directory

    Raises
    ------
    LogFormatError
        The directory is not an OnFly log (missing or malformed ``meta.json``, wrong file
        magic or version in ``frames.bin``); the message names the file.
    """

    kind = "onfly-log"

    def __init__(self, path) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise LogFormatError(f"{self.path}: not a directory (an OnFly log is a directory with {META_FILE}, {FRAMES_FILE}, {EVENTS_FILE})")
        meta_path = self.path / META_FILE
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise LogFormatError(f"{meta_path}: missing") from None
        except ValueError as exc:
            raise LogFormatError(f"{meta_path}: not valid JSON ({exc})") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
            raise LogFormatError(f"{meta_path}: 'format' is not {FORMAT_NAME!r}")
        if meta.get("version") != FORMAT_VERSION:
            raise LogFormatError(f"{meta_path}: unsupported version {meta.get('version')!r} (this reader knows {FORMAT_VERSION})")
        self.meta: dict = meta
        self.frames_path = self.path / FRAMES_FILE
        self.events_path = self.path / EVENTS_FILE
        f = self._open_frames()
        if f is not None:
            f.close()

    # -- protocol --------------------------------------------------------------------------------
    def __enter__(self) -> "LogReader":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def close(self) -> None:
        """Nothing stays open between iterations; present for the source protocol."""

    def __iter__(self) -> Iterator[Observation]:
        for frame in self.frames():
            yield frame.observation

    def __len__(self) -> int:
        """Number of whole frame records on disk now (bodies are not CRC-checked here)."""
        n = 0
        for _ in self._scan(decode=False):
            n += 1
        return n

    # -- frames ----------------------------------------------------------------------------------
    def _open_frames(self) -> BinaryIO | None:
        """``frames.bin`` positioned after its file header; None while the header is unfinished."""
        try:
            f = open(self.frames_path, "rb")
        except FileNotFoundError:
            raise LogFormatError(f"{self.frames_path}: missing") from None
        magic = f.read(len(FILE_MAGIC))
        if magic != FILE_MAGIC:
            f.close()
            if len(magic) < len(FILE_MAGIC) and FILE_MAGIC.startswith(magic):
                return None  # the writer has created the file but not yet written its header
            raise LogFormatError(f"{self.frames_path}: wrong file magic {magic!r} (expected {FILE_MAGIC!r})")
        return f

    def frames(self) -> Iterator[LogFrame]:
        """Decoded frames with their index, byte offset and stored header."""
        yield from self._scan(decode=True)

    def _scan(self, decode: bool) -> Iterator[LogFrame | None]:
        f = self._open_frames()
        if f is None:
            return
        with f:
            index = 0
            while True:
                offset = f.tell()
                prefix = f.read(PREFIX_SIZE)
                if not prefix:
                    return
                if len(prefix) < PREFIX_SIZE:
                    log.info("%s: unfinished record %d at byte %d ignored", self.frames_path, index, offset)
                    return
                parsed = decode_prefix(prefix)
                if parsed is None:
                    if prefix.count(0) == len(prefix) and _rest_is_zero(f):
                        log.warning("%s: zero-filled tail from byte %d ignored (unfinished write)", self.frames_path, offset)
                        return
                    raise LogCorruptError(self.frames_path, offset, index, "bad record marker or prefix CRC")
                header_len, payload_len, body_crc = parsed
                if not decode:
                    f.seek(header_len + payload_len, 1)
                    end = f.tell()
                    f.seek(0, 2)
                    if f.tell() < end:
                        return
                    f.seek(end)
                    index += 1
                    yield None
                    continue
                body = f.read(header_len + payload_len)
                if len(body) < header_len + payload_len:
                    log.info("%s: unfinished record %d at byte %d ignored", self.frames_path, index, offset)
                    return
                if zlib.crc32(body) != body_crc:
                    raise LogCorruptError(self.frames_path, offset, index, "body CRC mismatch")
                try:
                    header, arrays = decode_body(body[:header_len], body[header_len:])
                    obs = self._observation(header, arrays)
                except (ValueError, KeyError, TypeError, zlib.error) as exc:
                    raise LogCorruptError(self.frames_path, offset, index, str(exc)) from None
                yield LogFrame(index, offset, obs, header)
                index += 1

    @staticmethod
    def _observation(header: dict, arrays: dict[str, np.ndarray]) -> Observation:
        cam = header["camera"]
        camera = PinholeCamera(int(cam["width"]), int(cam["height"]), float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"]))
        annotation = None
        ann = header.get("annotation")
        if ann is not None:
            objects = {
                int(o["instance_id"]): VisibleObject.from_dict(o) for o in ann["objects"]
            }
            annotation = FrameAnnotation(
                instance_ids=arrays["annotation.instance_ids"],
                depth_m=arrays["annotation.depth_m"],
                objects=objects,
                semantic_ids=arrays.get("annotation.semantic_ids"),
            )
        depth = arrays["depth_m"]
        if depth.dtype != np.float32:
            raise ValueError(f"depth_m has dtype {depth.dtype}, expected float32")
        return Observation(
            t_s=float(header["t_s"]),
            rgb=arrays["rgb"],
            depth_m=depth,
            T_world_cam=np.array(header["T_world_cam"], dtype=float),
            camera=camera,
            frame_id=str(header["frame_id"]),
            T_body_cam=np.array(header["T_body_cam"], dtype=float),
            annotation=annotation,
        )

    # -- events ----------------------------------------------------------------------------------
    def events(self) -> Iterator[LogEvent]:
        """Events in file order. An unfinished last line (no newline) is ignored.

        Raises
        ------
        LogFormatError
            A complete line that is not a valid event, naming the file and line number.
        """
        if not self.events_path.exists():
            return
        with open(self.events_path, "rb") as f:
            for lineno, raw in enumerate(f, start=1):
                if not raw.endswith(b"\n"):
                    log.info("%s:%d: unfinished event line ignored", self.events_path, lineno)
                    return
                if not raw.strip():
                    continue
                try:
                    obj = json.loads(raw.decode("utf-8"))
                    event = LogEvent(
                        seq=int(obj["seq"]),
                        t_s=float(obj["t_s"]),
                        kind=str(obj["kind"]),
                        frame_index=None if obj.get("frame_index") is None else int(obj["frame_index"]),
                        data=obj.get("data") or {},
                    )
                except (ValueError, KeyError, TypeError) as exc:
                    raise LogFormatError(f"{self.events_path}:{lineno}: malformed event line ({exc})") from None
                yield event
