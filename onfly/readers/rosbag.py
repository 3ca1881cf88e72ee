"""Reader of ROS 1 ``.bag`` files and ROS 2 bag directories, through ``rosbags.highlevel.AnyReader``.

Messages understood
-------------------
- depth: ``sensor_msgs/Image`` with encoding ``16UC1`` / ``mono16`` (millimetres by REP 118;
  ``BagConfig.depth_scale_16u`` values per metre) or ``32FC1`` (metres); 0 / NaN = no reading,
  and a 16-bit 65535 (saturated) too (:func:`planning.camera.depth_from_counts`).
- colour: ``sensor_msgs/Image`` with encoding ``rgb8``, ``bgr8``, ``rgba8`` or ``bgra8``.
- intrinsics: ``sensor_msgs/CameraInfo`` (first message; ``K`` / ``k``; distortion is
  ignored with a warning when non-zero), or ``BagConfig.intrinsics``.
- pose: ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``,
  ``geometry_msgs/PoseWithCovarianceStamped``, or ``tf2_msgs/TFMessage`` filtered to the
  transform ``tf_parent_frame -> tf_child_frame`` (used inverted when stored the other way
  round; chains of transforms are not composed).

Times are the messages' ``header.stamp``. Each depth image becomes one observation at its
stamp: the colour image is associated by nearest stamp within ``max_difference_s`` (as
TUM's ``associate.py``), the pose is interpolated there (linear position, slerp rotation).
The pose topic is taken to describe the frame ``T_pose_cam`` maps the camera optical frame
into (identity by default: the poses are camera optical poses, as in TUM), so
``T_world_cam = T_world_pose @ T_pose_cam``.

Topics left unset are chosen when the choice is unambiguous (one depth-named image topic, one
other image topic, one CameraInfo topic or the depth topic's sibling ``camera_info``, one
pose-like topic); otherwise :class:`BagFormatError` lists the candidates. All checks that do
not need pixel data run when the reader is built, so a bad bag fails before the first frame.
"""

from __future__ import annotations

import logging
import posixpath
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.typesys import Stores, get_typestore

from onfly.observation import Observation
from onfly.readers.poses import PoseTrack, associate
from planning.camera import PinholeCamera, depth_from_counts
from planning.frames import T_BODY_CAM, check_transform, invert_transform, make_transform, matrix_from_quat, quat_from_matrix

__all__ = [
    "BagFormatError",
    "BagConfig",
    "BagReader",
    "BagSummary",
    "TopicSummary",
    "bag_summary",
    "resolve_bag_path",
    "image_to_array",
    "DEPTH_ENCODINGS",
    "RGB_ENCODINGS",
]

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_COV_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_COV_STAMPED, TF_MESSAGE)

DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
RGB_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
_ENCODING_LAYOUT = {
    # encoding: (numpy dtype, channels)
    "16UC1": (np.uint16, 1),
    "mono16": (np.uint16, 1),
    "32FC1": (np.float32, 1),
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
}


class BagFormatError(ValueError):
    """A bag that lacks a named topic, holds the wrong message type or encoding, or does not
    open; the message names the bag and the topic."""


def _default_mount() -> np.ndarray:
    return T_BODY_CAM.copy()


