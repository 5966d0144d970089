"""`treetraits doctor`: check that this machine can run the service, and say how to fix it.

Each check is a plain function returning `Check` records (name, ok/warn/fail, what was
found, the fix). They read the machine through `/sys`, `/proc` and `/dev`, which are
parameters so tests can hand them a fake tree for what CI cannot have (USB devices);
serial ports, groups, permissions and the UDP port are checked for real.

"Who holds it" is found like fuser(1): every /proc/PID/fd link that points at the device
(or, for a UDP port, at the socket inode /proc/net/udp lists for it).
"""

from __future__ import annotations

import contextlib
import enum
import grp
import os
import pwd
import re
import select
import shutil
import socket
import stat
import subprocess
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from treetraits.drivers.camera.devices import list_video_devices, resolve_device
from treetraits.errors import TreetraitsError
from treetraits.service import DEFAULT_CONFIG_PATH
from treetraits.service.config import ServiceConfig, load_config

SERVICE_USER = "treetraits"
SERVICE_GROUPS = ("dialout", "video")
SYSCTL_FILE = "systemd/60-treetraits.conf"
UDEV_RULES = "/etc/udev/rules.d/99-treetraits.rules"

# USB ids we know, and what they are on this robot.
KNOWN_USB: dict[str, str] = {
    "0483:5740": "Jackal MCU (STM32 virtual COM port)",
    "1546:01a5": "u-blox 5 GNSS",
    "1546:01a6": "u-blox 6 GNSS",
    "1546:01a7": "u-blox 7 GNSS",
    "1546:01a8": "u-blox 8 GNSS",
    "1546:01a9": "u-blox F9/M9 GNSS",
    "0403:6001": "FTDI FT232R USB-serial (a GNSS receiver?)",
    "0403:6015": "FTDI FT231X USB-serial (a GNSS receiver?)",
    "10c4:ea60": "Silicon Labs CP210x USB-serial (a GNSS receiver?)",
    "1a86:7523": "WCH CH340 USB-serial (a GNSS receiver?)",
}
JACKAL_USB = "0483:5740"
GNSS_USB_PREFIXES = ("1546:", "0403:", "10c4:", "1a86:")
CAMERA_PRODUCT = re.compile(r"mapir|survey", re.IGNORECASE)
# Receive-buffer use of a single-return VLP-16: 754 packets/s, each charged ~2.3 kB (the
# 1206-byte payload plus the kernel's per-packet overhead).
_VLP16_BUFFER_BYTES_PER_S = 754 * 2304


class Status(str, enum.Enum):
    OK = "ok"
    WARN = "warn"
    FAIL = "fail"


@dataclass(frozen=True, slots=True)
class Check:
    """One finding: `detail` says what was found, `fix` what to do (empty when ok)."""

    name: str
    status: Status
    detail: str
    fix: str = ""

    def as_dict(self) -> dict[str, str]:
        return {
            "name": self.name,
            "status": self.status.value,
            "detail": self.detail,
            "fix": self.fix,
        }


@dataclass(frozen=True, slots=True)
class Roots:
    """Where the kernel's views are mounted (tests point these at fake trees)."""

    sys: Path = Path("/sys")
    proc: Path = Path("/proc")
    dev: Path = Path("/dev")


@dataclass(frozen=True, slots=True)
class Holder:
    pid: int
    name: str

    def __str__(self) -> str:
        return f"{self.name} (pid {self.pid})"


# --- processes ------------------------------------------------------------------------


def _comm(proc: Path, pid: int) -> str:
    try:
        return (proc / str(pid) / "comm").read_text().strip()
    except OSError:
        return "?"


def _pids(proc: Path) -> list[int]:
    try:
        return sorted(int(p) for p in os.listdir(proc) if p.isdigit())
    except OSError:
        return []


def fd_holders(targets: Iterable[str], proc: Path, exclude: Iterable[int] = ()) -> list[Holder]:
    """Processes with an open descriptor whose /proc link reads as one of `targets`
    (a device's real path, or `socket:[INODE]`). Processes we may not inspect (another
    user's, when not root) are invisible: the result is then a lower bound."""
    wanted, skip = set(targets), set(exclude)
    found = []
    for pid in _pids(proc):
        if pid in skip:
            continue
        fd_dir = proc / str(pid) / "fd"
        try:
            names = os.listdir(fd_dir)
        except OSError:
            continue
        for name in names:
            try:
                if os.readlink(fd_dir / name) in wanted:
                    found.append(Holder(pid, _comm(proc, pid)))
                    break
            except OSError:
                continue
    return found


