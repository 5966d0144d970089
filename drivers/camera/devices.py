"""Which /dev node is the Survey3N: device names as the user gives them, turned into the
path OpenCV opens.

Accepted forms (`resolve_device`):
- `/dev/videoN`, a stable link such as `/dev/v4l/by-id/usb-...-video-index0` or the udev
  name `/dev/survey3n`, or any other path: opened as given (a link is followed at each
  open, so it survives re-enumeration after a replug);
- `N`: `/dev/videoN`;
- `usb:VID:PID` (hex): the USB device found with pyusb (bus and port path), mapped through
  sysfs to its V4L2 capture node;
- `auto`: the first V4L2 capture node whose name contains "MAPIR" or "Survey".

A UVC camera has two nodes, capture and metadata (sysfs `index` 0 and 1); only the capture
node is ever chosen. The Survey3's USB vendor/product id is not documented anywhere we
found, so `auto` matches the product string, as MAPIR's own ROS 2 udev rule does.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from treetraits.drivers.camera import v4l2
from treetraits.errors import ConfigError, SourceError

SYSFS = Path("/sys")
DEV = Path("/dev")
NAME_PATTERN = re.compile(r"mapir|survey", re.IGNORECASE)
_USB_SPEC = re.compile(r"usb:([0-9a-fA-F]{1,4}):([0-9a-fA-F]{1,4})")


@dataclass(frozen=True, slots=True)
class VideoDevice:
    """One V4L2 node as sysfs (and, when it can be opened, VIDIOC_QUERYCAP) describes it."""

    node: str  # /dev/videoN
    name: str  # the V4L2 name; for uvcvideo the USB product string
    index: int | None  # 0 = a function's capture node, 1 = its UVC metadata node
    usb_id: str | None  # "vvvv:pppp" (lower-case hex), None when not on USB
    usb_port: str | None  # sysfs USB device name "BUS-PORT[.PORT...]"
    capture: bool | None  # VIDIOC_QUERYCAP: a video capture node; None when not asked

    @property
    def is_capture(self) -> bool:
        """Capture capable: as the driver says when it could be asked, else by index 0."""
        return self.capture if self.capture is not None else self.index in (0, None)

    def describe(self) -> str:
        kind = "capture" if self.is_capture else "not capture (metadata?)"
        usb = f", USB {self.usb_id} at {self.usb_port}" if self.usb_id else ""
        return f"{self.node} {self.name!r} ({kind}{usb})"


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def _usb_device_dir(interface: Path) -> Path | None:
    """The USB device directory above a video node's `device` (a USB interface)."""
    for candidate in (interface, *interface.parents):
        if (candidate / "idVendor").is_file():
            return candidate
        if candidate.name.startswith("usb") or candidate == candidate.parent:
            break
    return None


def list_video_devices(
    sysfs: Path = SYSFS, dev: Path = DEV, query: bool = True
) -> list[VideoDevice]:
    """Every V4L2 node, ordered by number. `query` asks each node with VIDIOC_QUERYCAP
    (needs read/write access to the node; without it, `capture` is None)."""
    root = sysfs / "class" / "video4linux"
    if not root.is_dir():
        return []
    devices = []
    for entry in root.iterdir():
        match = re.fullmatch(r"video(\d+)", entry.name)
        if not match:
            continue
        index = _read(entry / "index")
        usb_dir = _usb_device_dir((entry / "device").resolve())
        usb_id = usb_port = None
        if usb_dir is not None:
            usb_id = f"{_read(usb_dir / 'idVendor')}:{_read(usb_dir / 'idProduct')}".lower()
            usb_port = usb_dir.name
        node = dev / entry.name
        capture = None
        if query:
            try:
                capture = v4l2.query_capability(node).is_video_capture
            except OSError:
                capture = None
        devices.append(
            VideoDevice(
                str(node),
                _read(entry / "name") or "",
                int(index) if index and index.isdigit() else None,
                usb_id,
                usb_port,
                capture,
            )
        )
    return sorted(devices, key=lambda d: int(re.sub(r"\D", "", Path(d.node).name) or 0))


def usb_port_name(bus: int, port_numbers: tuple[int, ...] | None) -> str | None:
    """The sysfs name of a USB device from its bus and port path (`1-2.4`); None for a
    root hub, which has no ports."""
    if not port_numbers:
        return None
    return f"{bus}-{'.'.join(str(p) for p in port_numbers)}"


