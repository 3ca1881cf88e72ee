"""The MAVLink link: one small protocol, a pymavlink-backed implementation and an in-memory fake.

A :class:`Link` moves whole MAVLink 2 messages between this process and one peer. It is a
context manager with ``connect`` / ``close`` / ``is_connected`` (LeRobot device style), and
``recv`` only ever returns well-formed messages: corrupted bytes are counted in
:attr:`Link.stats` and dropped, never raised.

Implementations
---------------
- :class:`MavlinkLink` wraps ``pymavlink.mavutil.mavlink_connection`` and accepts its URL
  spellings: ``udpin:HOST:PORT`` (listen; replies go to every peer that has sent to us, which is
  mavutil's behaviour), ``udpout:HOST:PORT`` (send to), ``tcp:HOST:PORT`` (connect),
  ``tcpin:HOST:PORT`` (accept one client), and a serial device path (``/dev/ttyACM0``, with
  ``baud``). The encoder/parser is always the MAVLink 2 ``ardupilotmega`` dialect (a superset of
  ``common``; it parses MAVLink 1 frames too), chosen explicitly rather than through mavutil's
  ``MAVLINK20`` environment flag.
- :class:`MemoryLink` (from :func:`memory_link_pair`) is the fake for tests: two endpoints joined
  by byte queues, encoding and parsing real MAVLink bytes, with :meth:`MemoryLink.inject_bytes`
  for corrupted input and :meth:`MemoryLink.set_cut` to drop all traffic.
"""

from __future__ import annotations

import abc
import collections
import logging
import queue
import select
import threading
import time
from dataclasses import dataclass

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

__all__ = [
    "LinkError",
    "LinkLostError",
    "LinkStats",
    "Link",
    "MavlinkLink",
    "MemoryLink",
    "memory_link_pair",
    "mavlink2",
]

log = logging.getLogger(__name__)

_NETWORK_PREFIXES = ("udpin:", "udpout:", "tcp:", "tcpin:")


class LinkError(ConnectionError):
    """A link that cannot be opened or used (bad URL, closed link, missing serial support)."""


class LinkLostError(LinkError):
    """The peer went silent or the transport failed while the link was in use."""


@dataclass
class LinkStats:
    """Traffic counters of one link (plain counters; read them, do not rely on atomicity).

    Attributes
    ----------
    messages_in : int, well-formed messages received
    bad_in : int, corrupted or unparseable frames dropped
    messages_out : int, messages sent
    """

    messages_in: int = 0
    bad_in: int = 0
    messages_out: int = 0


class Link(abc.ABC):
    """One MAVLink 2 connection to one peer.

    Messages are built with the encoder :attr:`mav` (``link.mav.heartbeat_encode(...)``), which
    signs them with ``source_system`` / ``source_component``, and sent with :meth:`send`.
    ``send`` is thread-safe; ``recv`` is meant for one reader thread.
    """

    def __init__(self, source_system: int, source_component: int) -> None:
        for name, val in (("source_system", source_system), ("source_component", source_component)):
            if not 0 <= int(val) <= 255:
                raise ValueError(f"{name} must be in [0, 255], got {val}")
        self.source_system = int(source_system)
        self.source_component = int(source_component)
        self.stats = LinkStats()
        self._send_lock = threading.Lock()

    # -- lifecycle --------------------------------------------------------------------------
    @abc.abstractmethod
    def connect(self) -> None:
        """Open the transport. Raises :class:`LinkError` if it cannot be opened."""

    @abc.abstractmethod
    def close(self) -> None:
        """Close the transport; idempotent."""

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool:
        """True between a successful :meth:`connect` and :meth:`close`."""

    def __enter__(self) -> "Link":
        if not self.is_connected:
            self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- traffic ----------------------------------------------------------------------------
    @property
    @abc.abstractmethod
    def mav(self) -> mavlink2.MAVLink:
        """The MAVLink 2 encoder of this end (build messages with its ``*_encode`` methods)."""

    def send(self, msg: mavlink2.MAVLink_message) -> None:
        """Send one message. Raises :class:`LinkError` if the link is closed."""
        if not self.is_connected:
            raise LinkError("send on a closed link")
        with self._send_lock:
            try:
                self.mav.send(msg)
            except OSError as exc:
                raise LinkLostError(f"send failed: {exc}") from exc
        self.stats.messages_out += 1

    def recv(self, timeout_s: float) -> mavlink2.MAVLink_message | None:
        """The next well-formed message, or None if none arrived within ``timeout_s`` seconds.

        Corrupted frames (``BAD_DATA``) are counted in ``stats.bad_in`` and skipped.
        """
        if not self.is_connected:
            raise LinkError("recv on a closed link")
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        while True:
            msg = self._poll()
            if msg is not None:
                if msg.get_type() == "BAD_DATA":
                    self.stats.bad_in += 1
                    continue
                self.stats.messages_in += 1
                return msg
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._wait(remaining)

    @abc.abstractmethod
    def _poll(self) -> mavlink2.MAVLink_message | None:
        """One parsed message (possibly BAD_DATA) if available now, else None."""

    @abc.abstractmethod
    def _wait(self, timeout_s: float) -> None:
        """Block until bytes may be available or ``timeout_s`` passes."""