@dataclass(frozen=True, eq=False)
class BagConfig:
    """Options of :class:`BagReader` (topics left None are chosen when unambiguous).

    Attributes
    ----------
    depth_topic, rgb_topic, camera_info_topic, pose_topic : topic names or None
    tf_parent_frame, tf_child_frame : the transform to read when the pose topic is a
        ``tf2_msgs/TFMessage`` topic (leading ``/`` ignored)
    max_difference_s : association tolerance between depth, colour and pose stamps, seconds
    pose_max_gap_s : largest gap between pose samples to interpolate across, seconds
    depth_scale_16u : ``16UC1`` depth values per metre (1000: millimetres)
    intrinsics : ``(fx, fy, cx, cy)`` pixels, overriding CameraInfo, or None
    T_pose_cam : (4, 4) camera optical frame -> the frame the pose topic describes
    T_body_cam : (4, 4) camera mount given to every observation
    """

    depth_topic: str | None = None
    rgb_topic: str | None = None
    camera_info_topic: str | None = None
    pose_topic: str | None = None
    tf_parent_frame: str | None = None
    tf_child_frame: str | None = None
    max_difference_s: float = 0.02
    pose_max_gap_s: float = 0.5
    depth_scale_16u: float = 1000.0
    intrinsics: tuple[float, float, float, float] | None = None
    T_pose_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    T_body_cam: np.ndarray = field(default_factory=_default_mount)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.max_difference_s) and self.max_difference_s > 0):
            raise ValueError(f"BagConfig.max_difference_s must be positive, got {self.max_difference_s}")
        if not (self.pose_max_gap_s > 0):
            raise ValueError(f"BagConfig.pose_max_gap_s must be positive, got {self.pose_max_gap_s}")
        if not (np.isfinite(self.depth_scale_16u) and self.depth_scale_16u > 0):
            raise ValueError(f"BagConfig.depth_scale_16u must be positive, got {self.depth_scale_16u}")
        if self.intrinsics is not None:
            k = tuple(float(v) for v in self.intrinsics)
            if len(k) != 4:
                raise ValueError(f"BagConfig.intrinsics must be (fx, fy, cx, cy), got {self.intrinsics}")
            object.__setattr__(self, "intrinsics", k)
        if (self.tf_parent_frame is None) != (self.tf_child_frame is None):
            raise ValueError("BagConfig.tf_parent_frame and tf_child_frame must be given together")
        object.__setattr__(self, "T_pose_cam", check_transform(self.T_pose_cam, "BagConfig.T_pose_cam"))
        object.__setattr__(self, "T_body_cam", check_transform(self.T_body_cam, "BagConfig.T_body_cam"))


# -- opening -----------------------------------------------------------------------------------


def resolve_bag_path(path) -> tuple[Path, str]:
    """The path AnyReader takes and the kind: ``"ros1-bag"`` or ``"ros2-bag"``.

    Accepts a ROS 1 ``.bag`` file, a ROS 2 bag directory (with ``metadata.yaml``), or a
    ``.db3`` / ``.mcap`` file inside such a directory.
    """
    p = Path(path)
    if not p.exists():
        raise BagFormatError(f"{p}: no such file or directory")
    if p.is_file() and p.suffix == ".bag":
        return p, "ros1-bag"
    if p.is_dir() and (p / "metadata.yaml").is_file():
        return p, "ros2-bag"
    if p.is_file() and p.suffix in (".db3", ".mcap") and (p.parent / "metadata.yaml").is_file():
        return p.parent, "ros2-bag"
    raise BagFormatError(f"{p}: not a ROS 1 .bag file or a ROS 2 bag directory (with metadata.yaml)")


def _open_any(path: Path, kind: str) -> AnyReader:
    default = get_typestore(Stores.ROS2_HUMBLE) if kind == "ros2-bag" else None
    try:
        reader = AnyReader([path], default_typestore=default)
        reader.open()
    except (AnyReaderError, OSError, KeyError, ValueError) as exc:
        raise BagFormatError(f"{path}: cannot open bag ({exc})") from None
    return reader


@dataclass(frozen=True)
class TopicSummary:
    """One topic of a bag: name, message type, message count."""

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagSummary:
    """What a bag holds (``onfly bag-info``).

    Attributes
    ----------
    path, kind : the bag and ``"ros1-bag"`` / ``"ros2-bag"``
    start_ns, end_ns : first and last message receive time, nanoseconds (0 when empty)
    messages : total message count
    topics : per-topic summaries sorted by name
    """

    path: Path
    kind: str
    start_ns: int
    end_ns: int
    messages: int
    topics: tuple[TopicSummary, ...]

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9


