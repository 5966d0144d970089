"""What a V4L2 video node offers: capabilities, pixel formats with their frame sizes and
rates, and controls, read with the enumeration ioctls (no third-party library).

OpenCV can set a mode and read back the one it got, but it cannot list the modes, so
`treetraits camera info` asks the kernel directly. Only enumeration and reads are done
here; the capture itself goes through OpenCV (`drivers.camera.live`). Enumerating on a
second file descriptor is allowed while another one streams.

Struct layouts and ioctl numbers are those of `linux/videodev2.h` (the generic `_IOC`
encoding used by x86-64 and arm64); `parse_*` are pure functions over the bytes.
"""

from __future__ import annotations

import contextlib
import errno
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field

# ioctl request numbers: _IOC(dir, 'V', nr, sizeof(struct)), dir 2 = read, 3 = read/write.
_CAPABILITY = struct.Struct("<16s32s32sIII12x")  # struct v4l2_capability (104 bytes)
_FMTDESC = struct.Struct("<III32sII12x")  # struct v4l2_fmtdesc (64)
_FRMSIZE = struct.Struct("<III6I8x")  # struct v4l2_frmsizeenum (44)
_FRMIVAL = struct.Struct("<IIIII6I8x")  # struct v4l2_frmivalenum (52)
_QUERYCTRL = struct.Struct("<II32siiiiI8x")  # struct v4l2_queryctrl (68)
_QUERYMENU = struct.Struct("<II32sI")  # struct v4l2_querymenu, packed (44)
_CONTROL = struct.Struct("<Ii")  # struct v4l2_control (8)


def _ioc(direction: int, number: int, size: int) -> int:
    return (direction << 30) | (size << 16) | (ord("V") << 8) | number


VIDIOC_QUERYCAP = _ioc(2, 0, _CAPABILITY.size)  # 0x80685600
VIDIOC_ENUM_FMT = _ioc(3, 2, _FMTDESC.size)  # 0xc0405602
VIDIOC_G_CTRL = _ioc(3, 27, _CONTROL.size)  # 0xc008561b
VIDIOC_QUERYCTRL = _ioc(3, 36, _QUERYCTRL.size)  # 0xc0445624
VIDIOC_QUERYMENU = _ioc(3, 37, _QUERYMENU.size)  # 0xc02c5625
VIDIOC_ENUM_FRAMESIZES = _ioc(3, 74, _FRMSIZE.size)  # 0xc02c564a
VIDIOC_ENUM_FRAMEINTERVALS = _ioc(3, 75, _FRMIVAL.size)  # 0xc034564b

BUF_TYPE_VIDEO_CAPTURE = 1
CAP_VIDEO_CAPTURE = 0x00000001
CAP_VIDEO_CAPTURE_MPLANE = 0x00001000
CAP_META_CAPTURE = 0x00800000
CAP_DEVICE_CAPS = 0x80000000
FMT_FLAG_COMPRESSED = 0x0001
CTRL_FLAG_NEXT_CTRL = 0x80000000
CTRL_FLAG_DISABLED = 0x0001
CTRL_FLAG_READ_ONLY = 0x0004
CTRL_FLAG_INACTIVE = 0x0010
CTRL_FLAG_WRITE_ONLY = 0x0040
_FRMSIZE_DISCRETE, _FRMIVAL_DISCRETE = 1, 1
_CTRL_TYPE_NAMES = {
    1: "int",
    2: "bool",
    3: "menu",
    4: "button",
    5: "int64",
    6: "class",
    7: "string",
    8: "bitmask",
    9: "intmenu",
}
_MENU_TYPES = (3, 9)


@dataclass(frozen=True, slots=True)
class Capability:
    """VIDIOC_QUERYCAP: who drives the node and what it can do."""

    driver: str
    card: str  # for uvcvideo, the USB product string
    bus_info: str
    version: str
    capabilities: int  # of the whole device
    device_caps: int  # of this node (0 on kernels without per-node caps)

    @property
    def node_caps(self) -> int:
        return self.device_caps if self.capabilities & CAP_DEVICE_CAPS else self.capabilities

    @property
    def is_video_capture(self) -> bool:
        return bool(self.node_caps & (CAP_VIDEO_CAPTURE | CAP_VIDEO_CAPTURE_MPLANE))

    @property
    def is_metadata(self) -> bool:
        return bool(self.node_caps & CAP_META_CAPTURE)


@dataclass(frozen=True, slots=True)
class FrameMode:
    """One pixel format at one frame size, with the frame rates offered for it."""

    fourcc: str
    description: str
    compressed: bool
    width: int
    height: int
    fps: tuple[float, ...]  # discrete rates, highest first; a (min, max) range otherwise
    stepwise: bool = False  # sizes or rates given as a range, not a list

    def as_dict(self) -> dict:
        return {
            "fourcc": self.fourcc,
            "size": f"{self.width}x{self.height}",
            "fps": [round(f, 3) for f in self.fps],
            "compressed": self.compressed,
            "stepwise": self.stepwise,
        }


