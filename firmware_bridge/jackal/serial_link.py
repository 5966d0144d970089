"""The MCU's USB serial port (`/dev/jackal`, 115200 8N1, no flow control): open, read, write.

A thin shell around pyserial. `read()` blocks for at most `read_timeout` waiting for the first
byte (pyserial waits in `select`, so an idle link costs no CPU) and returns whatever has
arrived; a vanished device or a closed pseudo-terminal raises `LinkLostError`. Writes go out one
frame per call, serialized by a lock, since the time replies and the teleop relay write from
different threads. The port is opened with an exclusive lock: a second treetraits fails
loudly instead of sharing the MCU (jackal_node does not take the lock; see docs/jackal.md).
"""

from __future__ import annotations

import contextlib
import errno
import threading
from dataclasses import asdict, dataclass

from treetraits.errors import SourceError

DEFAULT_PORT = "/dev/jackal"
DEFAULT_BAUDRATE = 115200


class LinkLostError(SourceError):
    """The port stopped working (unplugged, MCU reset, closed): reopen it."""


def _pyserial():
    try:
        import serial
    except ImportError as exc:  # pragma: no cover - a dependency of the package
        raise SourceError(
            "the Jackal MCU link needs pyserial: pip install 'pyserial>=3.5'"
        ) from exc
    return serial


def open_hint(port: str, exc: BaseException) -> str:
    """A message for a port that would not open, with what to do about it."""
    code = getattr(exc, "errno", None)
    if code == errno.ENOENT:
        return (
            f"{port}: no such device. Is the Jackal powered and its MCU USB cable plugged in? "
            "The udev rule names the STM32 VCP (0483:5740) /dev/jackal; check `ls -l /dev/jackal "
            "/dev/ttyACM*`"
        )
    if code in (errno.EACCES, errno.EPERM):
        return (
            f"{port}: permission denied. Add the service user to the `dialout` group "
            "(or install the udev rule from systemd/), then log in again"
        )
    if code in (errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK):
        return (
            f"{port}: busy. Only one process can own the MCU port: stop jackal_node "
            "(on Clearpath images `sudo systemctl stop ros`) or the other treetraits first"
        )
    return f"{port}: cannot open ({exc})"


@dataclass
class LinkStats:
    opens: int = 0
    open_failures: int = 0
    losses: int = 0
    bytes_read: int = 0
    bytes_written: int = 0
    write_timeouts: int = 0  # the MCU did not take a frame within `write_timeout`: dropped

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class SerialLink:
    def __init__(
        self,
        port: str = DEFAULT_PORT,
        baudrate: int = DEFAULT_BAUDRATE,
        read_timeout: float = 0.1,
        write_timeout: float = 0.5,
        exclusive: bool = True,
    ):
        self.port = port
        self.baudrate = baudrate
        self.read_timeout = read_timeout
        self.write_timeout = write_timeout
        self.exclusive = exclusive
        self.stats = LinkStats()
        self._serial = None
        self._write_lock = threading.Lock()

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def open(self) -> None:
        """Open the port and drop whatever was waiting in it. `SourceError` with a hint."""
        serial = _pyserial()
        port = serial.Serial()
        port.port = self.port
        port.baudrate = self.baudrate
        port.bytesize = serial.EIGHTBITS
        port.parity = serial.PARITY_NONE
        port.stopbits = serial.STOPBITS_ONE
        port.xonxoff = port.rtscts = port.dsrdtr = False
        port.timeout = self.read_timeout
        port.write_timeout = self.write_timeout
        port.exclusive = self.exclusive
        try:
            port.open()
            port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as exc:
            self.stats.open_failures += 1
            if port.is_open:
                port.close()
            raise SourceError(open_hint(self.port, exc)) from exc
        self.stats.opens += 1
        self._serial = port

    def read(self) -> bytes:
        """Bytes that arrived (b"" after `read_timeout` with none). `LinkLostError` on failure."""
        port = self._serial
        if port is None:
            raise LinkLostError(f"{self.port}: not open")
        serial = _pyserial()
        try:
            data = port.read(max(1, port.in_waiting))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # TypeError/AttributeError: pyserial's fd vanished under a concurrent close().
            self._lose()
            raise LinkLostError(f"{self.port}: read failed ({exc})") from exc
        self.stats.bytes_read += len(data)
        return data

    def write(self, frame: bytes) -> bool:
        """Write one frame in one call. False if the MCU did not take it in time (dropped);
        `LinkLostError` if the port is gone."""
        serial = _pyserial()
        with self._write_lock:
            port = self._serial
            if port is None:
                raise LinkLostError(f"{self.port}: not open")
            try:
                port.write(frame)
            except serial.SerialTimeoutException:
                self.stats.write_timeouts += 1
                return False
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                self._lose()
                raise LinkLostError(f"{self.port}: write failed ({exc})") from exc
            self.stats.bytes_written += len(frame)
            return True

    def _lose(self) -> None:
        if self._serial is not None:
            self.stats.losses += 1
        self.close()

    def close(self) -> None:
        port, self._serial = self._serial, None
        if port is not None:
            with contextlib.suppress(Exception):  # closing a port that is already gone
                port.close()
