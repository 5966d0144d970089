"""Where VLP-16 packets come from: live UDP, pcap/pcapng captures, raw payload files and
MCAP recordings, all behind `open_source(uri)` and one iteration interface.

A source yields `LidarPacket`s (the payload exactly as received and its host receive time)
and counts what it skipped. Packets are told apart by payload length (1206 data, 512
position), not by port, since ports can be reconfigured. Nothing here decodes points:
that is the batcher's job.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import selectors
import socket
import struct
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from decimal import Decimal
from operator import attrgetter
from pathlib import Path
from typing import Protocol
from urllib.parse import parse_qs, urlsplit

import dpkt

from treetraits.drivers import DATA_PORT, TELEMETRY_PORT
from treetraits.drivers.rosbag.detect import refuse_ros_bag
from treetraits.drivers.velodyne.models import DATA_PACKET_SIZE, HOUR_NS, POSITION_PACKET_SIZE
from treetraits.errors import SourceError

DEFAULT_RCVBUF = 8 * 1024 * 1024  # ~5 s of dual-return traffic; the kernel caps it at rmem_max
_CLOSE_POLL_S = 0.5
_SO_RXQ_OVFL = 40  # Linux: per-socket count of datagrams dropped for a full buffer
# Linux: each datagram carries the realtime clock of its arrival in the kernel (a struct
# timespec, two native longs). The same for SCM_TIMESTAMPNS; not in Python's socket module.
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("=qq")
_ANCILLARY_BYTES = socket.CMSG_SPACE(4) + socket.CMSG_SPACE(_TIMESPEC.size)
_DRAIN_MAX = 256  # datagrams read in one go after a wake-up (1/3 s of data packets)

_PCAP_MAGICS = {b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\x4d\x3c\xb2\xa1", b"\xa1\xb2\x3c\x4d"}
_PCAPNG_MAGIC = b"\x0a\x0d\x0d\x0a"
_PCAP_LE_MAGICS = {b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1"}
_LINKTYPE_RAW = 101  # raw IP as stored in files; dpkt's DLT_RAW is the in-memory 12 (14)
_MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True, slots=True)
class LidarPacket:
    """One UDP payload from the sensor: 1206 bytes (data) or 512 (position)."""

    payload: bytes
    t_host: int  # ns since the Unix epoch, when the bytes were received

    @property
    def is_data(self) -> bool:
        return len(self.payload) == DATA_PACKET_SIZE


@dataclass
class SourceStats:
    """What a source read and what it skipped."""

    packets: int = 0  # accepted: data + position
    bytes: int = 0
    data_packets: int = 0
    position_packets: int = 0
    malformed: int = 0  # on a sensor port (or in a raw file) with a length that fits no packet
    foreign: int = 0  # other traffic: other hosts, other ports, not UDP
    kernel_drops: int = 0  # live UDP only: dropped by the kernel for a full receive buffer
    truncated: bool = False  # a file that ended in the middle of a record

    def count(self, payload: bytes) -> None:
        self.packets += 1
        self.bytes += len(payload)
        if len(payload) == DATA_PACKET_SIZE:
            self.data_packets += 1
        else:
            self.position_packets += 1

    def as_dict(self) -> dict[str, int | bool]:
        return asdict(self)


class PacketSource(Protocol):
    """What every LiDAR source offers."""

    uri: str
    is_live: bool
    stats: SourceStats

    def __iter__(self) -> Iterator[LidarPacket]: ...

    def close(self) -> None: ...


def _is_sensor_payload(length: int) -> bool:
    return length in (DATA_PACKET_SIZE, POSITION_PACKET_SIZE)


class PcapSource:
    """libpcap or pcapng capture: Ethernet (with VLAN tags), Linux cooked (SLL, SLL2),
    raw IP and BSD loopback link types. IPv4 and IPv6 UDP; everything else is foreign."""

    is_live = False

    def __init__(self, path: str | Path, ports: tuple[int, ...] = (DATA_PORT, TELEMETRY_PORT)):
        self.uri = str(path)
        self.ports = ports
        self.stats = SourceStats()
        self._file = open(path, "rb")  # noqa: SIM115 - closed by close()
        try:
            magic = self._file.read(4)
            self._file.seek(0)
            self._pcapng = magic == _PCAPNG_MAGIC
            self._caplen = struct.Struct("<I" if magic in _PCAP_LE_MAGICS else ">I")
            self._size = os.fstat(self._file.fileno()).st_size
            reader_type = dpkt.pcapng.Reader if magic == _PCAPNG_MAGIC else dpkt.pcap.Reader
            self._reader = reader_type(self._file)
            self._link = _link_decoder(self._reader.datalink(), path)
        except (ValueError, dpkt.dpkt.Error, struct.error) as exc:
            self._file.close()
            raise SourceError(f"{path}: not a readable pcap/pcapng capture ({exc})") from exc
        except SourceError:
            self._file.close()
            raise

    def __iter__(self) -> Iterator[LidarPacket]:
        frames = iter(self._reader)
        while True:
            try:
                ts, frame = next(frames)
            except StopIteration:
                return
            except (dpkt.dpkt.Error, struct.error, ValueError):
                self.stats.truncated = True  # the file ends inside a record
                return
            if self._cut_short(frame):
                self.stats.truncated = True  # the file ends inside a record's frame
                return
            payload = self._udp_payload(frame)
            if payload is None:
                continue
            self.stats.count(payload)
            yield LidarPacket(payload, _ns(ts))

    def _cut_short(self, frame: bytes) -> bool:
        """dpkt's pcap reader yields a short frame when the file ends inside a record's data:
        at the end of the file, compare with the caplen in that record's header."""
        end = self._file.tell()
        if self._pcapng or end < self._size:
            return False
        self._file.seek(end - len(frame) - 8)  # ts_sec, ts_frac, caplen, len
        (caplen,) = self._caplen.unpack(self._file.read(4))
        self._file.seek(end)
        return len(frame) < caplen

    def _udp_payload(self, frame: bytes) -> bytes | None:
        try:
            packet = self._link(frame)
            while not isinstance(packet, dpkt.ip.IP | dpkt.ip6.IP6):
                inner = getattr(packet, "data", None)
                if inner is None or isinstance(inner, bytes):
                    self.stats.foreign += 1
                    return None
                packet = inner
            udp = packet.data
        except (dpkt.dpkt.Error, struct.error, ValueError, IndexError):
            self.stats.foreign += 1
            return None
        if not isinstance(udp, dpkt.udp.UDP):
            self.stats.foreign += 1
            return None
        payload = bytes(udp.data)
        if _is_sensor_payload(len(payload)):
            return payload
        if udp.dport in self.ports:
            self.stats.malformed += 1
        else:
            self.stats.foreign += 1
        return None

    def close(self) -> None:
        self._file.close()