@dataclass(frozen=True, slots=True)
class Control:
    """One user control (VIDIOC_QUERYCTRL) and its current value (VIDIOC_G_CTRL)."""

    id: int
    name: str
    type: str
    minimum: int
    maximum: int
    step: int
    default: int
    flags: int
    value: int | None  # None when it cannot be read (write-only, inactive, error)
    menu: dict[int, str] = field(default_factory=dict)

    @property
    def inactive(self) -> bool:
        return bool(self.flags & CTRL_FLAG_INACTIVE)

    @property
    def read_only(self) -> bool:
        return bool(self.flags & CTRL_FLAG_READ_ONLY)

    def as_dict(self) -> dict:
        facts: dict = {
            "name": self.name,
            "type": self.type,
            "value": self.value,
            "min": self.minimum,
            "max": self.maximum,
            "step": self.step,
            "default": self.default,
        }
        if self.menu:
            facts["menu"] = {str(k): v for k, v in self.menu.items()}
        if self.inactive:
            facts["inactive"] = True
        if self.read_only:
            facts["read_only"] = True
        return facts


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("utf-8", "replace")


def fourcc_text(code: int) -> str:
    """A V4L2/OpenCV fourcc integer as its four characters (little-endian)."""
    return int(code & 0xFFFFFFFF).to_bytes(4, "little").decode("latin-1").rstrip("\0 ")


def fourcc_code(text: str) -> int:
    if len(text) != 4:
        raise ValueError(f"a fourcc has four characters, got {text!r}")
    return int.from_bytes(text.encode("latin-1"), "little")


def parse_capability(data: bytes) -> Capability:
    driver, card, bus, version, caps, device_caps = _CAPABILITY.unpack(data)
    return Capability(
        _text(driver),
        _text(card),
        _text(bus),
        f"{version >> 16}.{(version >> 8) & 0xFF}.{version & 0xFF}",
        caps,
        device_caps,
    )


def parse_fmtdesc(data: bytes) -> tuple[int, str, bool]:
    """(pixelformat, description, compressed) of a struct v4l2_fmtdesc."""
    _index, _type, flags, description, pixelformat, _mbus = _FMTDESC.unpack(data)
    return pixelformat, _text(description), bool(flags & FMT_FLAG_COMPRESSED)


def parse_frmsize(data: bytes) -> tuple[int, tuple[int, ...]]:
    """(type, values) of a struct v4l2_frmsizeenum: (width, height) when discrete, else
    (min_w, max_w, step_w, min_h, max_h, step_h)."""
    _index, _fmt, kind, *values = _FRMSIZE.unpack(data)
    return kind, tuple(values[:2]) if kind == _FRMSIZE_DISCRETE else tuple(values)


def parse_frmival(data: bytes) -> tuple[int, tuple[float, ...]]:
    """(type, frame rates) of a struct v4l2_frmivalenum: one rate when discrete, else
    (min rate, max rate) from the (min, max, step) interval range."""
    _index, _fmt, _w, _h, kind, *values = _FRMIVAL.unpack(data)

    def rate(numerator: int, denominator: int) -> float:
        return denominator / numerator if numerator else 0.0

    if kind == _FRMIVAL_DISCRETE:
        return kind, (rate(values[0], values[1]),)
    return kind, (rate(values[2], values[3]), rate(values[0], values[1]))


def parse_queryctrl(data: bytes) -> tuple[int, str, str, int, int, int, int, int]:
    """(id, name, type, min, max, step, default, flags) of a struct v4l2_queryctrl."""
    cid, kind, name, minimum, maximum, step, default, flags = _QUERYCTRL.unpack(data)
    return (
        cid,
        _text(name),
        _CTRL_TYPE_NAMES.get(kind, str(kind)),
        minimum,
        maximum,
        step,
        default,
        flags,
    )


def _ioctl(fd: int, request: int, buffer: bytearray) -> bool:
    """Run one ioctl in place; False when the driver says EINVAL (end of an enumeration,
    or not supported), other errors raise OSError."""
    import fcntl

    try:
        fcntl.ioctl(fd, request, buffer, True)
    except OSError as error:
        if error.errno in (errno.EINVAL, errno.ENOTTY):
            return False
        raise
    return True


@contextlib.contextmanager
def _open(path: str | os.PathLike[str]) -> Iterator[int]:
    fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
    try:
        yield fd
    finally:
        os.close(fd)


