"""One interface over every recorded source of observations, and a factory that picks the reader.

Kinds
-----
``onfly-log``  a directory written by :class:`onfly.logs.LogWriter` (``meta.json`` + ``frames.bin``)
``tum``        a TUM RGB-D folder (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``)
``ros1-bag``   a ROS 1 ``.bag`` file
``ros2-bag``   a ROS 2 bag directory (``metadata.yaml``), or a ``.db3`` / ``.mcap`` inside one
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Iterator, Protocol, runtime_checkable

from onfly.logs.format import is_log_dir
from onfly.logs.reader import LogReader
from onfly.observation import Observation
from onfly.readers.rosbag import BagConfig, BagReader, resolve_bag_path, BagFormatError
from onfly.readers.tum import TumConfig, TumReader, is_tum_dir

__all__ = ["ObservationSource", "SourceKindError", "SOURCE_KINDS", "detect_kind", "open_source", "known_length"]

#: kind -> what it looks like on disk (used in error messages).
SOURCE_KINDS = {
    "onfly-log": "OnFly log directory (meta.json + frames.bin)",
    "tum": "TUM RGB-D folder (rgb.txt, depth.txt, groundtruth.txt)",
    "ros1-bag": "ROS 1 bag file (*.bag)",
    "ros2-bag": "ROS 2 bag directory (metadata.yaml)",
}


class SourceKindError(ValueError):
    """A path that is no known kind of source, or options that kind does not take."""


@runtime_checkable
class ObservationSource(Protocol):
    """A recorded stream of observations.

    Iterating yields :class:`Observation` in time order; iterating again starts over.
    Sources whose length is known before reading (all readers here) also define
    ``__len__`` (see :func:`known_length`). A source is a context manager; ``close``
    releases any open file and is idempotent.

    Attributes
    ----------
    kind : one of :data:`SOURCE_KINDS` (or another name for sources defined elsewhere)
    path : Path the source reads
    """

    kind: str
    path: Path

    def __iter__(self) -> Iterator[Observation]: ...

    def __enter__(self) -> "ObservationSource": ...

    def __exit__(self, exc_type, exc, tb) -> None: ...

    def close(self) -> None: ...


def known_length(source: Any) -> int | None:
    """``len(source)`` when the source knows it, else None."""
    try:
        return len(source)
    except TypeError:
        return None


def detect_kind(path) -> str:
    """The kind of source at ``path``.

    Raises
    ------
    SourceKindError
        Listing the valid kinds, when the path matches none (or does not exist).
    """
    p = Path(path)
    if not p.exists():
        raise SourceKindError(f"{p}: no such file or directory")
    if is_log_dir(p):
        return "onfly-log"
    if is_tum_dir(p):
        return "tum"
    try:
        return resolve_bag_path(p)[1]
    except BagFormatError:
        pass
    valid = "; ".join(SOURCE_KINDS.values())
    raise SourceKindError(f"{p}: not a recognised observation source (expected one of: {valid})")


def _config(cls, kind: str, options: dict[str, Any]):
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(options) - names)
    if unknown:
        raise SourceKindError(f"option(s) {', '.join(unknown)} do not apply to a {kind} source (valid: {', '.join(sorted(names))})")
    return cls(**options)


def open_source(path, *, kind: str | None = None, **options: Any) -> ObservationSource:
    """Open the right reader for ``path``.

    Parameters
    ----------
    path : a log directory, TUM folder, ``.bag`` file or ROS 2 bag directory
    kind : force a kind instead of detecting it (one of :data:`SOURCE_KINDS`)
    **options : fields of that kind's config (:class:`TumConfig` for ``tum``,
        :class:`BagConfig` for bags; logs take none). Options that are None are ignored, so
        a CLI can pass all of its flags.

    Raises
    ------
    SourceKindError
        Unknown kind, undetectable path, or an option the kind does not take.
    """
    options = {k: v for k, v in options.items() if v is not None}
    if kind is None:
        kind = detect_kind(path)
    elif kind not in SOURCE_KINDS:
        raise SourceKindError(f"unknown source kind {kind!r} (valid: {', '.join(SOURCE_KINDS)})")
    if kind == "onfly-log":
        if options:
            raise SourceKindError(f"option(s) {', '.join(sorted(options))} do not apply to an onfly-log source (it takes none)")
        return LogReader(path)
    if kind == "tum":
        return TumReader(path, _config(TumConfig, kind, options))
    return BagReader(path, _config(BagConfig, kind, options))
