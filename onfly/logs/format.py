"""The OnFly log format, version 1: what is on disk, and the codec for one frame record.

A log is a **directory** holding three files:

``meta.json``
    Written once when the log is created (atomically: temporary file + rename) and rewritten
    atomically when the writer closes cleanly. Keys: ``format`` (always ``"onfly-log"``),
    ``version`` (``1``), ``created_unix_s``, ``closed`` (``true`` after a clean close),
    ``frames`` (count at clean close, absent before), ``user`` (free JSON the caller passed).
    Readers never depend on ``closed`` / ``frames``: a log cut by a crash is still a log.

``frames.bin``
    Append-only. Starts with the 12-byte file header ``b"ONFLYLOG"`` + ``u32`` format
    version, then one **record** per frame, each written with a single ``write`` and
    flushed. All integers are little-endian::

        offset  size  field
        0       4     marker        b"OFR1"
        4       4     header_len    u32, bytes of the JSON header (H)
        8       8     payload_len   u64, bytes of the array payload (P)
        16      4     prefix_crc    u32, CRC-32 of bytes 0..16 (marker and both lengths)
        20      4     body_crc      u32, CRC-32 of header + payload
        24      H     header        UTF-8 JSON object (see below)
        24+H    P     payload       the arrays, each encoded, concatenated in header order

    The prefix CRC tells a corrupt length (an error) from a record the writer has not
    finished (the file simply ends early: a reader stops there, silently). A tail of zero
    bytes (what some file systems leave after a power cut) also counts as unfinished.

    The header JSON of a frame::

        {"index": 0, "t_s": 0.0, "frame_id": "...",
         "camera": {"width": 640, "height": 480, "fx": .., "fy": .., "cx": .., "cy": ..},
         "T_world_cam": [[4 floats] x 4], "T_body_cam": [[4 floats] x 4],
         "arrays": [{"name": "rgb", "dtype": "|u1", "shape": [480, 640, 3],
                     "encoding": "zlib", "nbytes": 123456}, ...],
         "annotation": null | {"objects": [{"instance_id": 3, "name": .., "label": ..,
                                            "aliases": [..]}, ...]}}

    Floats are written by Python's shortest round-trip ``repr``, so times and poses read
    back bit for bit. Arrays are the raw C-order bytes of the stated ``dtype`` (a numpy
    dtype string with explicit byte order), optionally zlib-compressed (``encoding`` is
    ``"raw"`` or ``"zlib"``): lossless, so arrays read back bit for bit, NaN payloads
    included. Arrays always present: ``rgb`` (uint8 (H, W, 3)) and ``depth_m`` (float32
    (H, W), z-depth in metres, 0/NaN/inf = no reading). With an annotation (embedded world
    only): ``annotation.instance_ids``, ``annotation.depth_m`` and optionally
    ``annotation.semantic_ids``.

``events.jsonl``
    Append-only JSON lines, one event per line, flushed per line: the agents' inputs and
    outputs (prompts, raw model text, parsed pixel, verifier record, status...)::

        {"seq": 0, "t_s": 1.25, "kind": "decision", "frame_index": 3, "data": {...}}

    ``frame_index`` is the index of the frame the event belongs to, or ``null``. The JSON
    dialect is Python's: ``NaN`` and ``Infinity`` are allowed. A last line without its
    newline is an unfinished write and is ignored; a malformed complete line is an error.
"""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FILE_MAGIC",
    "RECORD_MARKER",
    "PREFIX_SIZE",
    "META_FILE",
    "FRAMES_FILE",
    "EVENTS_FILE",
    "ENCODINGS",
    "LogError",
    "LogFormatError",
    "LogCorruptError",
    "LogExistsError",
    "LogEvent",
    "ArraySpec",
    "encode_record",
    "decode_prefix",
    "decode_body",
    "is_log_dir",
]

FORMAT_NAME = "onfly-log"
FORMAT_VERSION = 1
FILE_MAGIC = b"ONFLYLOG" + struct.pack("<I", FORMAT_VERSION)
RECORD_MARKER = b"OFR1"
_PREFIX = struct.Struct("<4sIQII")
PREFIX_SIZE = _PREFIX.size  # 24
META_FILE = "meta.json"
FRAMES_FILE = "frames.bin"
EVENTS_FILE = "events.jsonl"
ENCODINGS = ("raw", "zlib")
#: Array dtypes a log may hold (no object or void dtypes: a log never unpickles anything).
_ALLOWED_KINDS = frozenset("biuf")
_MAX_HEADER_BYTES = 1 << 24


class LogError(ValueError):
    """Base class of log errors."""


class LogFormatError(LogError):
    """A file that is not a valid OnFly log (or a malformed part of one), naming the file."""


class LogCorruptError(LogFormatError):
    """A frame record whose bytes are damaged.

    Attributes
    ----------
    path : Path of ``frames.bin``
    offset : int, byte offset of the record in that file
    frame_index : int, index of the record (0-based count of records before it)
    """

    def __init__(self, path: Path, offset: int, frame_index: int, reason: str) -> None:
        super().__init__(f"{path}: corrupt frame record {frame_index} at byte offset {offset}: {reason}")
        self.path = Path(path)
        self.offset = int(offset)
        self.frame_index = int(frame_index)


class LogExistsError(LogError):
    """The writer refuses to write into a directory that already holds a log or other files."""