def _ns(ts: float | Decimal) -> int:
    """A capture time in ns: dpkt gives float seconds, a Decimal for nanosecond pcaps."""
    if isinstance(ts, Decimal):
        return int(ts * 1_000_000_000)
    return round(ts * 1e6) * 1000


def _link_decoder(datalink: int, path: str | Path):
    decoders = {
        dpkt.pcap.DLT_EN10MB: dpkt.ethernet.Ethernet,
        dpkt.pcap.DLT_LINUX_SLL: dpkt.sll.SLL,
        dpkt.pcap.DLT_LINUX_SLL2: dpkt.sll2.SLL2,
        dpkt.pcap.DLT_RAW: dpkt.ip.IP,
        _LINKTYPE_RAW: dpkt.ip.IP,
        dpkt.pcap.DLT_IPV4: dpkt.ip.IP,
        dpkt.pcap.DLT_IPV6: dpkt.ip6.IP6,
        dpkt.pcap.DLT_NULL: dpkt.loopback.Loopback,
        dpkt.pcap.DLT_LOOP: dpkt.loopback.Loopback,
    }
    if datalink not in decoders:
        raise SourceError(
            f"{path}: capture link type {datalink} is not supported; "
            "expected Ethernet, Linux cooked (SLL/SLL2), raw IP or loopback"
        )
    return decoders[datalink]


class RawPayloadSource:
    """Back-to-back 1206-byte data payloads with no headers or capture times.

    With no host clock in the file, `t_host` is rebuilt from the packets' own ToH,
    counting hours from the Unix epoch, so per-point times are device times.
    """

    is_live = False

    def __init__(self, path: str | Path):
        self.uri = str(path)
        self.stats = SourceStats()
        self._file = open(path, "rb")  # noqa: SIM115 - closed by close()

    def __iter__(self) -> Iterator[LidarPacket]:
        hour = 0
        last_toh: int | None = None
        while chunk := self._file.read(DATA_PACKET_SIZE):
            if len(chunk) < DATA_PACKET_SIZE:
                self.stats.malformed += 1
                self.stats.truncated = True
                return
            (toh,) = struct.unpack_from("<I", chunk, 1200)
            if last_toh is not None and toh + HOUR_NS // 2000 < last_toh:
                hour += 1  # the microseconds-past-the-hour counter wrapped
            last_toh = toh
            self.stats.count(chunk)
            yield LidarPacket(chunk, hour * HOUR_NS + toh * 1000)

    def close(self) -> None:
        self._file.close()