def processes_named(name: str, proc: Path) -> list[Holder]:
    return [Holder(pid, name) for pid in _pids(proc) if _comm(proc, pid) == name]


def _is_service(holder: Holder) -> bool:
    return holder.name.startswith("treetraits")


# --- config ---------------------------------------------------------------------------


def check_config(path: Path | None) -> tuple[Check, ServiceConfig]:
    """Load the config; on failure report it and go on with the defaults."""
    if path is None:
        if DEFAULT_CONFIG_PATH.exists():
            path = DEFAULT_CONFIG_PATH
        else:
            return (
                Check(
                    "config",
                    Status.WARN,
                    f"no {DEFAULT_CONFIG_PATH}: checking against the built-in defaults",
                    "sudo make install (installs the default config), or --config FILE",
                ),
                load_config(None),
            )
    try:
        return Check("config", Status.OK, f"{path} loads"), load_config(path)
    except TreetraitsError as error:
        return (
            Check(
                "config", Status.FAIL, str(error), f"edit {path}; `treetraits config check {path}`"
            ),
            load_config(None),
        )


# --- serial ports ---------------------------------------------------------------------


def check_serial_port(name: str, port: str, proc: Path = Path("/proc")) -> list[Check]:
    """The port exists, is a character device, is readable and writable by this user,
    and nobody else holds it."""
    label = f"{name} port"
    real = os.path.realpath(port)
    shown = port if real == port else f"{port} (-> {real})"
    try:
        mode = os.stat(port).st_mode
    except FileNotFoundError:
        return [
            Check(
                label,
                Status.FAIL,
                f"{port} does not exist",
                "plug the device in and power it; install the udev rules for the stable "
                f"names (sudo make install, then replug); see `ls -l /dev/serial/by-id/`; "
                f"or set the port in the config ({name} section)",
            )
        ]
    except OSError as error:
        return [Check(label, Status.FAIL, f"{port}: {error.strerror}", "check the path")]
    if not stat.S_ISCHR(mode):
        return [
            Check(
                label,
                Status.FAIL,
                f"{shown} is not a character device",
                f"point the config's {name} port at the serial device (/dev/ttyUSB*, /dev/ttyACM*)",
            )
        ]
    checks = []
    if os.access(real, os.R_OK | os.W_OK):
        checks.append(Check(label, Status.OK, f"{shown}: character device, read/write allowed"))
    else:
        user = _user_name()
        checks.append(
            Check(
                label,
                Status.FAIL,
                f"{shown}: no read/write permission for {user} "
                f"(owner {_owner(real)}, mode {stat.filemode(mode)})",
                f"sudo usermod -aG dialout {user} and log in again; the service user gets "
                "it from the unit (SupplementaryGroups=dialout)",
            )
        )
    holders = fd_holders([real], proc, exclude=[os.getpid()])
    if holders:
        ours = all(_is_service(h) for h in holders)
        checks.append(
            Check(
                f"{name} port holders",
                Status.OK if ours else Status.WARN,
                f"{shown} is open in " + ", ".join(str(h) for h in holders),
                ""
                if ours
                else "only one program may read the port: stop the other one (ModemManager: "
                "install the udev rule with ID_MM_DEVICE_IGNORE, or `sudo systemctl disable "
                "--now ModemManager`; gpsd: `sudo systemctl stop gpsd gpsd.socket`)",
            )
        )
    return checks


def _user_name() -> str:
    try:
        return pwd.getpwuid(os.geteuid()).pw_name
    except KeyError:
        return str(os.geteuid())


def _owner(path: str) -> str:
    info = os.stat(path)
    try:
        user = pwd.getpwuid(info.st_uid).pw_name
    except KeyError:
        user = str(info.st_uid)
    try:
        group = grp.getgrgid(info.st_gid).gr_name
    except KeyError:
        group = str(info.st_gid)
    return f"{user}:{group}"


def check_modemmanager(proc: Path = Path("/proc"), udev_rules: Path = Path(UDEV_RULES)) -> Check:
    running = processes_named("ModemManager", proc)
    if not running:
        return Check("ModemManager", Status.OK, "not running")
    if udev_rules.exists():
        return Check(
            "ModemManager",
            Status.OK,
            f"running ({running[0]}); {udev_rules} tells it to ignore the GNSS and Jackal ports",
        )
    return Check(
        "ModemManager",
        Status.WARN,
        f"running ({running[0]}) and {udev_rules} is missing: it probes new serial ports and "
        "can hold the GNSS or Jackal port for seconds",
        "sudo make install (udev rule with ID_MM_DEVICE_IGNORE), or, with no modem on the "
        "robot, sudo systemctl disable --now ModemManager",
    )


