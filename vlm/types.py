"""The backend protocol and the values that cross it.

A backend takes chat messages and images and returns text, with usage and timing. Images are
:class:`VlmImage` values: real backends read only ``rgb``; the simulated VLM may also read the
``annotation`` the embedded world attaches (what the camera saw, never the map). Nothing here
imports ``planning`` or ``onfly``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

__all__ = [
    "ChatMessage",
    "VisibleObject",
    "FrameAnnotation",
    "VlmImage",
    "VisionFeatures",
    "CallStatus",
    "Usage",
    "VlmResponse",
    "VlmBackend",
    "VlmError",
    "VlmConnectionError",
    "VlmHttpError",
    "VlmResponseError",
    "VlmParseError",
]


class VlmError(RuntimeError):
    """Base class of errors raised by the VLM layer's convenience functions."""


class VlmConnectionError(VlmError):
    """The server could not be reached (refused, DNS, reset)."""


class VlmHttpError(VlmError):
    """The server answered with an HTTP error status; carries ``status`` and the body."""

    def __init__(self, message: str, status: int, body: str = "") -> None:
        super().__init__(message)
        self.status = status
        self.body = body


class VlmResponseError(VlmError):
    """The server answered 200 with a body that is not the expected JSON."""


class VlmParseError(VlmError):
    """Model text that does not contain what the prompt asked for; ``raw`` keeps the text."""

    def __init__(self, message: str, raw: str) -> None:
        super().__init__(message)
        self.raw = raw


@dataclass(frozen=True)
class ChatMessage:
    """One chat turn. ``content`` may contain ``<image>`` placeholders, one per image, in order.

    ``role`` is ``system``, ``user`` or ``assistant``. Images referenced by a message are
    passed separately to :meth:`VlmBackend.complete` in the order the placeholders appear
    across all messages.
    """

    role: str
    content: str

    def __post_init__(self) -> None:
        if self.role not in ("system", "user", "assistant"):
            raise ValueError(f"role must be system, user or assistant, got {self.role!r}")


@dataclass(frozen=True)
class VisibleObject:
    """An object instance the camera saw in a frame (embedded world only).

    Attributes
    ----------
    instance_id : int, id in :attr:`FrameAnnotation.instance_ids`
    name : str, e.g. ``"red van"``
    label : str, semantic class, e.g. ``"van"``
    aliases : tuple of str, other names a person might use
    target : bool, False for what a task never names as a goal (ground, walls, roofs, the
        scene file's ``target = false``); the simulated VLM never grounds a goal on it
    moving : bool, the instance was moving when the frame was taken (a walking actor of the
        embedded world); a standing person or any static object is False
    """

    instance_id: int
    name: str
    label: str
    aliases: tuple[str, ...] = ()
    target: bool = True
    moving: bool = False

    def to_dict(self) -> dict:
        """JSON form (logs, the MAVLink camera channel)."""
        return {"instance_id": int(self.instance_id), "name": self.name, "label": self.label,
                "aliases": list(self.aliases), "target": bool(self.target), "moving": bool(self.moving)}

    @classmethod
    def from_dict(cls, d: dict) -> "VisibleObject":
        """Inverse of :meth:`to_dict`; ``aliases``, ``target`` and ``moving`` are optional
        (older logs carry none: every object then counts as a possible target, standing)."""
        return cls(int(d["instance_id"]), str(d["name"]), str(d["label"]), tuple(d.get("aliases", ())), bool(d.get("target", True)),
                   bool(d.get("moving", False)))


@dataclass(frozen=True, eq=False)
class FrameAnnotation:
    """What the simulated camera saw: per-pixel ids and z-depth, and the visible instances.

    Attributes
    ----------
    instance_ids : int array (H, W); 0 means background / sky
    depth_m : float32 array (H, W), z-depth in metres; 0/NaN/inf = no reading
    objects : mapping instance_id -> VisibleObject, only instances present in ``instance_ids``
    semantic_ids : optional int array (H, W) of label ids
    """

    instance_ids: np.ndarray
    depth_m: np.ndarray
    objects: Mapping[int, VisibleObject]
    semantic_ids: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class VlmImage:
    """An image handed to a backend.

    Attributes
    ----------
    rgb : uint8 array (H, W, 3)
    frame_id : str, unique per camera frame; the feature cache keys on it
    annotation : optional FrameAnnotation, read only by the simulated VLM
    """

    rgb: np.ndarray
    frame_id: str
    annotation: FrameAnnotation | None = None

    def __post_init__(self) -> None:
        rgb = np.asarray(self.rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be uint8 with shape (H, W, 3), got {rgb.dtype} {rgb.shape}")

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return (int(self.rgb.shape[1]), int(self.rgb.shape[0]))


@dataclass(frozen=True, eq=False)
class VisionFeatures:
    """Per-patch vision features of one image.

    Attributes
    ----------
    grid : float32 array (Hp, Wp, C), one feature vector per patch
    patch_px : float, side of one patch in pixels of the *original* image (patch (i, j)
        covers rows ``[i * patch_px, (i + 1) * patch_px)`` and the same for columns)
    image_size : (width, height) of the original image in pixels
    source : str, what produced them (e.g. ``"qwen2_5_vl.visual"``, ``"sim:labels"``)
    """

    grid: np.ndarray
    patch_px: float
    image_size: tuple[int, int]
    source: str = ""

    def patch_of(self, u: float, v: float) -> tuple[int, int]:
        """Patch ``(row, col)`` holding pixel ``(u, v)``, clipped to the grid."""
        hp, wp = self.grid.shape[:2]
        return (int(np.clip(v // self.patch_px, 0, hp - 1)), int(np.clip(u // self.patch_px, 0, wp - 1)))


class CallStatus(str, Enum):
    OK = "ok"
    TIMEOUT = "timeout"
    ERROR = "error"


@dataclass(frozen=True)
class Usage:
    """Token counts for one call; ``cached_tokens`` is the prompt prefix served from cache."""

    prompt_tokens: int = 0
    completion_tokens: int = 0
    cached_tokens: int = 0


@dataclass(frozen=True)
class VlmResponse:
    """Outcome of one call. ``text`` is empty unless ``status`` is OK.

    ``latency_s`` is measured wall time for real backends and the modelled latency for the
    simulated VLM; ``error`` says what went wrong for TIMEOUT / ERROR.
    """

    status: CallStatus
    text: str = ""
    usage: Usage = field(default_factory=Usage)
    latency_s: float = 0.0
    error: str = ""

    @property
    def ok(self) -> bool:
        return self.status is CallStatus.OK


@runtime_checkable
class VlmBackend(Protocol):
    """What every backend offers. Backends are context managers (``close`` on exit)."""

    name: str

    def complete(
        self,
        messages: Sequence[ChatMessage],
        images: Sequence[VlmImage] = (),
        *,
        deadline_s: float | None = None,
        json_schema: dict | None = None,
        max_new_tokens: int = 64,
        cache_key: str | None = None,
    ) -> VlmResponse:
        """Answer the chat. Never raises for a timeout or a server fault: returns a response
        with status TIMEOUT or ERROR. ``cache_key`` names a conversation stream (e.g. the
        decision or monitoring agent) whose prompt prefix the backend may keep cached."""
        ...

    def features(self, image: VlmImage) -> VisionFeatures | None:
        """Patch features of an image, or None if this backend has none."""
        ...

    def close(self) -> None: ...