def find_usb_ports(vendor: int, product: int, sysfs: Path = SYSFS) -> list[str]:
    """Where the USB devices with this vendor/product id are plugged (sysfs names).

    Asks libusb through pyusb; when pyusb has no backend (libusb missing), reads the ids
    from sysfs instead, which gives the same answer on Linux.
    """
    try:
        import usb.core
    except ImportError:
        pass
    else:
        try:
            found = usb.core.find(find_all=True, idVendor=vendor, idProduct=product)
            ports = [usb_port_name(d.bus, d.port_numbers) for d in found]
            return sorted(p for p in ports if p)
        except usb.core.NoBackendError:
            pass  # no libusb: sysfs below
        except usb.core.USBError as exc:
            raise SourceError(f"USB lookup of {vendor:04x}:{product:04x} failed: {exc}") from exc
    ports = []
    usb_root = sysfs / "bus" / "usb" / "devices"
    if usb_root.is_dir():
        for entry in usb_root.iterdir():
            vid, pid = _read(entry / "idVendor"), _read(entry / "idProduct")
            if vid and pid and int(vid, 16) == vendor and int(pid, 16) == product:
                ports.append(entry.name)
    return sorted(ports)


def resolve_device(spec: str, sysfs: Path = SYSFS, dev: Path = DEV) -> str:
    """The node path to open for a device spec (see the module doc). Raises SourceError
    with what was found when nothing matches, ConfigError for a malformed spec."""
    spec = spec.strip()
    if spec.isdigit():
        return str(dev / f"video{int(spec)}")
    if spec.startswith(("/", "./", "../")):
        return spec
    if spec == "auto":
        return _resolve_auto(sysfs, dev)
    match = _USB_SPEC.fullmatch(spec)
    if match:
        return _resolve_usb(int(match[1], 16), int(match[2], 16), sysfs, dev)
    if spec.startswith("usb:"):
        raise ConfigError(
            f"camera device {spec!r}: expected usb:VID:PID in hex, e.g. usb:1a2b:3c4d"
        )
    raise ConfigError(
        f"camera device {spec!r}: expected auto, usb:VID:PID, a number N (/dev/videoN) or a "
        "path such as /dev/video0, /dev/v4l/by-id/... or /dev/survey3n"
    )


def _found(devices: list[VideoDevice]) -> str:
    if not devices:
        return (
            "no V4L2 video devices at all: is the camera plugged into its USB/POWER port and "
            "switched on (not in media-transfer mode, where it is a disk), and is the "
            "uvcvideo module loaded (lsmod | grep uvcvideo)?"
        )
    return "V4L2 devices found: " + "; ".join(d.describe() for d in devices)


def _resolve_auto(sysfs: Path, dev: Path) -> str:
    devices = list_video_devices(sysfs, dev)
    for device in devices:
        if NAME_PATTERN.search(device.name) and device.is_capture:
            return device.node
    raise SourceError(
        "camera auto: no V4L2 capture device named like MAPIR/Survey. "
        + _found(devices)
        + ". Give the device explicitly (--device /dev/videoN or /dev/v4l/by-id/...)."
    )


def _resolve_usb(vendor: int, product: int, sysfs: Path, dev: Path) -> str:
    wanted = f"{vendor:04x}:{product:04x}"
    ports = find_usb_ports(vendor, product, sysfs)
    devices = list_video_devices(sysfs, dev)
    if not ports:
        raise SourceError(f"camera usb:{wanted}: no such USB device plugged in. " + _found(devices))
    nodes = [d for d in devices if d.usb_port in ports and d.is_capture]
    if not nodes:
        raise SourceError(
            f"camera usb:{wanted}: the USB device is at {', '.join(ports)} but has no V4L2 "
            "capture node: a Survey3 in media-transfer mode shows up as a disk, not a camera "
            "(send the 1500 us PWM toggle again or power-cycle it). " + _found(devices)
        )
    if len({d.usb_port for d in nodes}) > 1:
        raise SourceError(
            f"camera usb:{wanted}: {len(ports)} such cameras ({', '.join(ports)}); name one "
            "by path: " + "; ".join(d.describe() for d in nodes)
        )
    return nodes[0].node


def describe_node(path: str) -> str:
    """A hint for a node that could not be opened: missing, no permission, or busy."""
    if not os.path.exists(path):
        return f"{path} does not exist: is the camera plugged in and on?"
    real = os.path.realpath(path)
    shown = path if real == path else f"{path} (-> {real})"
    if not os.access(real, os.R_OK | os.W_OK):
        return f"no read/write permission on {shown}: add the user to group 'video'"
    return (
        f"{shown} exists and is accessible: another program may hold it (fuser -v {real}), "
        "or it is a UVC metadata node rather than the capture node (index 0)"
    )