# --- USB and video --------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class UsbDevice:
    port: str  # sysfs name, BUS-PORT[.PORT]
    usb_id: str  # vvvv:pppp
    product: str


def list_usb_devices(sysfs: Path = Path("/sys")) -> list[UsbDevice]:
    root = sysfs / "bus" / "usb" / "devices"
    found = []
    with contextlib.suppress(OSError):
        for entry in sorted(root.iterdir()):
            try:
                vid = (entry / "idVendor").read_text().strip().lower()
                pid = (entry / "idProduct").read_text().strip().lower()
            except OSError:
                continue  # an interface, not a device
            try:
                product = (entry / "product").read_text().strip()
            except OSError:
                product = ""
            found.append(UsbDevice(entry.name, f"{vid}:{pid}", product))
    return found


def check_usb(config: ServiceConfig, sysfs: Path = Path("/sys")) -> Check:
    """The USB devices this robot should have, by id (and the camera by product name)."""
    devices = list_usb_devices(sysfs)
    known = [
        f"{KNOWN_USB.get(d.usb_id, d.product or 'camera')} {d.usb_id} at {d.port}"
        for d in devices
        if d.usb_id in KNOWN_USB or CAMERA_PRODUCT.search(d.product)
    ]
    missing, fixes = [], []
    jackal = config.wheels.enabled and config.wheels.kind == "jackal"
    if jackal and not any(d.usb_id == JACKAL_USB for d in devices):
        missing.append(f"Jackal MCU ({JACKAL_USB})")
        fixes.append("power the Jackal and plug its MCU USB cable in")
    if config.gnss.enabled and not any(d.usb_id.startswith(GNSS_USB_PREFIXES) for d in devices):
        missing.append("a GNSS receiver (u-blox 1546:*, or an FTDI/CP210x/CH340 adapter)")
        fixes.append("plug the GNSS receiver in (lsusb lists what is there)")
    camera_auto = config.camera.device == "auto"
    if (
        config.camera.enabled
        and camera_auto
        and not any(CAMERA_PRODUCT.search(d.product) for d in devices)
    ):
        missing.append("the Survey3N (product MAPIR/Survey)")
        fixes.append("plug the camera into USB and switch it on in camera (not disk) mode")
    detail = "found: " + ("; ".join(known) if known else f"none of ours among {len(devices)}")
    if missing:
        return Check(
            "USB devices", Status.WARN, f"missing {', '.join(missing)}; {detail}", "; ".join(fixes)
        )
    return Check("USB devices", Status.OK, detail)


def check_camera(config: ServiceConfig, roots: Roots = Roots()) -> list[Check]:
    """The V4L2 nodes there are, and which one the configured camera resolves to."""
    if not config.camera.enabled:
        return [Check("camera", Status.OK, "disabled in the config")]
    devices = list_video_devices(roots.sys, roots.dev)
    listing = "; ".join(d.describe() for d in devices) or "no V4L2 devices"
    checks = [
        Check(
            "video devices",
            Status.OK if devices else Status.WARN,
            listing,
            "" if devices else "plug the camera in; lsmod | grep uvcvideo",
        )
    ]
    spec = config.camera.device
    try:
        node = resolve_device(spec, roots.sys, roots.dev)
    except TreetraitsError as error:
        checks.append(Check("camera", Status.FAIL, str(error), "set camera.device in the config"))
        return checks
    if os.path.isfile(node):
        checks.append(Check("camera", Status.OK, f"{spec}: a video file (playback)"))
    elif not os.path.exists(node):
        checks.append(
            Check(
                "camera",
                Status.FAIL,
                f"{spec}: {node} does not exist",
                "plug the camera in; install the udev rules (sudo make install) for /dev/survey3n",
            )
        )
    elif not os.access(node, os.R_OK | os.W_OK):
        user = _user_name()
        checks.append(
            Check(
                "camera",
                Status.FAIL,
                f"{spec}: {node} not readable/writable by {user}",
                f"sudo usermod -aG video {user} and log in again",
            )
        )
    else:
        holders = fd_holders([os.path.realpath(node)], roots.proc, exclude=[os.getpid()])
        held = f"; open in {', '.join(map(str, holders))}" if holders else ""
        checks.append(Check("camera", Status.OK, f"{spec} -> {node}{held}"))
    return checks


# --- LiDAR UDP ------------------------------------------------------------------------