class MavlinkLink(Link):
    """A :class:`Link` over ``pymavlink.mavutil.mavlink_connection``.

    Parameters
    ----------
    url : str, ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``tcp:HOST:PORT``, ``tcpin:HOST:PORT``
        or a serial device path
    source_system, source_component : ids this end signs its messages with
    baud : int, serial baud rate (ignored for network URLs)
    """

    def __init__(self, url: str, source_system: int, source_component: int, baud: int = 921600) -> None:
        super().__init__(source_system, source_component)
        if not isinstance(url, str) or not url:
            raise LinkError(f"link URL must be a non-empty string, got {url!r}")
        if not url.startswith(_NETWORK_PREFIXES) and not url.startswith("/dev/") and not url.upper().startswith("COM"):
            raise LinkError(
                f"unsupported link URL {url!r}; use udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, "
                "tcpin:HOST:PORT or a serial device path"
            )
        self.url = url
        self.baud = int(baud)
        self._conn = None

    def connect(self) -> None:
        if self._conn is not None:
            return
        serial = not self.url.startswith(_NETWORK_PREFIXES)
        if serial:
            try:
                import serial as _pyserial  # noqa: F401  (pymavlink needs pyserial for serial ports)
            except ImportError as exc:
                raise LinkError(f"serial link {self.url!r} needs the pyserial package, which is not installed") from exc
        if self.url.startswith("udpin:"):
            _check_udp_port_free(self.url)
        try:
            conn = mavutil.mavlink_connection(
                self.url,
                baud=self.baud,
                source_system=self.source_system,
                source_component=self.source_component,
                autoreconnect=False,
            )
        except (OSError, ValueError) as exc:
            raise LinkError(f"cannot open MAVLink link {self.url!r}: {exc}") from exc
        # Explicit MAVLink 2 encoder/parser (parses MAVLink 1 frames as well); never let mavutil
        # switch dialects through its process-wide environment flag.
        conn.mav = mavlink2.MAVLink(conn, srcSystem=self.source_system, srcComponent=self.source_component)
        conn.mav.robust_parsing = True
        conn.WIRE_PROTOCOL_VERSION = "2.0"
        conn.first_byte = False
        self._conn = conn
        log.info("MAVLink link open on %s as %d/%d", self.url, self.source_system, self.source_component)

    def close(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except OSError as exc:  # closing a dead socket is not worth raising
                log.debug("closing %s: %s", self.url, exc)

    @property
    def is_connected(self) -> bool:
        return self._conn is not None

    @property
    def mav(self) -> mavlink2.MAVLink:
        if self._conn is None:
            raise LinkError(f"link {self.url!r} is not connected")
        return self._conn.mav

    @property
    def local_address(self) -> tuple[str, int] | None:
        """(host, port) this end's socket is bound to (network links), else None."""
        sock = getattr(self._conn, "port", None)
        if sock is None or not hasattr(sock, "getsockname"):
            return None
        return sock.getsockname()

    def _poll(self):
        conn = self._conn
        if conn is None:
            raise LinkLostError(f"link {self.url!r} closed while reading")
        try:
            # under the send lock: a udpin connection's read adds each new peer to the set its
            # write iterates (pymavlink's mavudp), and a read on the reader thread while another
            # thread sends raised "Set changed size during iteration" in the sender. Reads are
            # non-blocking (pymavlink opens its sockets and ports so), so the lock is held briefly
            with self._send_lock:
                return conn.recv_msg()
        except mavlink2.MAVError:  # a frame even robust parsing could not turn into BAD_DATA
            self.stats.bad_in += 1
            return None
        except (OSError, ValueError) as exc:
            raise LinkLostError(f"link {self.url!r} failed while reading: {exc}") from exc

    def _wait(self, timeout_s: float) -> None:
        conn = self._conn
        fd = getattr(conn, "fd", None) if conn is not None else None
        if fd is None:
            time.sleep(min(timeout_s, 0.005))  # transport without a selectable descriptor
            return
        try:
            select.select([fd], [], [], timeout_s)
        except (OSError, ValueError) as exc:
            raise LinkLostError(f"link {self.url!r} failed while waiting: {exc}") from exc


class _QueueSink:
    """File-like sink the MAVLink encoder writes packed bytes into."""

    def __init__(self, owner: "MemoryLink") -> None:
        self._owner = owner

    def write(self, buf: bytes) -> None:
        self._owner._deliver(bytes(buf))


def _check_udp_port_free(url: str) -> None:
    """Raise :class:`LinkError` if another socket already listens on ``udpin:HOST:PORT``.

    pymavlink opens UDP inputs with SO_REUSEADDR, so a second listener on a busy port would
    start silently and receive nothing (or half the traffic); a plain bind tells the truth.
    """
    import socket

    host, _, port = url[len("udpin:"):].rpartition(":")
    try:
        port_i = int(port)
    except ValueError as exc:
        raise LinkError(f"bad UDP port in {url!r}") from exc
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host or "0.0.0.0", port_i))
    except OSError as exc:
        raise LinkError(f"UDP port {port_i} is busy ({url}): another program (a second sim-vehicle, a GCS?) listens there") from exc
    finally:
        probe.close()