@dataclass(frozen=True)
class LogEvent:
    """One event of ``events.jsonl``.

    Attributes
    ----------
    seq : int, 0-based position in the events file
    t_s : float, seconds on the log's clock
    kind : str, e.g. ``"decision"``, ``"monitor"``, ``"verifier"``, ``"status"``
    frame_index : int or None, the frame the event belongs to
    data : JSON-compatible mapping
    """

    seq: int
    t_s: float
    kind: str
    frame_index: int | None
    data: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ArraySpec:
    """How one array sits in a record's payload."""

    name: str
    dtype: str
    shape: tuple[int, ...]
    encoding: str
    nbytes: int

    def to_json(self) -> dict:
        return {"name": self.name, "dtype": self.dtype, "shape": list(self.shape), "encoding": self.encoding, "nbytes": self.nbytes}


def _encode_array(arr: np.ndarray, encoding: str, zlib_level: int) -> tuple[bytes, str]:
    arr = np.ascontiguousarray(arr)
    if arr.dtype.kind not in _ALLOWED_KINDS:
        raise LogError(f"cannot log arrays of dtype {arr.dtype}; allowed kinds: bool, int, uint, float")
    raw = arr.tobytes(order="C")
    if encoding == "raw":
        return raw, arr.dtype.str
    if encoding == "zlib":
        return zlib.compress(raw, zlib_level), arr.dtype.str
    raise LogError(f"encoding must be one of {ENCODINGS}, got {encoding!r}")


def encode_record(header: Mapping[str, Any], arrays: Mapping[str, np.ndarray], *, encoding: str = "zlib", zlib_level: int = 1) -> bytes:
    """Serialize one frame record (prefix + header + payload), ready for a single write.

    Parameters
    ----------
    header : JSON-compatible mapping; its ``"arrays"`` key is filled in here
    arrays : name -> array, written in the mapping's order
    encoding : ``"raw"`` or ``"zlib"``
    zlib_level : 0..9, zlib compression level when ``encoding == "zlib"``
    """
    specs = []
    chunks = []
    for name, arr in arrays.items():
        arr = np.asarray(arr)
        data, dtype_str = _encode_array(arr, encoding, zlib_level)
        specs.append(ArraySpec(name, dtype_str, tuple(int(s) for s in arr.shape), encoding, len(data)).to_json())
        chunks.append(data)
    full_header = dict(header)
    full_header["arrays"] = specs
    header_bytes = json.dumps(full_header, separators=(",", ":")).encode("utf-8")
    payload = b"".join(chunks)
    body_crc = zlib.crc32(payload, zlib.crc32(header_bytes))
    lengths = struct.pack("<4sIQ", RECORD_MARKER, len(header_bytes), len(payload))
    prefix = lengths + struct.pack("<II", zlib.crc32(lengths), body_crc)
    return prefix + header_bytes + payload


def decode_prefix(prefix: bytes) -> tuple[int, int, int] | None:
    """Check a 24-byte record prefix.

    Returns
    -------
    ``(header_len, payload_len, body_crc)``, or None if the prefix is damaged (wrong marker,
    prefix CRC mismatch, absurd header length).
    """
    marker, header_len, payload_len, prefix_crc, body_crc = _PREFIX.unpack(prefix)
    if marker != RECORD_MARKER or zlib.crc32(prefix[:16]) != prefix_crc or header_len > _MAX_HEADER_BYTES:
        return None
    return header_len, payload_len, body_crc


def decode_body(header_bytes: bytes, payload: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    """Decode a record's header JSON and arrays (the CRC has been checked by the caller).

    Raises
    ------
    ValueError
        With a short reason when the header or an array does not decode; the reader wraps
        it in :class:`LogCorruptError` naming the file and offset.
    """
    header = json.loads(header_bytes.decode("utf-8"))
    if not isinstance(header, dict) or not isinstance(header.get("arrays"), list):
        raise ValueError("record header is not a JSON object with an 'arrays' list")
    arrays: dict[str, np.ndarray] = {}
    pos = 0
    for spec in header["arrays"]:
        name, dtype_str, shape, enc, nbytes = spec["name"], spec["dtype"], tuple(spec["shape"]), spec["encoding"], int(spec["nbytes"])
        dtype = np.dtype(dtype_str)
        if dtype.kind not in _ALLOWED_KINDS:
            raise ValueError(f"array {name!r} has disallowed dtype {dtype_str!r}")
        chunk = payload[pos : pos + nbytes]
        if len(chunk) != nbytes:
            raise ValueError(f"array {name!r} runs past the payload")
        pos += nbytes
        if enc == "zlib":
            chunk = zlib.decompress(chunk)
        elif enc != "raw":
            raise ValueError(f"array {name!r} has unknown encoding {enc!r}")
        expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if len(chunk) != expected:
            raise ValueError(f"array {name!r}: {len(chunk)} bytes for shape {shape} of {dtype_str}")
        arrays[name] = np.frombuffer(chunk, dtype=dtype).reshape(shape).copy()
    if pos != len(payload):
        raise ValueError(f"{len(payload) - pos} trailing payload bytes")
    return header, arrays


def is_log_dir(path: Path) -> bool:
    """True if ``path`` is a directory with ``meta.json`` naming the OnFly log format."""
    path = Path(path)
    meta = path / META_FILE
    if not (path.is_dir() and meta.is_file() and (path / FRAMES_FILE).is_file()):
        return False
    try:
        return json.loads(meta.read_text(encoding="utf-8")).get("format") == FORMAT_NAME
    except (OSError, ValueError, AttributeError):
        return False