def bag_summary(path) -> BagSummary:
    """Topics, types, counts and time span of a ROS 1 or ROS 2 bag."""
    bag_path, kind = resolve_bag_path(path)
    reader = _open_any(bag_path, kind)
    try:
        count = reader.message_count
        topics = tuple(
            TopicSummary(name, info.msgtype or "<mixed>", info.msgcount) for name, info in sorted(reader.topics.items())
        )
        if count:
            # end_time is "after the latest message" (latest + 1 ns) in rosbags.
            start, end = reader.start_time, reader.end_time - 1
        else:
            start = end = 0
    finally:
        reader.close()
    return BagSummary(bag_path, kind, int(start), int(max(end, start)), int(count), topics)


# -- decoding ----------------------------------------------------------------------------------


def _stamp_ns(msg: Any) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def image_to_array(msg: Any, topic: str, allowed: tuple[str, ...]) -> np.ndarray:
    """Pixels of a ``sensor_msgs/Image`` as a numpy array, row padding (``step``) removed.

    Returns
    -------
    array (H, W) for one channel, (H, W, C) otherwise, dtype of the encoding in native order

    Raises
    ------
    BagFormatError
        Encoding not in ``allowed`` or data shorter than ``height * step``, naming the topic.
    """
    enc = msg.encoding
    if enc not in allowed:
        raise BagFormatError(f"topic {topic}: image encoding {enc!r} is not supported here (expected one of {', '.join(allowed)})")
    dtype, channels = _ENCODING_LAYOUT[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = np.dtype(dtype).itemsize
    row_bytes = w * channels * itemsize
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if step < row_bytes or data.size < h * step:
        raise BagFormatError(f"topic {topic}: image data of {data.size} bytes does not hold {h} rows of step {step} ({w} x {channels} x {itemsize} bytes)")
    rows = data[: h * step].reshape(h, step)[:, :row_bytes]
    order = ">" if msg.is_bigendian else "<"
    arr = np.ascontiguousarray(rows).view(np.dtype(dtype).newbyteorder(order) if itemsize > 1 else dtype)
    arr = arr.astype(dtype, copy=False).reshape((h, w) if channels == 1 else (h, w, channels))
    return arr


def _depth_m(arr: np.ndarray, encoding: str, scale_16u: float) -> np.ndarray:
    if encoding == "32FC1":
        return arr.astype(np.float32, copy=False)
    return depth_from_counts(arr, scale_16u)  # 0 and 65535: no reading


def _rgb(arr: np.ndarray, encoding: str) -> np.ndarray:
    if encoding in ("bgr8", "bgra8"):
        arr = arr[:, :, 2::-1]
    return np.ascontiguousarray(arr[:, :, :3])


def _pose_of(position: Any, orientation: Any) -> tuple[np.ndarray, np.ndarray]:
    p = np.array([position.x, position.y, position.z], dtype=float)
    q = np.array([orientation.w, orientation.x, orientation.y, orientation.z], dtype=float)
    return p, q


def _strip(frame: str) -> str:
    return frame.lstrip("/")


# -- the reader --------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Frame:
    stamp_ns: int
    depth_ordinal: int
    rgb_ordinal: int
    T_world_cam: np.ndarray


class BagReader:
    """Observations of a ROS 1 or ROS 2 bag, one per associated depth image.

    Parameters
    ----------
    path : ``.bag`` file or ROS 2 bag directory
    config : :class:`BagConfig`

    Attributes
    ----------
    kind : ``"ros1-bag"`` or ``"ros2-bag"``
    topics : dict role -> topic actually used (``depth``, ``rgb``, ``camera_info``, ``pose``)
    camera : PinholeCamera
    poses : PoseTrack of the pose topic (before ``T_pose_cam``)
    dropped : how many depth images were dropped and why
    """

    def __init__(self, path, config: BagConfig = BagConfig()) -> None:
        self.path, self.kind = resolve_bag_path(path)
        self.config = config
        self._reader = _open_any(self.path, self.kind)
        try:
            self._setup()
        except BaseException:
            self.close()
            raise

    # -- topic choice ----------------------------------------------------------------------------
    def _fail(self, message: str) -> BagFormatError:
        return BagFormatError(f"{self.path}: {message}")

    def _topic_types(self) -> dict[str, str]:
        return {name: info.msgtype or "" for name, info in self._reader.topics.items()}

    def _check_topic(self, role: str, topic: str, types: tuple[str, ...]) -> str:
        have = self._topic_types()
        if topic not in have:
            listing = ", ".join(f"{n} ({t})" for n, t in sorted(have.items())) or "none"
            raise self._fail(f"no topic {topic} for {role} (topics: {listing})")
        if have[topic] not in types:
            raise self._fail(f"topic {topic} for {role} has type {have[topic]}, expected {' or '.join(types)}")
        return topic

    def _choose(self, role: str, option: str, candidates: list[str]) -> str:
        if len(candidates) == 1:
            return candidates[0]
        if not candidates:
            raise self._fail(f"no topic for {role} found; pass {option}")
        raise self._fail(f"several topics could be {role} ({', '.join(sorted(candidates))}); pass {option}")

    def _select_topics(self) -> dict[str, str | None]:
        cfg = self.config
        types = self._topic_types()
        images = [n for n, t in types.items() if t == IMAGE]
        if cfg.depth_topic is not None:
            depth = self._check_topic("depth", cfg.depth_topic, (IMAGE,))
        else:
            depth = self._choose("depth", "depth_topic", [n for n in images if "depth" in n.lower()])
        if cfg.rgb_topic is not None:
            rgb = self._check_topic("rgb", cfg.rgb_topic, (IMAGE,))
        else:
            rgb = self._choose("rgb", "rgb_topic", [n for n in images if "depth" not in n.lower()])
        info: str | None = None
        if cfg.camera_info_topic is not None:
            info = self._check_topic("camera_info", cfg.camera_info_topic, (CAMERA_INFO,))
        elif cfg.intrinsics is None:
            sibling = posixpath.join(posixpath.dirname(depth), "camera_info")
            infos = [n for n, t in types.items() if t == CAMERA_INFO]
            info = sibling if sibling in infos else self._choose("camera_info", "camera_info_topic or intrinsics", infos)
        if cfg.pose_topic is not None:
            pose = self._check_topic("pose", cfg.pose_topic, POSE_TYPES)
        else:
            poses = [n for n, t in types.items() if t in (ODOMETRY, POSE_STAMPED, POSE_COV_STAMPED)]
            if not poses and cfg.tf_parent_frame is not None:
                poses = [n for n, t in types.items() if t == TF_MESSAGE and n in ("/tf", "/tf_static", "tf")]
            pose = self._choose("pose", "pose_topic (or tf_parent_frame/tf_child_frame with a /tf topic)", poses)
        if types[pose] == TF_MESSAGE and cfg.tf_parent_frame is None:
            raise self._fail(f"topic {pose} is a TF topic; pass tf_parent_frame and tf_child_frame")
        return {"depth": depth, "rgb": rgb, "camera_info": info, "pose": pose}

    def _messages(self, topic: str) -> Iterator[tuple[int, Any]]:
        conns = [c for c in self._reader.connections if c.topic == topic]
        for conn, bag_ns, raw in self._reader.messages(connections=conns):
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
            except AnyReaderError as exc:
                raise self._fail(f"topic {topic}: message at {bag_ns} ns does not deserialize ({exc})") from None
            yield bag_ns, msg

    # -- set-up pass -----------------------------------------------------------------------------
    def _setup(self) -> None:
        cfg = self.config
        self.topics = self._select_topics()
        self.poses = self._read_poses(self.topics["pose"])
        depth_stamps, size = self._read_image_stamps(self.topics["depth"], DEPTH_ENCODINGS)
        rgb_stamps, rgb_size = self._read_image_stamps(self.topics["rgb"], RGB_ENCODINGS)
        if size != rgb_size:
            raise self._fail(f"depth {self.topics['depth']} is {size[1]}x{size[0]} but rgb {self.topics['rgb']} is {rgb_size[1]}x{rgb_size[0]}")
        self.camera = self._camera(size)

        t_depth = np.array(depth_stamps, dtype=np.int64) / 1e9
        t_rgb = np.array(rgb_stamps, dtype=np.int64) / 1e9
        pairs = dict(associate(t_depth, t_rgb, cfg.max_difference_s))
        self.dropped = {"no_rgb": len(depth_stamps) - len(pairs), "no_pose": 0}
        frames = []
        for i in sorted(pairs, key=lambda i: (depth_stamps[i], i)):
            T = self.poses.interpolate(depth_stamps[i] / 1e9, max_gap_s=cfg.pose_max_gap_s, end_tolerance_s=cfg.max_difference_s)
            if T is None:
                self.dropped["no_pose"] += 1
                continue
            frames.append(_Frame(depth_stamps[i], i, pairs[i], T @ cfg.T_pose_cam))
        if any(self.dropped.values()):
            log.warning("%s: dropped depth images: %s", self.path, self.dropped)
        if not frames:
            raise self._fail(
                f"no depth image on {self.topics['depth']} has an rgb image on {self.topics['rgb']} within "
                f"{cfg.max_difference_s} s and a pose on {self.topics['pose']}"
            )
        self._frames = frames

    def _read_image_stamps(self, topic: str, allowed: tuple[str, ...]) -> tuple[list[int], tuple[int, int]]:
        stamps, size = [], None
        for _, msg in self._messages(topic):
            if msg.encoding not in allowed:
                raise self._fail(f"topic {topic}: image encoding {msg.encoding!r} is not supported (expected one of {', '.join(allowed)})")
            s = (int(msg.height), int(msg.width))
            if size is None:
                size = s
            elif s != size:
                raise self._fail(f"topic {topic}: image size changes from {size} to {s}")
            stamps.append(_stamp_ns(msg))
        if size is None:
            raise self._fail(f"topic {topic} has no messages")
        return stamps, size

    def _camera(self, size: tuple[int, int]) -> PinholeCamera:
        h, w = size
        if self.config.intrinsics is not None:
            fx, fy, cx, cy = self.config.intrinsics
            try:
                return PinholeCamera(w, h, fx, fy, cx, cy)
            except ValueError as exc:
                raise self._fail(f"BagConfig.intrinsics {self.config.intrinsics} do not fit the {w}x{h} images: {exc}") from None
        topic = self.topics["camera_info"]
        for _, msg in self._messages(topic):
            K = np.asarray(msg.K if hasattr(msg, "K") else msg.k, dtype=float).reshape(-1)
            D = np.asarray(msg.D if hasattr(msg, "D") else msg.d, dtype=float).reshape(-1)
            if K.size != 9 or not np.all(np.isfinite(K)) or K[0] <= 0 or K[4] <= 0:
                raise self._fail(f"topic {topic}: CameraInfo K is not a valid intrinsic matrix: {K.tolist()}")
            if (int(msg.width), int(msg.height)) not in ((w, h), (0, 0)):
                raise self._fail(f"topic {topic}: CameraInfo is {msg.width}x{msg.height} but images are {w}x{h}")
            if D.size and np.any(D != 0):
                log.warning("%s: %s has distortion %s; images are used as if undistorted", self.path, topic, D.tolist())
            try:
                return PinholeCamera(w, h, K[0], K[4], K[2], K[5])
            except ValueError as exc:  # a principal point off the image
                raise self._fail(f"topic {topic}: CameraInfo does not fit the {w}x{h} images: {exc}") from None
        raise self._fail(f"topic {topic} has no messages")

    def _read_poses(self, topic: str) -> PoseTrack:
        msgtype = self._topic_types()[topic]
        t, ps, qs = [], [], []
        pairs_seen: set[tuple[str, str]] = set()
        parent = _strip(self.config.tf_parent_frame or "")
        child = _strip(self.config.tf_child_frame or "")
        for _, msg in self._messages(topic):
            if msgtype == TF_MESSAGE:
                for tr in msg.transforms:
                    a, b = _strip(tr.header.frame_id), _strip(tr.child_frame_id)
                    pairs_seen.add((a, b))
                    if (a, b) not in ((parent, child), (child, parent)):
                        continue
                    T = make_transform(matrix_from_quat([tr.transform.rotation.w, tr.transform.rotation.x, tr.transform.rotation.y, tr.transform.rotation.z]), [tr.transform.translation.x, tr.transform.translation.y, tr.transform.translation.z])
                    if (a, b) == (child, parent):
                        T = invert_transform(T)
                    t.append(_stamp_ns(tr))
                    ps.append(T[:3, 3])
                    qs.append(quat_from_matrix(T[:3, :3]))
                continue
            pose = msg.pose.pose if msgtype in (ODOMETRY, POSE_COV_STAMPED) else msg.pose
            p, q = _pose_of(pose.position, pose.orientation)
            if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q)) and np.linalg.norm(q) > 1e-6):
                raise self._fail(f"topic {topic}: invalid pose at stamp {_stamp_ns(msg)} ns (position {p.tolist()}, quaternion wxyz {q.tolist()})")
            t.append(_stamp_ns(msg))
            ps.append(p)
            qs.append(q)
        if not t:
            if msgtype == TF_MESSAGE:
                seen = ", ".join(f"{a}->{b}" for a, b in sorted(pairs_seen)) or "none"
                raise self._fail(f"topic {topic} has no transform {parent}->{child} (transforms seen: {seen})")
            raise self._fail(f"topic {topic} has no messages")
        return PoseTrack.from_samples(np.array(t, dtype=np.int64) / 1e9, ps, qs)

    # -- protocol --------------------------------------------------------------------------------
    def __enter__(self) -> "BagReader":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def close(self) -> None:
        """Close the underlying bag. Idempotent."""
        reader, self._reader = getattr(self, "_reader", None), None
        if reader is not None and reader.stack is not None:
            reader.close()

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def timestamps_s(self) -> np.ndarray:
        """Depth stamps of the frames this reader yields, shape (n,), seconds."""
        return np.array([f.stamp_ns for f in self._frames], dtype=np.int64) / 1e9

    def __iter__(self) -> Iterator[Observation]:
        if self._reader is None:
            raise self._fail("reader is closed")
        cfg = self.config
        depth_topic, rgb_topic = self.topics["depth"], self.topics["rgb"]
        need_depth = {f.depth_ordinal for f in self._frames}
        need_rgb = {f.rgb_ordinal for f in self._frames}
        depth_buf: dict[int, np.ndarray] = {}
        rgb_buf: dict[int, np.ndarray] = {}
        counters = {depth_topic: 0, rgb_topic: 0}
        conns = [c for c in self._reader.connections if c.topic in (depth_topic, rgb_topic)]
        nxt = 0
        for conn, bag_ns, raw in self._reader.messages(connections=conns):
            ordinal = counters[conn.topic]
            counters[conn.topic] += 1
            is_depth = conn.topic == depth_topic
            if ordinal not in (need_depth if is_depth else need_rgb):
                continue
            try:
                msg = self._reader.deserialize(raw, conn.msgtype)
            except AnyReaderError as exc:
                raise self._fail(f"topic {conn.topic}: message at {bag_ns} ns does not deserialize ({exc})") from None
            if is_depth:
                depth_buf[ordinal] = _depth_m(image_to_array(msg, conn.topic, DEPTH_ENCODINGS), msg.encoding, cfg.depth_scale_16u)
            else:
                rgb_buf[ordinal] = _rgb(image_to_array(msg, conn.topic, RGB_ENCODINGS), msg.encoding)
            while nxt < len(self._frames):
                f = self._frames[nxt]
                if f.depth_ordinal not in depth_buf or f.rgb_ordinal not in rgb_buf:
                    break
                yield Observation(
                    t_s=f.stamp_ns / 1e9,
                    rgb=rgb_buf.pop(f.rgb_ordinal),
                    depth_m=depth_buf.pop(f.depth_ordinal),
                    T_world_cam=f.T_world_cam,
                    camera=self.camera,
                    frame_id=f"{self.kind}:{self.path.name}:{depth_topic}:{f.stamp_ns}",
                    T_body_cam=cfg.T_body_cam,
                )
                nxt += 1
        if nxt < len(self._frames):
            raise self._fail(f"{len(self._frames) - nxt} frames indexed at open could not be read back (bag changed while open?)")
