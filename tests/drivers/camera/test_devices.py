"""Finding the camera's node, on a sysfs tree laid out as Linux lays it out for two UVC
cameras (each with a capture node, index 0, and a metadata node, index 1); and the V4L2
structures `camera info` reads, against the numbers of linux/videodev2.h.
"""

from __future__ import annotations

import struct
from types import SimpleNamespace

import pytest
import usb.core

from tests.helpers.sysfs import make_sysfs
from treetraits.drivers.camera import v4l2
from treetraits.drivers.camera.devices import (
    find_usb_ports,
    list_video_devices,
    resolve_device,
    usb_port_name,
)
from treetraits.errors import ConfigError, SourceError

LAPTOP = (0, "Integrated Camera: Integrated C", "04f2", "b6dd", "1-5")
SURVEY = (2, "MAPIR Survey3N: MAPIR Survey3N", "1a2b", "3c4d", "3-1.2")


def test_auto_picks_the_capture_node_named_mapir(tmp_path):
    sysfs, dev = make_sysfs(tmp_path, [LAPTOP, SURVEY])
    devices = list_video_devices(sysfs, dev)
    assert [(d.node[-6:], d.index, d.usb_id, d.usb_port) for d in devices] == [
        ("video0", 0, "04f2:b6dd", "1-5"),
        ("video1", 1, "04f2:b6dd", "1-5"),
        ("video2", 0, "1a2b:3c4d", "3-1.2"),
        ("video3", 1, "1a2b:3c4d", "3-1.2"),
    ]
    assert all(d.capture is None for d in devices)  # no real node to ask: index decides
    assert resolve_device("auto", sysfs, dev) == str(dev / "video2")


def test_auto_without_a_survey_lists_what_it_found(tmp_path):
    sysfs, dev = make_sysfs(tmp_path, [LAPTOP])
    with pytest.raises(SourceError) as error:
        resolve_device("auto", sysfs, dev)
    message = str(error.value)
    assert "no V4L2 capture device named like MAPIR/Survey" in message
    assert "video0 'Integrated Camera: Integrated C' (capture, USB 04f2:b6dd at 1-5)" in message
    assert "--device" in message

    with pytest.raises(SourceError, match=r"no V4L2 video devices at all.*uvcvideo"):
        resolve_device("auto", tmp_path / "empty", dev)


def test_usb_vid_pid_maps_through_pyusb_and_sysfs(tmp_path, monkeypatch):
    sysfs, dev = make_sysfs(tmp_path, [LAPTOP, SURVEY])
    plugged = [SimpleNamespace(bus=3, port_numbers=(1, 2), idVendor=0x1A2B, idProduct=0x3C4D)]

    def find(find_all=False, idVendor=None, idProduct=None):
        return [d for d in plugged if (d.idVendor, d.idProduct) == (idVendor, idProduct)]

    monkeypatch.setattr(usb.core, "find", find)  # no USB camera on CI
    assert resolve_device("usb:1a2b:3c4d", sysfs, dev) == str(dev / "video2")
    with pytest.raises(SourceError, match="usb:04f2:0001: no such USB device"):
        resolve_device("usb:04f2:0001", sysfs, dev)


def test_usb_lookup_falls_back_to_sysfs_without_libusb(tmp_path, monkeypatch):
    sysfs, dev = make_sysfs(tmp_path, [LAPTOP, SURVEY])

    def no_backend(**_):
        raise usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(usb.core, "find", no_backend)
    assert find_usb_ports(0x1A2B, 0x3C4D, sysfs) == ["3-1.2"]
    assert resolve_device("usb:1A2B:3C4D", sysfs, dev) == str(dev / "video2")


def test_usb_device_without_a_video_node_is_explained(tmp_path, monkeypatch):
    sysfs, dev = make_sysfs(tmp_path, [LAPTOP])
    disk = SimpleNamespace(bus=2, port_numbers=(4,))
    monkeypatch.setattr(usb.core, "find", lambda **_: [disk])
    with pytest.raises(SourceError, match=r"at 2-4 but has no V4L2 capture node.*media-transfer"):
        resolve_device("usb:1a2b:3c4d", sysfs, dev)