class MemoryLink(Link):
    """In-memory fake :class:`Link` (one end of :func:`memory_link_pair`).

    Bytes sent by one end are parsed by the other with the real MAVLink 2 parser, so framing,
    CRCs and corrupted input behave as on a wire.
    """

    def __init__(self, source_system: int, source_component: int) -> None:
        super().__init__(source_system, source_component)
        self._inbox: queue.Queue[bytes] = queue.Queue()
        self._pending: collections.deque[bytes] = collections.deque()
        self._peer: MemoryLink | None = None
        self._mav = mavlink2.MAVLink(_QueueSink(self), srcSystem=self.source_system, srcComponent=self.source_component)
        self._mav.robust_parsing = True
        self._parser = mavlink2.MAVLink(None, srcSystem=0, srcComponent=0)
        self._parser.robust_parsing = True
        self._connected = False
        self._cut = threading.Event()

    def connect(self) -> None:
        if self._peer is None:
            raise LinkError("memory link has no peer; build it with memory_link_pair()")
        self._connected = True

    def close(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def mav(self) -> mavlink2.MAVLink:
        return self._mav

    def set_cut(self, cut: bool) -> None:
        """Drop (True) or pass (False) everything this end sends and receives."""
        if cut:
            self._cut.set()
        else:
            self._cut.clear()

    def inject_bytes(self, data: bytes) -> None:
        """Put raw bytes into this end's input, as if they arrived on the wire."""
        self._inbox.put(bytes(data))

    def _deliver(self, buf: bytes) -> None:
        peer = self._peer
        if self._cut.is_set() or peer is None or peer._cut.is_set() or not peer._connected:
            return
        peer._inbox.put(buf)

    def _poll(self):
        msg = self._parser.parse_char(b"")
        if msg is not None:
            return msg
        if self._pending:
            data = self._pending.popleft()
        else:
            try:
                data = self._inbox.get_nowait()
            except queue.Empty:
                return None
        if self._cut.is_set():
            return None
        try:
            return self._parser.parse_char(data)
        except mavlink2.MAVError:
            self.stats.bad_in += 1
            return None

    def _wait(self, timeout_s: float) -> None:
        try:
            self._pending.append(self._inbox.get(timeout=timeout_s))
        except queue.Empty:
            return


def memory_link_pair(system_a: int, component_a: int, system_b: int, component_b: int) -> tuple[MemoryLink, MemoryLink]:
    """Two connected in-memory links: what ``a`` sends, ``b`` receives, and vice versa."""
    a = MemoryLink(system_a, component_a)
    b = MemoryLink(system_b, component_b)
    a._peer, b._peer = b, a
    return a, b