def udp_port_inodes(port: int, proc: Path = Path("/proc")) -> list[str]:
    """Inodes of the UDP sockets bound to `port` (IPv4 and IPv6), from /proc/net/udp*."""
    inodes = []
    for table in ("udp", "udp6"):
        try:
            lines = (proc / "net" / table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 9 and int(fields[1].rsplit(":", 1)[1], 16) == port:
                inodes.append(fields[9])
    return inodes


def check_udp(bind: str, port: int, seconds: float, proc: Path = Path("/proc")) -> Check:
    """Bind the LiDAR port briefly and wait for a datagram; if it is taken, say by whom."""
    name = f"UDP {port}"
    sock = socket.socket(socket.AF_INET6 if ":" in bind else socket.AF_INET, socket.SOCK_DGRAM)
    try:
        try:
            sock.bind((bind, port))
        except OSError as error:
            holders = fd_holders(
                [f"socket:[{i}]" for i in udp_port_inodes(port, proc)], proc, exclude=[os.getpid()]
            )
            who = ", ".join(map(str, holders)) or "another process (run as root to see which)"
            if holders and all(_is_service(h) for h in holders):
                return Check(name, Status.OK, f"in use by the running service: {who}")
            return Check(
                name,
                Status.FAIL,
                f"cannot bind {bind}:{port} ({error.strerror}); held by {who}",
                "stop that program (e.g. a ROS velodyne_driver, VeloView, or a second "
                "treetraits), then run doctor again",
            )
        start = time.monotonic()
        count, senders, sizes = 0, set(), set()
        while (left := seconds - (time.monotonic() - start)) > 0:
            ready, _, _ = select.select([sock], [], [], left)
            if not ready:
                break
            data, sender = sock.recvfrom(65535)
            count += 1
            senders.add(sender[0])
            sizes.add(len(data))
        if count:
            return Check(
                name,
                Status.OK,
                f"{count} datagrams in {time.monotonic() - start:.1f} s from "
                f"{', '.join(sorted(senders))} (sizes {', '.join(map(str, sorted(sizes)))}; "
                "a VLP-16 data packet is 1206 bytes)",
            )
        return Check(
            name,
            Status.FAIL,
            f"nothing received on {bind}:{port} in {seconds:g} s",
            "check the LiDAR's power and Ethernet cable; give this host an address in the "
            "sensor's subnet (VLP-16 default 192.168.1.201: e.g. sudo ip addr add "
            "192.168.1.100/24 dev eth0); check its web page for the destination IP and port; "
            "check the firewall",
        )
    finally:
        sock.close()


def check_rmem(rcvbuf_bytes: int, proc: Path = Path("/proc")) -> Check:
    """net.core.rmem_max caps the LiDAR socket's SO_RCVBUF."""
    path = proc / "sys" / "net" / "core" / "rmem_max"
    try:
        rmem_max = int(path.read_text())
    except (OSError, ValueError) as error:
        return Check("rmem_max", Status.WARN, f"cannot read {path}: {error}")
    if rmem_max >= rcvbuf_bytes:
        return Check(
            "rmem_max",
            Status.OK,
            f"net.core.rmem_max {rmem_max} >= lidar.rcvbuf_bytes {rcvbuf_bytes}",
        )
    return Check(
        "rmem_max",
        Status.WARN,
        f"net.core.rmem_max {rmem_max} < lidar.rcvbuf_bytes {rcvbuf_bytes}: the LiDAR socket "
        f"gets {rmem_max} bytes, about {rmem_max / _VLP16_BUFFER_BYTES_PER_S:.1f} s of "
        "VLP-16 packets, and drops packets when the process pauses longer",
        f"sudo install -m 644 {SYSCTL_FILE} /etc/sysctl.d/ && sudo sysctl --system "
        "(sudo make install does it)",
    )


# --- users, firewall, disk -------------------------------------------------------------


def check_groups(user: str | None = None, required: Iterable[str] = SERVICE_GROUPS) -> Check:
    """`user` (default: whoever runs this) is in the groups the devices belong to.
    For the running user, the groups of this process count, not just /etc/group."""
    me = user is None
    name = _user_name() if me else user
    assert name is not None
    try:
        entry = pwd.getpwnam(name)
    except KeyError:
        return Check(
            f"groups of {name}",
            Status.FAIL if not me else Status.WARN,
            f"no user {name}",
            "sudo make install (creates the service user treetraits)"
            if name == SERVICE_USER
            else "",
        )
    if me and os.geteuid() == 0:
        return Check(f"groups of {name}", Status.OK, "root: device permissions do not apply")
    # For the running user the groups of this process count, not just /etc/group.
    gids = set(os.getgroups()) | {os.getegid()} if me else set(os.getgrouplist(name, entry.pw_gid))
    missing, stale = [], []
    for group in required:
        try:
            info = grp.getgrnam(group)
        except KeyError:
            missing.append(group)
            continue
        if info.gr_gid in gids:
            continue
        missing.append(group)
        if me and name in info.gr_mem:
            stale.append(group)  # added in /etc/group, but this session predates it
    if not missing:
        return Check(f"groups of {name}", Status.OK, f"member of {', '.join(required)}")
    if stale and len(stale) == len(missing):
        return Check(
            f"groups of {name}",
            Status.WARN,
            f"in {', '.join(stale)} per /etc/group, but not in this login session",
            "log out and in again (or run: newgrp dialout)",
        )
    return Check(
        f"groups of {name}",
        Status.FAIL,
        f"not in {', '.join(missing)}: serial ports (dialout) and cameras (video) need them",
        f"sudo usermod -aG {','.join(missing)} {name}" + (" and log in again" if me else ""),
    )


def _run(argv: list[str]) -> str | None:
    if shutil.which(argv[0]) is None:
        return None
    try:
        result = subprocess.run(argv, capture_output=True, text=True, timeout=5, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return result.stdout if result.returncode == 0 else None


def check_firewall(ports: Iterable[int]) -> Check:
    """Best effort: an active ufw or an nftables input chain that drops by default and
    does not mention the LiDAR ports."""
    ports = [p for p in ports if p]
    status = _run(["ufw", "status"])
    if status is not None and status.startswith("Status: active"):
        closed = [p for p in ports if not re.search(rf"\b{p}(/udp)?\b", status)]
        if closed:
            return Check(
                "firewall",
                Status.WARN,
                f"ufw is active with no rule for UDP {', '.join(map(str, closed))}",
                " && ".join(f"sudo ufw allow {p}/udp" for p in closed),
            )
        return Check("firewall", Status.OK, "ufw allows the LiDAR ports")
    ruleset = _run(["nft", "list", "ruleset"])
    if ruleset and re.search(r"hook input .*policy drop", ruleset):
        closed = [p for p in ports if str(p) not in ruleset]
        if closed:
            return Check(
                "firewall",
                Status.WARN,
                "an nftables input chain drops by default and names no UDP "
                + ", ".join(map(str, closed)),
                "add e.g. `udp dport { 2368, 8308 } accept` to that input chain",
            )
    if status is None and ruleset is None:
        return Check("firewall", Status.OK, "no ufw/nft (or not root): not checked")
    return Check("firewall", Status.OK, "no active rule set blocking the LiDAR ports found")


def check_disk(directory: str, min_free_bytes: int = 10 * 1024**3) -> Check:
    """Free space where the outputs (and recordings) go."""
    path = Path(directory)
    probe = path
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    usage = shutil.disk_usage(probe)
    free_gib = usage.free / 1024**3
    where = str(path) if probe == path else f"{path} (not created yet; on {probe})"
    detail = f"{free_gib:.1f} GiB free of {usage.total / 1024**3:.1f} GiB at {where}"
    if usage.free < min_free_bytes:
        return Check(
            "disk",
            Status.WARN if usage.free >= 1024**3 else Status.FAIL,
            detail + f" (want >= {min_free_bytes / 1024**3:.0f} GiB; a recording takes a few GB/h)",
            "free space, or point output.dir / record.dir at a bigger disk",
        )
    return Check("disk", Status.OK, detail)


# --- all of it ------------------------------------------------------------------------


def run_checks(
    config_path: Path | None,
    *,
    roots: Roots = Roots(),
    udp_seconds: float = 2.0,
    udev_rules: Path = Path(UDEV_RULES),
) -> list[Check]:
    config_check, config = check_config(config_path)
    checks = [config_check]
    if config.gnss.enabled:
        checks += check_serial_port("gnss", config.gnss.port, roots.proc)
    if config.wheels.enabled:
        checks += check_serial_port("wheels", config.wheels.port, roots.proc)
    checks.append(check_modemmanager(roots.proc, udev_rules))
    checks.append(check_usb(config, roots.sys))
    checks += check_camera(config, roots)
    if config.lidar.enabled:
        checks.append(check_udp(config.lidar.bind, config.lidar.data_port, udp_seconds, roots.proc))
        checks.append(check_rmem(config.lidar.rcvbuf_bytes, roots.proc))
        checks.append(check_firewall([config.lidar.data_port, config.lidar.telemetry_port]))
    checks.append(check_groups())
    with contextlib.suppress(KeyError):
        pwd.getpwnam(SERVICE_USER)
        if _user_name() != SERVICE_USER:
            checks.append(check_groups(SERVICE_USER))
    checks.append(check_disk(config.output.dir))
    return checks
