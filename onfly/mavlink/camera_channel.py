"""Loopback camera handoff: the simulated vehicle's camera, served to the companion over TCP.

A real drone's camera is wired to the companion; the simulated vehicle runs in another
process, so its frames cross a socket. :class:`FrameServer` calls any ``source() ->
Observation`` at ``rate_hz`` and sends each frame to every connected client;
:class:`FrameClient` is an iterable observation source yielding
:class:`onfly.observation.Observation`, the interface every other frame source implements.

Wire format (one frame)
-----------------------
``8-byte big-endian unsigned length`` followed by an ``.npz`` archive (``numpy.savez``, no
pickle) holding ``rgb`` uint8 (H, W, 3), ``depth_m`` float32 (H, W), ``T_world_cam`` (4, 4),
``T_body_cam`` (4, 4), ``intrinsics`` float64 ``[width, height, fx, fy, cx, cy]``, ``t_s``
float64, ``frame_id`` str; when the observation carries a
:class:`vlm.types.FrameAnnotation` also ``ann_instance_ids``, ``ann_depth_m``,
``ann_semantic_ids`` (optional) and ``ann_objects`` (JSON). Clients refuse frames above
``max_frame_bytes`` and archives with missing or mis-shaped fields (:class:`FrameChannelError`).
Listening is restricted to loopback unless ``allow_remote=True``.
"""

from __future__ import annotations

import io
import json
import logging
import socket
import struct
import threading
import time
from typing import Callable, Iterator
from urllib.parse import urlparse

import numpy as np

from onfly.observation import Observation
from planning.camera import PinholeCamera
from vlm.types import FrameAnnotation, VisibleObject

__all__ = ["FrameChannelError", "encode_observation", "decode_observation", "FrameServer", "FrameClient", "parse_tcp_url"]

log = logging.getLogger(__name__)
_HEADER = struct.Struct(">Q")


class FrameChannelError(ValueError):
    """A malformed frame, an oversized frame, or a bad channel URL."""


def parse_tcp_url(url: str) -> tuple[str, int]:
    """``tcp://HOST:PORT`` -> (host, port); raises FrameChannelError naming the URL."""
    parsed = urlparse(url)
    if parsed.scheme != "tcp" or not parsed.hostname or parsed.port is None:
        raise FrameChannelError(f"camera URL must look like tcp://127.0.0.1:PORT, got {url!r}")
    return parsed.hostname, parsed.port


def encode_observation(obs: Observation) -> bytes:
    """One observation as a length-prefixed npz frame (see the module docstring)."""
    cam = obs.camera
    arrays = {
        "rgb": np.ascontiguousarray(obs.rgb, dtype=np.uint8),
        "depth_m": np.ascontiguousarray(obs.depth_m, dtype=np.float32),
        "T_world_cam": np.asarray(obs.T_world_cam, dtype=float),
        "T_body_cam": np.asarray(obs.T_body_cam, dtype=float),
        "intrinsics": np.array([cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy], dtype=float),
        "t_s": np.array(obs.t_s, dtype=float),
        "frame_id": np.array(str(obs.frame_id)),
    }
    ann = obs.annotation
    if isinstance(ann, FrameAnnotation):
        arrays["ann_instance_ids"] = np.asarray(ann.instance_ids)
        arrays["ann_depth_m"] = np.asarray(ann.depth_m, dtype=np.float32)
        if ann.semantic_ids is not None:
            arrays["ann_semantic_ids"] = np.asarray(ann.semantic_ids)
        objects = [o.to_dict() for o in ann.objects.values()]
        arrays["ann_objects"] = np.array(json.dumps(objects))
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    payload = buf.getvalue()
    return _HEADER.pack(len(payload)) + payload


def decode_observation(payload: bytes) -> Observation:
    """Inverse of :func:`encode_observation` without the length prefix."""
    try:
        with np.load(io.BytesIO(payload), allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError) as exc:
        raise FrameChannelError(f"frame is not a valid npz archive: {exc}") from exc
    missing = {"rgb", "depth_m", "T_world_cam", "T_body_cam", "intrinsics", "t_s", "frame_id"} - set(data)
    if missing:
        raise FrameChannelError(f"frame lacks fields {sorted(missing)}")
    intr = data["intrinsics"]
    if intr.shape != (6,):
        raise FrameChannelError(f"intrinsics must have shape (6,), got {intr.shape}")
    try:
        camera = PinholeCamera(int(intr[0]), int(intr[1]), *map(float, intr[2:]))
        annotation = None
        if "ann_instance_ids" in data:
            objs = json.loads(str(data["ann_objects"]))
            objects = {int(o["instance_id"]): VisibleObject.from_dict(o) for o in objs}
            annotation = FrameAnnotation(data["ann_instance_ids"], data["ann_depth_m"], objects, data.get("ann_semantic_ids"))
        return Observation(
            t_s=float(data["t_s"]),
            rgb=data["rgb"],
            depth_m=data["depth_m"],
            T_world_cam=data["T_world_cam"],
            camera=camera,
            frame_id=str(data["frame_id"]),
            T_body_cam=data["T_body_cam"],
            annotation=annotation,
        )
    except (ValueError, KeyError, TypeError) as exc:
        raise FrameChannelError(f"frame fields are malformed: {exc}") from exc


