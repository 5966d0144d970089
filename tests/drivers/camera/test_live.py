"""The live camera path with the only thing CI cannot have replaced: the USB camera.

`cv2.VideoCapture` is swapped, at the outermost boundary, for `FakeCapture`: it serves
real MJPG frames (JPEGs encoded by cv2.imencode from real images), paces them at the
device's frame rate, stamps them like the kernel does (CLOCK_MONOTONIC, start of
exposure), applies the V4L2 backend's property rules (size applied when both width and
height are set, the nearest offered mode granted, -1 for a missing control) and records
every property set on it. The grab thread, ring, timestamping, backoff and reopen logic in
`drivers.camera.live` run for real.
"""

from __future__ import annotations

import itertools
import logging
import time

import cv2
import numpy as np
import pytest

from treetraits.drivers.camera import CameraSettings, UvcCamera, open_camera_source
from treetraits.drivers.camera.frames import ClockSample, capture_time_ns
from treetraits.drivers.camera.v4l2 import fourcc_code
from treetraits.errors import ConfigError, SourceError

MJPG = fourcc_code("MJPG")
MS = 1_000_000


def sample_images(width: int, height: int, count: int = 6) -> list[np.ndarray]:
    """Distinct real images: gradients with a moving bar, so each frame differs."""
    y, x = np.mgrid[0:height, 0:width]
    images = []
    for k in range(count):
        image = np.dstack([(x * 255 // width), (y * 255 // height), np.full_like(x, 40 * k)])
        image = image.astype(np.uint8)
        image[:, (k * width // count) : (k * width // count) + 8] = 255
        images.append(image)
    return images


def encode(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return data.tobytes()


class FakeDevice:
    """The camera at the end of the cable: its modes, controls, and whether it is there."""

    def __init__(
        self,
        sizes=((1280, 720),),
        fourccs=("MJPG",),
        fps=30.0,
        controls=None,
        read_only=(),
        limits=None,
        ignores_convert_rgb=False,
        latency_ms=40.0,
    ):
        self.sizes = list(sizes)
        self.fourccs = [fourcc_code(f) for f in fourccs]
        self.fps = fps
        self.controls = dict(controls or {})
        self.read_only = set(read_only)
        self.limits = dict(limits or {})
        self.ignores_convert_rgb = ignores_convert_rgb
        self.latency_ms = latency_ms
        self.plugged = True
        self.captures: list[FakeCapture] = []
        self.jpegs = {size: [encode(i) for i in sample_images(*size)] for size in self.sizes}

    def open(self, path: str, api: int) -> FakeCapture:
        capture = FakeCapture(self, path, api)
        self.captures.append(capture)
        return capture


class FakeCapture:
    """Stands in for cv2.VideoCapture(path, cv2.CAP_V4L2) on a UVC camera."""

    def __init__(self, device: FakeDevice, path: str, api: int):
        self.device, self.path, self.api = device, path, api
        self.opened = device.plugged
        self.sets: list[tuple[int, float, bool]] = []
        self.fourcc = device.fourccs[0]
        self.width, self.height = device.sizes[-1]
        self.pending_size: dict[int, int] = {}
        self.convert_rgb = True
        self.buffers = 4
        self.index = -1
        self.stamp_ms = 0.0
        self.next_due = time.monotonic()
        self.served: list[bytes] = []

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return self.opened

    def release(self) -> None:
        self.opened = False

    def set(self, prop: int, value: float) -> bool:
        ok = self._set(prop, value)
        self.sets.append((prop, value, ok))
        return ok

    def _set(self, prop: int, value: float) -> bool:
        device = self.device
        if prop == cv2.CAP_PROP_FOURCC:
            if int(value) not in device.fourccs:
                return False
            self.fourcc = int(value)
            return True
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            self.pending_size[prop] = int(value)
            if len(self.pending_size) == 2:  # applied when both are set, like the backend
                w = self.pending_size[cv2.CAP_PROP_FRAME_WIDTH]
                h = self.pending_size[cv2.CAP_PROP_FRAME_HEIGHT]
                self.width, self.height = min(
                    device.sizes, key=lambda s: abs(s[0] - w) + abs(s[1] - h)
                )
                self.pending_size.clear()
            return True
        if prop == cv2.CAP_PROP_FPS:
            return True  # the fake offers one rate: it is granted whatever is asked
        if prop == cv2.CAP_PROP_CONVERT_RGB:
            self.convert_rgb = bool(value)
            return True
        if prop == cv2.CAP_PROP_BUFFERSIZE:
            self.buffers = int(value)
            return True
        if prop == cv2.CAP_PROP_MODE:
            return True
        if prop not in device.controls or prop in device.read_only:
            return False
        low, high = device.limits.get(prop, (-(2**31), 2**31 - 1))
        device.controls[prop] = float(min(max(value, low), high))
        return True

    def get(self, prop: int) -> float:
        values = {
            cv2.CAP_PROP_FOURCC: float(self.fourcc),
            cv2.CAP_PROP_FRAME_WIDTH: float(self.width),
            cv2.CAP_PROP_FRAME_HEIGHT: float(self.height),
            cv2.CAP_PROP_FPS: self.device.fps,
            cv2.CAP_PROP_CONVERT_RGB: float(self.convert_rgb),
            cv2.CAP_PROP_BUFFERSIZE: float(self.buffers),
            cv2.CAP_PROP_POS_MSEC: self.stamp_ms,
        }
        if prop in values:
            return values[prop]
        return float(self.device.controls.get(prop, -1.0))

    def grab(self) -> bool:
        if not (self.opened and self.device.plugged):
            return False  # ENODEV: an unplugged device fails at once
        now = time.monotonic()
        if now < self.next_due:
            time.sleep(self.next_due - now)
        self.next_due = max(self.next_due, time.monotonic() - 1.0) + 1.0 / self.device.fps
        exposure_start = time.clock_gettime_ns(time.CLOCK_MONOTONIC) - self.device.latency_ms * MS
        self.stamp_ms = round(exposure_start / 1000) / 1000  # a timeval, in ms
        self.index += 1
        return True

    def retrieve(self):
        if not (self.opened and self.device.plugged) or self.index < 0:
            return False, None
        jpegs = self.device.jpegs[(self.width, self.height)]
        data = jpegs[self.index % len(jpegs)]
        self.served.append(data)
        if self.convert_rgb or self.device.ignores_convert_rgb:
            return True, cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        return True, np.frombuffer(data, np.uint8).reshape(1, -1).copy()


def settings(**overrides) -> CameraSettings:
    values = {"backoff_initial_s": 0.05, "backoff_max_s": 0.4}
    values.update(overrides)
    return CameraSettings(**values)


def wait_until(condition, timeout: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


def test_asks_for_mjpg_720p30_and_reports_what_the_device_gave(caplog):
    device = FakeDevice(sizes=[(640, 480)])  # this camera only offers VGA
    caplog.set_level(logging.WARNING, logger="treetraits.camera")
    with UvcCamera("/dev/video0", settings(), capture_factory=device.open) as camera:
        capture = device.captures[0]
        assert capture.path == "/dev/video0" and capture.api == cv2.CAP_V4L2
        asked = [(prop, value) for prop, value, _ in capture.sets]
        order = [p for p, _ in asked]
        # The order the V4L2 backend needs: fourcc, width and height, then the rate.
        assert asked[:4] == [
            (cv2.CAP_PROP_FOURCC, MJPG),
            (cv2.CAP_PROP_FRAME_WIDTH, 1280),
            (cv2.CAP_PROP_FRAME_HEIGHT, 720),
            (cv2.CAP_PROP_FPS, 30.0),
        ]
        assert (cv2.CAP_PROP_CONVERT_RGB, 0) in asked
        assert order.index(cv2.CAP_PROP_CONVERT_RGB) > order.index(cv2.CAP_PROP_FPS)

        got = camera.negotiation
        assert (got.fourcc, got.width, got.height, got.fps) == ("MJPG", 640, 480, 30.0)
        assert got.raw_jpeg
        assert got.mismatches == ["size 640x480 instead of 1280x720"]
        assert "640x480 instead of 1280x720" in caplog.text

        frame = camera.next_frame(timeout=2.0)
        assert frame is not None
        assert camera.decode(frame).shape == (480, 640, 3)


def test_strict_mode_refuses_another_mode_and_releases_the_device():
    device = FakeDevice(sizes=[(640, 480)])
    with pytest.raises(SourceError, match=r"640x480 instead of 1280x720.*camera info"):
        UvcCamera("/dev/video0", settings(strict_mode=True), capture_factory=device.open)
    assert not device.captures[0].opened


def test_exposure_gain_and_white_balance_locked_where_the_device_allows():
    device = FakeDevice(
        controls={
            cv2.CAP_PROP_AUTO_EXPOSURE: 3,  # aperture priority (auto)
            cv2.CAP_PROP_EXPOSURE: 156,
            cv2.CAP_PROP_GAIN: 4,
            cv2.CAP_PROP_AUTO_WB: 1,
            cv2.CAP_PROP_WB_TEMPERATURE: 4600,
        },
        read_only={cv2.CAP_PROP_WB_TEMPERATURE},
        limits={cv2.CAP_PROP_GAIN: (0, 100)},
    )
    wanted = settings(exposure=50, gain=250, wb_temperature=5000)
    with UvcCamera("/dev/video0", wanted, capture_factory=device.open) as camera:
        outcome = {c.name: c for c in camera.controls}
    assert set(outcome) == {
        "auto_exposure",
        "exposure",
        "gain",
        "auto_white_balance",
        "white_balance_temperature",
    }
    assert (outcome["auto_exposure"].before, outcome["auto_exposure"].after) == (3, 1)
    assert outcome["auto_exposure"].status == "set"
    assert (outcome["exposure"].after, outcome["exposure"].status) == (50, "set")
    assert (outcome["gain"].after, outcome["gain"].status) == (100, "differs")  # clamped
    assert (outcome["auto_white_balance"].after, outcome["auto_white_balance"].status) == (
        0,
        "set",
    )
    assert outcome["white_balance_temperature"].status == "refused"
    assert outcome["white_balance_temperature"].after == 4600
    # Manual exposure went in before the exposure value (or the value would not stick).
    order = [prop for prop, _, _ in device.captures[0].sets]
    assert order.index(cv2.CAP_PROP_AUTO_EXPOSURE) < order.index(cv2.CAP_PROP_EXPOSURE)


def test_controls_the_device_lacks_are_reported_unsupported_and_values_kept():
    device = FakeDevice(controls={cv2.CAP_PROP_AUTO_EXPOSURE: 3, cv2.CAP_PROP_EXPOSURE: 156})
    with UvcCamera("/dev/video0", settings(), capture_factory=device.open) as camera:
        outcome = {c.name: (c.status, c.after) for c in camera.controls}
    assert outcome == {
        "auto_exposure": ("set", 1),
        "exposure": ("kept", 156),  # frozen where auto exposure left it
        "gain": ("unsupported", None),
        "auto_white_balance": ("unsupported", None),
        "white_balance_temperature": ("unsupported", None),
    }

    device = FakeDevice(controls={cv2.CAP_PROP_AUTO_EXPOSURE: 3})
    with UvcCamera("/dev/video0", settings(lock=False), capture_factory=device.open) as camera:
        assert {c.name: c.status for c in camera.controls}["auto_exposure"] == "kept"
    assert device.controls[cv2.CAP_PROP_AUTO_EXPOSURE] == 3


@pytest.mark.realtime
def test_frames_arrive_on_the_thread_with_rising_times_and_nothing_is_decoded(decode_calls):
    device = FakeDevice(latency_ms=40.0)
    with UvcCamera("/dev/video0", settings(), capture_factory=device.open) as camera:
        frames = []
        deadline = time.monotonic() + 0.6
        while time.monotonic() < deadline:
            frame = camera.next_frame(timeout=0.5)
            if frame is not None:
                frames.append(frame)
        assert decode_calls == []  # 30 fps of 720p grabbed, not one decode
        assert camera.stats.decoded == 0

        assert len(frames) >= 12
        t_host = [f.t_host for f in frames]
        assert all(b > a for a, b in itertools.pairwise(t_host))
        assert [f.sequence for f in frames] == sorted({f.sequence for f in frames})
        # t_capture is the exposure start the (fake) kernel stamped, on the realtime clock.
        for frame in frames:
            assert 40 * MS - 1000 <= frame.t_host - frame.t_capture <= 100 * MS
        assert abs(frames[-1].t_host - time.time_ns()) < 2_000 * MS
        # The bytes are the camera's own, not a re-encoding.
        served = set(device.captures[0].served)
        assert all(f.jpeg in served for f in frames)
        assert camera.stats.reencoded == 0 and camera.stats.timestamp_fallbacks == 0

        image = camera.decode(frames[-1])
        assert image.shape == (720, 1280, 3)
        assert len(decode_calls) == 1 and camera.stats.decoded == 1


def test_the_ring_keeps_the_newest_frames_and_counts_the_overwritten(decode_calls):
    device = FakeDevice(fps=60.0)
    with UvcCamera("/dev/video0", settings(ring_size=4), capture_factory=device.open) as camera:
        assert wait_until(lambda: camera.stats.frames >= 20)
        held = camera.ring.frames()
        stats = camera.stats
        assert len(held) == 4
        assert stats.overwritten >= stats.frames - 5  # the grabber may push one more meanwhile
        assert stats.dropped == stats.overwritten  # nobody consumed any

        newest = held[-1]
        assert camera.frame_near(newest.t_capture + 3 * MS, 5 * MS) == newest
        assert camera.frame_near(newest.t_capture + 10_000 * MS, 5 * MS) is None
        assert camera.stats.near_misses == 1
    assert decode_calls == []


@pytest.mark.realtime
def test_unplug_reopens_with_backoff_without_spinning_and_recovers():
    device = FakeDevice()
    camera = UvcCamera("/dev/video0", settings(), capture_factory=device.open)
    try:
        assert wait_until(lambda: camera.stats.frames >= 5)
        before = camera.latest()

        device.plugged = False  # reads now fail at once, and opening fails
        assert wait_until(lambda: camera.state == "reconnecting")
        cpu_start, opens_start = camera.cpu_time_s(), len(device.captures)
        time.sleep(1.0)
        cpu_used = camera.cpu_time_s() - cpu_start
        attempts = len(device.captures) - opens_start
        assert cpu_used < 0.05, f"grab thread used {cpu_used:.3f} s of CPU in 1 s: spinning"
        assert 2 <= attempts <= 8  # backoff 0.05 s doubling to 0.4 s
        assert camera.stats.read_failures >= 1
        assert camera.stats.open_failures >= attempts
        assert camera.state == "reconnecting"

        device.plugged = True
        assert wait_until(lambda: camera.state == "streaming", timeout=2.0)
        assert camera.stats.reopens == 1
        after = camera.next_frame(timeout=2.0)
        assert wait_until(lambda: camera.latest().sequence > before.sequence + 2)
        after = camera.latest()
        assert after.sequence > before.sequence and after.t_host > before.t_host
        assert camera.negotiation.width == 1280  # configured again after the reopen
    finally:
        camera.close()
    assert camera.state == "closed"
    assert not any(c.opened for c in device.captures)


def test_a_backend_that_ignores_convert_rgb_is_reported_and_reencoded(caplog):
    device = FakeDevice(sizes=[(640, 480)], ignores_convert_rgb=True)
    caplog.set_level(logging.WARNING, logger="treetraits.camera")
    with UvcCamera("/dev/video0", settings(), capture_factory=device.open) as camera:
        assert wait_until(lambda: camera.stats.frames >= 3)
        frame = camera.latest()
        assert camera.jpeg_path == "reencoded"
        assert camera.stats.reencoded == camera.stats.frames
        assert camera.decode(frame).shape == (480, 640, 3)
    assert caplog.text.count("re-encoding") == 1


def test_an_implausible_buffer_time_falls_back_to_the_receive_time():
    device = FakeDevice(latency_ms=900.0)  # older than max_latency_ms: not trusted
    with UvcCamera("/dev/video0", settings(), capture_factory=device.open) as camera:
        frame = camera.next_frame(timeout=2.0)
        assert frame.t_capture == frame.t_host
        assert camera.stats.timestamp_fallbacks >= 1


def test_an_absent_camera_is_a_clear_error_or_awaited():
    device = FakeDevice()
    device.plugged = False
    with pytest.raises(SourceError, match=r"cannot open /dev/video9.*does not exist"):
        open_camera_source("/dev/video9", settings(), capture_factory=device.open)

    camera = open_camera_source(
        "/dev/video9", settings(wait_for_device=True), capture_factory=device.open
    )
    try:
        assert camera.is_live and camera.state == "reconnecting"
        device.plugged = True
        assert camera.next_frame(timeout=3.0) is not None
        assert camera.stats.open_failures >= 1 and camera.stats.reopens == 0
    finally:
        camera.close()

    with pytest.raises(ConfigError, match="usb:VID:PID"):
        open_camera_source("usb:nope", settings(), capture_factory=device.open)


def test_capture_time_from_the_kernel_buffer_stamp():
    clocks = ClockSample(monotonic_ns=5_000_000_000_000, realtime_ns=1_780_000_000_000_000_000)
    offset = clocks.realtime_ns - clocks.monotonic_ns
    stamp_ms = (clocks.monotonic_ns - 40 * MS) / MS  # 40 ms before the dequeue, monotonic
    assert capture_time_ns(stamp_ms, clocks) == clocks.monotonic_ns - 40 * MS + offset
    # the timeval's microseconds survive the trip through a float of milliseconds:
    # tv_sec 4999, tv_usec 960123 -> 1000 * 4999 + 960123 / 1000
    assert capture_time_ns(1000 * 4999 + 960123 / 1000, clocks) == 4_999_960_123_000 + offset
    # a driver stamping on the realtime clock
    assert capture_time_ns((clocks.realtime_ns - 30 * MS) / MS, clocks) == (
        clocks.realtime_ns - 30 * MS
    )
    assert capture_time_ns(0.0, clocks) is None  # before the first frame
    assert capture_time_ns(float("nan"), clocks) is None
    assert capture_time_ns((clocks.monotonic_ns - 500 * MS) / MS, clocks) is None  # too old
    assert capture_time_ns((clocks.monotonic_ns + 5 * MS) / MS, clocks) is None  # future


@pytest.mark.realtime
def test_camera_info_and_grab_on_a_live_camera(monkeypatch, tmp_path, capsys):
    """`treetraits camera info|grab` end to end, cv2.VideoCapture replaced by the fake."""
    import json

    from treetraits.cli import main

    device = FakeDevice(sizes=[(640, 480)], controls={cv2.CAP_PROP_AUTO_EXPOSURE: 3})
    monkeypatch.setattr(cv2, "VideoCapture", device.open)

    assert main(["camera", "info", "/dev/video0", "--seconds", "0.5", "--json"]) == 0
    facts = json.loads(capsys.readouterr().out)
    assert (facts["kind"], facts["device"], facts["state"]) == ("live", "/dev/video0", "streaming")
    assert "cannot enumerate /dev/video0" in facts["v4l2"]  # no real node to ask on CI
    assert facts["negotiation"]["mismatches"] == ["size 640x480 instead of 1280x720"]
    assert {c["name"]: c["status"] for c in facts["locked"]}["auto_exposure"] == "set"
    measured = facts["measured"]
    assert 10 <= measured["frames"] <= 17
    assert measured["fps_median"] == pytest.approx(30.0, rel=0.15)
    assert 40 <= measured["latency_ms_median"] <= 100
    assert (measured["width"], measured["height"]) == (640, 480)
    assert measured["grab_cpu_percent"] < 50
    assert facts["counters"]["decoded"] == 1  # the first frame, for its size

    assert main(["camera", "info", "/dev/video0", "--seconds", "0.2"]) == 0
    text = capsys.readouterr().out
    assert "size 640x480 instead of 1280x720" in text and "auto_exposure" in text

    out = tmp_path / "grab"
    assert main(["camera", "grab", "/dev/video0", "--out", str(out), "-n", "4"]) == 0
    assert "wrote 4 frames" in capsys.readouterr().out
    back = list(open_camera_source(out))
    assert len(back) == 4
    served = set(device.captures[-1].served)
    assert all(f.jpeg in served for f in back)  # the camera's bytes, as sent
    assert all(b.t_capture > a.t_capture for a, b in itertools.pairwise(back))