class McapSource:
    """LiDAR channels of an MCAP recording (format v1); other topics are skipped."""

    is_live = False

    def __init__(self, path: str | Path):
        from treetraits.drivers import recording

        self.uri = str(path)
        self.stats = SourceStats()
        self._recording = recording.read_recording(
            path, topics=[recording.LIDAR_PACKETS, recording.LIDAR_TELEMETRY]
        )

    def __iter__(self) -> Iterator[LidarPacket]:
        for message in self._recording:
            if _is_sensor_payload(len(message.data)):
                self.stats.count(message.data)
                yield LidarPacket(bytes(message.data), message.log_time)
            else:
                self.stats.malformed += 1
        # A chunk skipped as damaged is reported as a cut is: data was lost.
        self.stats.truncated = self._recording.truncated or self._recording.lost_data

    @property
    def recording(self):
        """The recording's reader: what of it could not be read (treetraits/damage.py)."""
        return self._recording

    def close(self) -> None:
        self._recording.close()


class UdpSource:
    """Live packets from the sensor: the data port and, optionally, the telemetry port.

    Each socket gets a large `SO_RCVBUF` (the kernel caps it at net.core.rmem_max, see
    `effective_rcvbuf`) and `SO_RXQ_OVFL`, so drops in the kernel are counted, not guessed.
    With `sensor_ip` set, datagrams from any other address are foreign and skipped.
    Iteration blocks in `select` (no busy loop) and ends when `close()` is called.

    A packet's `t_host` is when the kernel received it (`SO_TIMESTAMPNS`, the realtime
    clock), not when this thread got round to reading it: a reader held up by a busy
    process (the GIL) does not move the scan's time, and may read in bursts
    (`kernel_timestamps`; without them, `time.time_ns()` at the read). After a wake-up
    every datagram already queued is read at once (`pending`).
    """

    is_live = True

    def __init__(
        self,
        host: str = "0.0.0.0",
        port: int = DATA_PORT,
        telemetry_port: int | None = TELEMETRY_PORT,
        sensor_ip: str | None = None,
        rcvbuf: int = DEFAULT_RCVBUF,
    ):
        self.uri = f"udp://{host}:{port}"
        self.stats = SourceStats()
        try:
            self.sensor_ip = str(ipaddress.ip_address(sensor_ip)) if sensor_ip else None
        except ValueError as exc:
            raise SourceError(f"sensor IP {sensor_ip!r} is not an IPv4 or IPv6 address") from exc
        self._selector = selectors.DefaultSelector()
        self._sockets: list[socket.socket] = []
        self._closed = False
        self._kernel_drops: dict[int, int] = {}
        self._pending: deque[LidarPacket] = deque()
        self.kernel_timestamps = True  # until a socket refuses them
        try:
            for p in (port, telemetry_port):
                if p is not None:
                    self._sockets.append(self._bind(host, p, rcvbuf))
        except OSError as exc:
            self.close()
            ports = "/".join(str(p) for p in (port, telemetry_port) if p is not None)
            raise SourceError(
                f"cannot listen on UDP {host}:{ports}: {exc.strerror or exc}; is another "
                "program (a ROS driver, VeloView, a second treetraits) bound to the port?"
            ) from exc
        for sock in self._sockets:
            self._selector.register(sock, selectors.EVENT_READ)

    def _bind(self, host: str, port: int, rcvbuf: int) -> socket.socket:
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        # No SO_REUSEADDR: a second reader on the port must fail loudly, not share it.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        with contextlib.suppress(OSError):  # not on every kernel
            sock.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError:
            self.kernel_timestamps = False
        sock.bind((host, port))
        sock.setblocking(False)
        return sock

    @property
    def ports(self) -> list[int]:
        """The bound ports (useful when asked for port 0)."""
        return [s.getsockname()[1] for s in self._sockets]

    @property
    def effective_rcvbuf(self) -> int:
        """The receive buffer the kernel granted (it doubles the request, capped at rmem_max)."""
        return self._sockets[0].getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    @property
    def pending(self) -> int:
        """Packets read from the sockets and not yet returned by `read`."""
        return len(self._pending)

    def read(self, timeout: float | None = None) -> LidarPacket | None:
        """The next accepted packet, or None when `timeout` seconds pass without one."""
        if self._pending:
            return self._pending.popleft()
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._closed:
            # Wait in slices so a close() from another thread ends even an unbounded read.
            remaining = _CLOSE_POLL_S
            if deadline is not None:
                remaining = min(remaining, max(0.0, deadline - time.monotonic()))
            try:
                events = self._selector.select(remaining)
            except (OSError, ValueError):
                if self._closed:
                    return None  # closed by another thread while we were about to wait
                raise
            for key, _ in events:
                self._drain(key.fileobj)
            if self._pending:
                if len(events) > 1:  # data and telemetry: one stream in arrival order
                    self._pending = deque(sorted(self._pending, key=attrgetter("t_host")))
                return self._pending.popleft()
            if deadline is not None and time.monotonic() >= deadline:
                return None
        return None

    def _drain(self, sock) -> None:
        """Every datagram queued on `sock` (up to `_DRAIN_MAX`), accepted ones to `_pending`."""
        for _ in range(_DRAIN_MAX):
            try:
                payload, ancillary, _flags, address = sock.recvmsg(2048, _ANCILLARY_BYTES)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # closed under us
            packet = self._accept(sock, payload, ancillary, address)
            if packet is not None:
                self._pending.append(packet)

    def _accept(self, sock, payload: bytes, ancillary, address) -> LidarPacket | None:
        t_host = None
        for level, kind, data in ancillary:
            if level != socket.SOL_SOCKET:
                continue
            if kind == _SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
                seconds, nanoseconds = _TIMESPEC.unpack_from(data)
                t_host = seconds * 1_000_000_000 + nanoseconds
            elif kind == _SO_RXQ_OVFL and len(data) >= 4:
                self._kernel_drops[sock.fileno()] = struct.unpack("=I", data[:4])[0]
                self.stats.kernel_drops = sum(self._kernel_drops.values())
        if t_host is None:
            t_host = time.time_ns()
        if self.sensor_ip is not None and address[0] != self.sensor_ip:
            self.stats.foreign += 1
            return None
        if not _is_sensor_payload(len(payload)):
            self.stats.malformed += 1
            return None
        self.stats.count(payload)
        return LidarPacket(payload, t_host)

    def __iter__(self) -> Iterator[LidarPacket]:
        while not self._closed:
            packet = self.read()
            if packet is not None:
                yield packet

    def close(self) -> None:
        self._closed = True
        with contextlib.suppress(Exception):
            self._selector.close()
        for sock in self._sockets:
            sock.close()