class FrameServer:
    """Serves ``source()`` observations to TCP clients at ``rate_hz`` from its own thread.

    Parameters
    ----------
    source : callable returning an Observation (or None to skip a tick)
    host, port : bind address; port 0 picks a free port (read :attr:`address`)
    rate_hz : frames per second
    allow_remote : permit a non-loopback bind address
    """

    def __init__(self, source: Callable[[], Observation | None], host: str = "127.0.0.1", port: int = 0, rate_hz: float = 10.0, allow_remote: bool = False) -> None:
        if not (rate_hz > 0 and np.isfinite(rate_hz)):
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        if not allow_remote and host not in ("127.0.0.1", "localhost", "::1"):
            raise FrameChannelError(f"camera server binds to loopback only unless allow_remote=True, got host {host!r}")
        self.source = source
        self.rate_hz = float(rate_hz)
        self._sock = socket.create_server((host, int(port)))
        self._sock.settimeout(0.05)
        self.address = self._sock.getsockname()[:2]
        self._clients: list[socket.socket] = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.frames_sent = 0

    @property
    def url(self) -> str:
        return f"tcp://{self.address[0]}:{self.address[1]}"

    def start(self) -> "FrameServer":
        self._threads = [
            threading.Thread(target=self._accept_loop, name="frame-accept", daemon=True),
            threading.Thread(target=self._send_loop, name="frame-send", daemon=True),
        ]
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        for c in self._clients:
            c.close()
        self._sock.close()

    def __enter__(self) -> "FrameServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, addr = self._sock.accept()
            except (socket.timeout, TimeoutError):
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            log.info("camera client %s connected", addr)
            self._clients.append(conn)

    def _send_loop(self) -> None:
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        while not self._stop.wait(max(0.0, next_t - time.monotonic())):
            next_t = max(next_t + period, time.monotonic())
            if not self._clients:
                continue
            try:
                obs = self.source()
            except Exception:
                log.exception("camera source failed; frame skipped")
                continue
            if obs is None:
                continue
            frame = encode_observation(obs)
            for c in list(self._clients):
                try:
                    c.sendall(frame)
                except OSError:
                    self._clients.remove(c)
                    c.close()
            self.frames_sent += 1


class FrameClient:
    """Iterable observation source reading a :class:`FrameServer` (``tcp://HOST:PORT``).

    Iteration ends when the server closes the connection; a malformed frame raises
    :class:`FrameChannelError`; no frame within ``timeout_s`` raises ``TimeoutError``.
    """

    def __init__(self, url: str, timeout_s: float = 5.0, max_frame_bytes: int = 64 * 2**20) -> None:
        self.url = url
        self.host, self.port = parse_tcp_url(url)
        self.timeout_s = float(timeout_s)
        self.max_frame_bytes = int(max_frame_bytes)
        self._sock: socket.socket | None = None

    def connect(self) -> None:
        if self._sock is None:
            try:
                self._sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
            except OSError as exc:
                raise ConnectionError(f"cannot connect to camera {self.url}: {exc}") from exc

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> "FrameClient":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _read_exact(self, n: int) -> bytes | None:
        chunks, got = [], 0
        while got < n:
            chunk = self._sock.recv(min(n - got, 1 << 20))
            if not chunk:
                if got == 0:
                    return None
                raise FrameChannelError(f"camera stream {self.url} ended inside a frame")
            chunks.append(chunk)
            got += len(chunk)
        return b"".join(chunks)

    def read(self) -> Observation | None:
        """The next observation, or None at end of stream."""
        self.connect()
        header = self._read_exact(_HEADER.size)
        if header is None:
            return None
        (n,) = _HEADER.unpack(header)
        if n > self.max_frame_bytes:
            raise FrameChannelError(f"frame of {n} bytes exceeds max_frame_bytes={self.max_frame_bytes}")
        payload = self._read_exact(n)
        if payload is None:
            raise FrameChannelError(f"camera stream {self.url} ended inside a frame")
        return decode_observation(payload)

    def __iter__(self) -> Iterator[Observation]:
        while True:
            obs = self.read()
            if obs is None:
                return
            yield obs