def query_capability(path: str | os.PathLike[str]) -> Capability:
    """VIDIOC_QUERYCAP on a node. Raises OSError when it cannot be opened or asked."""
    with _open(path) as fd:
        buffer = bytearray(_CAPABILITY.size)
        if not _ioctl(fd, VIDIOC_QUERYCAP, buffer):
            raise OSError(errno.ENOTTY, "not a V4L2 device", os.fspath(path))
        return parse_capability(bytes(buffer))


def list_modes(path: str | os.PathLike[str]) -> list[FrameMode]:
    """Every capture pixel format, frame size and frame rate the node offers."""
    modes = []
    with _open(path) as fd:
        for index in range(256):
            buffer = bytearray(_FMTDESC.pack(index, BUF_TYPE_VIDEO_CAPTURE, 0, b"", 0, 0))
            if not _ioctl(fd, VIDIOC_ENUM_FMT, buffer):
                break
            pixelformat, description, compressed = parse_fmtdesc(bytes(buffer))
            for width, height, stepwise_size in _frame_sizes(fd, pixelformat):
                rates, stepwise_rate = _frame_rates(fd, pixelformat, width, height)
                modes.append(
                    FrameMode(
                        fourcc_text(pixelformat),
                        description,
                        compressed,
                        width,
                        height,
                        rates,
                        stepwise_size or stepwise_rate,
                    )
                )
    return modes


def _frame_sizes(fd: int, pixelformat: int) -> list[tuple[int, int, bool]]:
    sizes = []
    for index in range(256):
        buffer = bytearray(_FRMSIZE.pack(index, pixelformat, 0, 0, 0, 0, 0, 0, 0))
        if not _ioctl(fd, VIDIOC_ENUM_FRAMESIZES, buffer):
            break
        kind, values = parse_frmsize(bytes(buffer))
        if kind == _FRMSIZE_DISCRETE:
            sizes.append((values[0], values[1], False))
        else:  # a range: report its two ends
            sizes.append((values[0], values[3], True))
            sizes.append((values[1], values[4], True))
            break
    return sizes


def _frame_rates(fd: int, pixelformat: int, width: int, height: int) -> tuple[tuple, bool]:
    rates: list[float] = []
    for index in range(256):
        buffer = bytearray(_FRMIVAL.pack(index, pixelformat, width, height, 0, 0, 0, 0, 0, 0, 0))
        if not _ioctl(fd, VIDIOC_ENUM_FRAMEINTERVALS, buffer):
            break
        kind, values = parse_frmival(bytes(buffer))
        if kind != _FRMIVAL_DISCRETE:
            return values, True
        rates.extend(values)
    return tuple(sorted(rates, reverse=True)), False


def list_controls(path: str | os.PathLike[str]) -> list[Control]:
    """Every control of the node with its range and current value (class headers and
    disabled controls left out)."""
    controls = []
    with _open(path) as fd:
        cid = 0
        for _ in range(1024):
            buffer = bytearray(_QUERYCTRL.pack(cid | CTRL_FLAG_NEXT_CTRL, 0, b"", 0, 0, 0, 0, 0))
            if not _ioctl(fd, VIDIOC_QUERYCTRL, buffer):
                break
            cid, name, kind, minimum, maximum, step, default, flags = parse_queryctrl(bytes(buffer))
            if kind == "class" or flags & CTRL_FLAG_DISABLED:
                continue
            value = None
            if not flags & CTRL_FLAG_WRITE_ONLY and kind in ("int", "bool", "menu", "intmenu"):
                value = _get_control(fd, cid)
            menu = _menu(fd, cid, minimum, maximum, kind) if kind in ("menu", "intmenu") else {}
            controls.append(
                Control(cid, name, kind, minimum, maximum, step, default, flags, value, menu)
            )
    return controls


def _get_control(fd: int, cid: int) -> int | None:
    buffer = bytearray(_CONTROL.pack(cid, 0))
    try:
        if not _ioctl(fd, VIDIOC_G_CTRL, buffer):
            return None
    except OSError:  # EACCES (write-only), EIO (device busy/inactive)
        return None
    return _CONTROL.unpack(bytes(buffer))[1]


def _menu(fd: int, cid: int, minimum: int, maximum: int, kind: str) -> dict[int, str]:
    items = {}
    for index in range(max(minimum, 0), min(maximum, 63) + 1):
        buffer = bytearray(_QUERYMENU.pack(cid, index, b"", 0))
        if _ioctl(fd, VIDIOC_QUERYMENU, buffer):  # menus may have holes
            raw = bytes(buffer)[8:40]
            if kind == "intmenu":
                items[index] = str(struct.unpack_from("<q", raw)[0])
            else:
                items[index] = _text(raw)
    return items