def _udp_source(uri: str) -> UdpSource:
    parts = urlsplit(uri)
    query = {k: v[-1] for k, v in parse_qs(parts.query).items()}
    known = {"telemetry", "sensor", "rcvbuf"}
    unknown = set(query) - known
    if unknown:
        raise SourceError(f"{uri}: unknown option(s) {sorted(unknown)}; known: {sorted(known)}")
    try:
        telemetry = int(query.get("telemetry", TELEMETRY_PORT)) or None
        rcvbuf = int(query.get("rcvbuf", DEFAULT_RCVBUF))
        port = parts.port if parts.port is not None else DATA_PORT
    except ValueError as exc:
        raise SourceError(f"{uri}: {exc}") from exc
    return UdpSource(
        host=parts.hostname or "0.0.0.0",
        port=port,
        telemetry_port=telemetry,
        sensor_ip=query.get("sensor"),
        rcvbuf=rcvbuf,
    )


def open_source(uri: str | os.PathLike) -> PacketSource:
    """Open a LiDAR packet source.

    - `udp://HOST:PORT?telemetry=8308&sensor=192.168.1.201&rcvbuf=8388608`: live sensor
      (defaults: 0.0.0.0, data port 2368, telemetry 8308; `telemetry=0` disables it);
    - a libpcap or pcapng capture, an MCAP recording (format v1), or a raw file of
      back-to-back 1206-byte payloads, recognised by content, not by name.
    """
    text = os.fspath(uri)
    if text.startswith("udp://"):
        return _udp_source(text)
    path = Path(text)
    refuse_ros_bag(path, "a capture or a recording")
    if not path.is_file():
        raise SourceError(f"{text}: no such file (expected a pcap, pcapng, mcap or raw capture)")
    with open(path, "rb") as f:
        head = f.read(8)
    if head[:4] in _PCAP_MAGICS or head[:4] == _PCAPNG_MAGIC:
        return PcapSource(path)
    if head == _MCAP_MAGIC:
        return McapSource(path)
    size = path.stat().st_size
    raw_sized = size % DATA_PACKET_SIZE == 0 or path.suffix in (".bin", ".raw")
    if size and raw_sized and head[:2] == b"\xff\xee":
        return RawPayloadSource(path)
    raise SourceError(
        f"{text}: not a pcap, pcapng or MCAP file, nor raw 1206-byte VLP-16 payloads "
        f"(first bytes {head.hex()})"
    )