def test_plain_names_and_paths():
    assert resolve_device("3") == "/dev/video3"
    assert resolve_device("/dev/video0") == "/dev/video0"
    by_id = "/dev/v4l/by-id/usb-MAPIR_Survey3N-video-index0"
    assert resolve_device(by_id) == by_id  # opened as given: the link follows a replug
    assert resolve_device("/dev/survey3n") == "/dev/survey3n"
    for bad in ("usb:xyz", "camera", "usb:1:2:3"):
        with pytest.raises(ConfigError):
            resolve_device(bad)
    assert usb_port_name(1, (2, 4)) == "1-2.4"
    assert usb_port_name(1, None) is None  # a root hub


# --- V4L2 structures ---------------------------------------------------------------


def test_ioctl_numbers_are_those_of_videodev2_h():
    # Printed by a C program including <linux/videodev2.h> (kernel 6.x headers, x86-64;
    # arm64 uses the same generic _IOC encoding and these structs have no pointers).
    assert v4l2.VIDIOC_QUERYCAP == 0x80685600
    assert v4l2.VIDIOC_ENUM_FMT == 0xC0405602
    assert v4l2.VIDIOC_G_CTRL == 0xC008561B
    assert v4l2.VIDIOC_QUERYCTRL == 0xC0445624
    assert v4l2.VIDIOC_QUERYMENU == 0xC02C5625
    assert v4l2.VIDIOC_ENUM_FRAMESIZES == 0xC02C564A
    assert v4l2.VIDIOC_ENUM_FRAMEINTERVALS == 0xC034564B


def test_parse_structures():
    cap = struct.pack(
        "<16s32s32sIII12x", b"uvcvideo", b"MAPIR Survey3N", b"usb-0000:00:14.0-2", 0x060800,
        0x84A00001, 0x04200001,
    )  # fmt: skip
    parsed = v4l2.parse_capability(cap)
    assert (parsed.driver, parsed.card, parsed.version) == ("uvcvideo", "MAPIR Survey3N", "6.8.0")
    assert parsed.is_video_capture and not parsed.is_metadata
    meta = struct.pack("<16s32s32sIII12x", b"uvcvideo", b"x", b"y", 0, 0x84A00001, 0x04800000)
    assert v4l2.parse_capability(meta).is_metadata
    assert not v4l2.parse_capability(meta).is_video_capture

    fmt = struct.pack("<III32sII12x", 0, 1, 1, b"Motion-JPEG", v4l2.fourcc_code("MJPG"), 0)
    assert v4l2.parse_fmtdesc(fmt) == (v4l2.fourcc_code("MJPG"), "Motion-JPEG", True)
    size = struct.pack("<III6I8x", 0, 0, 1, 1280, 720, 0, 0, 0, 0)
    assert v4l2.parse_frmsize(size) == (1, (1280, 720))
    interval = struct.pack("<IIIII6I8x", 0, 0, 1280, 720, 1, 1, 30, 0, 0, 0, 0)
    assert v4l2.parse_frmival(interval) == (1, (30.0,))
    stepwise = struct.pack("<IIIII6I8x", 0, 0, 1280, 720, 3, 1, 60, 1, 5, 1, 60)
    assert v4l2.parse_frmival(stepwise) == (3, (5.0, 60.0))
    ctrl = struct.pack(
        "<II32siiiiI8x", 0x009A0902, 1, b"Exposure Time, Absolute", 1, 5000, 1, 156, 0x10
    )
    assert v4l2.parse_queryctrl(ctrl) == (
        0x009A0902, "Exposure Time, Absolute", "int", 1, 5000, 1, 156, 0x10,
    )  # fmt: skip
    assert v4l2.fourcc_text(0x47504A4D) == "MJPG"
    assert v4l2.fourcc_code("YUYV") == 0x56595559


def test_enumerating_a_missing_node_raises_oserror(tmp_path):
    with pytest.raises(OSError):
        v4l2.list_modes(tmp_path / "video0")
    with pytest.raises(OSError):
        v4l2.query_capability(tmp_path / "video0")
