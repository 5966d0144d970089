"""The Survey3N live: UVC through OpenCV's V4L2 backend, grabbed on a thread.

`UvcCamera` opens the node (see `drivers.camera.devices`), asks for MJPG 1280x720 at 30 fps
and reads back what the device really gave (`Negotiation`), locks exposure, gain and white
balance where the device allows it and reports each control (`ControlOutcome`), then grabs
on a thread into a small ring of the newest frames (`FrameRing`). Each frame keeps the
compressed bytes exactly as the camera sent them: with CAP_PROP_CONVERT_RGB off, OpenCV's
V4L2 backend hands over an MJPG buffer as a 1xN uint8 array instead of decoding it, so the
thread never decodes anything. The pipeline takes the frame nearest a scan
(`frame_near`) and decodes only that one.

Times: `t_host` is the realtime clock right after `grab()` returned; `t_capture` is the
kernel buffer timestamp (CAP_PROP_POS_MSEC, start of exposure on CLOCK_MONOTONIC for
uvcvideo) moved to the realtime clock with the monotonic-to-realtime offset sampled at the
same moment (`frames.capture_time_ns`).

When the camera goes away (unplugged, USB reset), grabbing fails: the thread releases the
device and reopens it with exponential backoff (waiting on an event, never spinning),
resolving the device name again so a by-id or usb:VID:PID name finds the new node.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from treetraits.drivers.camera.devices import DEV, SYSFS, describe_node, resolve_device
from treetraits.drivers.camera.frames import (
    CameraStats,
    FrameRing,
    capture_time_ns,
    compressed_bytes,
    decode_frame,
    encode_jpeg,
    looks_like_jpeg,
    sample_clocks,
)
from treetraits.drivers.camera.settings import CameraSettings
from treetraits.drivers.camera.v4l2 import fourcc_code, fourcc_text
from treetraits.drivers.records import Frame
from treetraits.errors import SourceError

log = logging.getLogger("treetraits.camera")

# What makes the capture object: cv2.VideoCapture, or a stand-in in tests.
CaptureFactory = Callable[[str, int], Any]

_JPEG_FOURCCS = ("MJPG", "JPEG")
_V4L2_EXPOSURE_MANUAL = 1  # V4L2_EXPOSURE_MANUAL in the exposure_auto menu (3 = aperture priority)
_UNSUPPORTED = -1.0  # what the V4L2 backend's get() returns for a control the device lacks


@dataclass(frozen=True, slots=True)
class Negotiation:
    """The mode asked for and the mode the device gave, read back after setting it."""

    device: str
    requested_fourcc: str
    requested_width: int
    requested_height: int
    requested_fps: float
    fourcc: str
    width: int
    height: int
    fps: float
    raw_jpeg: bool  # CONVERT_RGB off took: compressed buffers are handed over untouched
    buffers: int | None  # kernel buffers, as read back

    @property
    def mismatches(self) -> list[str]:
        """What differs from the request, one phrase each; empty when all was granted."""
        found = []
        if self.fourcc != self.requested_fourcc:
            found.append(f"format {self.fourcc or '?'} instead of {self.requested_fourcc}")
        if (self.width, self.height) != (self.requested_width, self.requested_height):
            found.append(
                f"size {self.width}x{self.height} instead of "
                f"{self.requested_width}x{self.requested_height}"
            )
        if abs(self.fps - self.requested_fps) > 0.01 * self.requested_fps:
            found.append(f"{self.fps:g} fps instead of {self.requested_fps:g}")
        if not self.raw_jpeg:
            found.append("no raw JPEG pass-through: frames are decoded and re-encoded")
        return found

    def as_dict(self) -> dict:
        return {**asdict(self), "mismatches": self.mismatches}


@dataclass(frozen=True, slots=True)
class ControlOutcome:
    """What happened to one camera control when the settings were applied.

    `status`: `set` (accepted and read back as asked), `differs` (accepted, read back
    otherwise: clamped or ignored), `refused` (the device has it but set() failed),
    `unsupported` (the device lacks it), `unverified` (accepted, cannot be read back),
    `kept` (nothing asked: the current value stays).
    """

    name: str
    requested: float | None
    before: float | None
    after: float | None
    status: str

    def as_dict(self) -> dict:
        return asdict(self)


# (name, OpenCV property). The V4L2 backend maps them to exposure_auto,
# exposure_absolute, gain, white_balance_automatic and white_balance_temperature.
_CONTROLS = (
    ("auto_exposure", cv2.CAP_PROP_AUTO_EXPOSURE),
    ("exposure", cv2.CAP_PROP_EXPOSURE),
    ("gain", cv2.CAP_PROP_GAIN),
    ("auto_white_balance", cv2.CAP_PROP_AUTO_WB),
    ("white_balance_temperature", cv2.CAP_PROP_WB_TEMPERATURE),
)


def _read_property(capture: Any, prop: int) -> float | None:
    value = float(capture.get(prop))
    return None if value == _UNSUPPORTED else value


def apply_control(capture: Any, name: str, prop: int, value: float | None) -> ControlOutcome:
    """Set one control (when `value` is not None), read it back and say what happened."""
    before = _read_property(capture, prop)
    if value is None:
        status = "kept" if before is not None else "unsupported"
        return ControlOutcome(name, None, before, before, status)
    accepted = bool(capture.set(prop, value))
    after = _read_property(capture, prop)
    if not accepted:
        status = "unsupported" if before is None else "refused"
    elif after is None:
        status = "unverified"
    else:
        status = "set" if after == value else "differs"
    return ControlOutcome(name, value, before, after, status)


def lock_controls(capture: Any, settings: CameraSettings) -> list[ControlOutcome]:
    """Manual exposure and white balance (and the given values), each control reported.

    With `lock` off only the explicitly given values are set. Auto exposure off freezes
    exposure and gain at what the camera last chose unless values are given; UVC has no
    separate auto gain. OpenCV's normalised property ranges are switched off first
    (CAP_PROP_MODE 0) so values are the device's own units.
    """
    capture.set(cv2.CAP_PROP_MODE, 0)
    wanted: dict[str, float | None] = {
        "auto_exposure": _V4L2_EXPOSURE_MANUAL if settings.lock else None,
        "exposure": settings.exposure,
        "gain": settings.gain,
        "auto_white_balance": 0 if settings.lock else None,
        "white_balance_temperature": settings.wb_temperature,
    }
    return [apply_control(capture, name, prop, wanted[name]) for name, prop in _CONTROLS]


def negotiate(capture: Any, device: str, settings: CameraSettings) -> Negotiation:
    """Ask for the format, size and rate, in the order the V4L2 backend needs (fourcc,
    then width and height, applied together, then fps), and read back what was granted.

    For a JPEG format CONVERT_RGB is switched off so buffers arrive compressed. For any
    other format OpenCV is left to convert to BGR, which is then re-encoded (counted).
    """
    capture.set(cv2.CAP_PROP_FOURCC, fourcc_code(settings.fourcc))
    capture.set(cv2.CAP_PROP_FRAME_WIDTH, settings.width)
    capture.set(cv2.CAP_PROP_FRAME_HEIGHT, settings.height)
    capture.set(cv2.CAP_PROP_FPS, settings.fps)
    if settings.v4l2_buffers is not None:
        capture.set(cv2.CAP_PROP_BUFFERSIZE, settings.v4l2_buffers)
    fourcc = fourcc_text(int(capture.get(cv2.CAP_PROP_FOURCC)))
    raw = False
    if fourcc in _JPEG_FOURCCS:
        raw = bool(capture.set(cv2.CAP_PROP_CONVERT_RGB, 0))
        raw = raw and float(capture.get(cv2.CAP_PROP_CONVERT_RGB)) == 0
    else:
        capture.set(cv2.CAP_PROP_CONVERT_RGB, 1)
    buffers = capture.get(cv2.CAP_PROP_BUFFERSIZE)
    return Negotiation(
        device=device,
        requested_fourcc=settings.fourcc,
        requested_width=settings.width,
        requested_height=settings.height,
        requested_fps=settings.fps,
        fourcc=fourcc,
        width=int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)),
        height=int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)),
        fps=float(capture.get(cv2.CAP_PROP_FPS)),
        raw_jpeg=raw,
        buffers=int(buffers) if buffers and buffers > 0 else None,
    )


class UvcCamera:
    """A live Survey3N (or any UVC camera) grabbed on a thread into a ring of frames.

    `uri` is a device spec (`auto`, `usb:VID:PID`, `/dev/videoN`, `/dev/v4l/by-id/...`).
    The constructor opens and configures the device and raises SourceError when it cannot
    (unless `settings.wait_for_device`); from then on failures are counted and the device
    reopened, never raised. Consumers call `frame_near`, `latest` or `next_frame`, or
    iterate; none of them decodes. `decode(frame)` decodes one frame and counts it.
    """

    is_live = True

    def __init__(
        self,
        uri: str = "auto",
        settings: CameraSettings | None = None,
        *,
        capture_factory: CaptureFactory | None = None,
        sysfs: Path = SYSFS,
        dev: Path = DEV,
    ):
        self.uri = uri
        self.settings = settings or CameraSettings()
        self.stats = CameraStats()
        self.ring = FrameRing(self.settings.ring_size, self.stats)
        self.negotiation: Negotiation | None = None
        self.controls: list[ControlOutcome] = []
        self.device: str | None = None
        self.last_error: str | None = None
        self.jpeg_path = "raw"  # or "reencoded" when the device/backend gives no JPEG bytes
        self._factory: CaptureFactory = capture_factory or cv2.VideoCapture
        self._sysfs, self._dev = sysfs, dev
        self._capture: Any = None
        self._sequence = 0
        self._cursor: int | None = None  # last sequence handed out by next_frame
        self._last_capture: int | None = None
        self._stop = threading.Event()
        self._thread_cpu_s = 0.0
        self._opened_once = False
        try:
            self._connect()
        except SourceError as exc:  # a malformed spec (ConfigError) is never waited for
            if not self.settings.wait_for_device:
                raise
            self.stats.open_failures += 1
            self.last_error = str(exc)
            log.warning("camera %s: %s; retrying in the background", uri, exc)
        self._thread = threading.Thread(target=self._run, name="camera-grab", daemon=True)
        self._thread.start()

    # --- consumers -----------------------------------------------------------------

    @property
    def state(self) -> str:
        if self._stop.is_set():
            return "closed"
        return "streaming" if self._capture is not None else "reconnecting"

    def frame_near(self, t_ns: int, max_skew_ns: int) -> Frame | None:
        """The held frame whose capture time is nearest `t_ns`, within `max_skew_ns`."""
        return self.ring.frame_near(t_ns, max_skew_ns)

    def latest(self) -> Frame | None:
        return self.ring.latest()

    def next_frame(self, timeout: float | None = None) -> Frame | None:
        """The next frame after the last one this method returned (frames overwritten
        in between are skipped and counted as dropped); None on timeout or close."""
        frame = self.ring.next_after(self._cursor, timeout)
        if frame is not None:
            self._cursor = frame.sequence
        return frame

    def __iter__(self) -> Iterator[Frame]:
        while not self._stop.is_set():
            frame = self.next_frame(timeout=0.5)
            if frame is not None:
                yield frame

    def decode(self, frame: Frame) -> np.ndarray:
        """The frame as a BGR image (counted); ParseError for a corrupt JPEG (counted)."""
        return decode_frame(frame, self.stats)

    def cpu_time_s(self) -> float:
        """CPU time the grab thread has used so far (Linux; 0.0 where not available)."""
        ident = self._thread.ident
        if ident is not None and self._thread.is_alive():
            with contextlib.suppress(AttributeError, OSError):
                self._thread_cpu_s = time.clock_gettime(time.pthread_getcpuclockid(ident))
        return self._thread_cpu_s

    def close(self) -> None:
        """Stop the thread and release the device. Idempotent. A grab blocked inside
        OpenCV (a stalled device: up to its 10 s select timeout) is left to finish on
        its own; the thread then releases the device itself."""
        self._stop.set()
        self.ring.close()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self.cpu_time_s()
            self._thread.join(timeout=2.0 + 2.0 / self.settings.fps)

    def __enter__(self) -> UvcCamera:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # --- the device ----------------------------------------------------------------

    def _connect(self) -> None:
        path = resolve_device(self.uri, self._sysfs, self._dev)
        capture = self._factory(path, cv2.CAP_V4L2)
        if not capture.isOpened():
            capture.release()
            raise SourceError(
                f"camera {self.uri}: OpenCV's V4L2 backend cannot open {path}: "
                f"{describe_node(path)}"
            )
        try:
            negotiation = negotiate(capture, path, self.settings)
            controls = lock_controls(capture, self.settings)
        except BaseException:
            capture.release()
            raise
        if negotiation.mismatches:
            message = (
                f"camera {path} gave {', '.join(negotiation.mismatches)} (asked for "
                f"{self.settings.fourcc} {self.settings.width}x{self.settings.height} at "
                f"{self.settings.fps:g} fps)"
            )
            if self.settings.strict_mode:
                capture.release()
                raise SourceError(
                    message + "; list its modes with `treetraits camera info`, or drop "
                    "strict mode to accept what it gives"
                )
            log.warning("%s", message)
        for outcome in controls:
            if outcome.status in ("refused", "differs", "unverified") or (
                outcome.requested is not None and outcome.status == "unsupported"
            ):
                log.warning("camera %s: control %s: %s", path, outcome.name, outcome.status)
        self.negotiation, self.controls, self.device = negotiation, controls, path
        self.jpeg_path = "raw" if negotiation.raw_jpeg else "reencoded"
        self._last_capture = None
        if self._opened_once:
            self.stats.reopens += 1
        self._opened_once = True
        self._capture = capture

    def _disconnect(self) -> None:
        capture, self._capture = self._capture, None
        if capture is not None:
            with contextlib.suppress(cv2.error):
                capture.release()

    def _run(self) -> None:
        backoff = self.settings.backoff_initial_s
        try:
            while not self._stop.is_set():
                try:
                    if self._capture is None:
                        self._connect()
                        log.warning("camera %s: streaming from %s", self.uri, self.device)
                    frame = self._grab()
                except SourceError as exc:  # not back yet: wait and try again
                    self.stats.open_failures += 1
                    self.last_error = str(exc)
                except Exception as exc:  # whatever the device layer throws, the thread lives
                    self.stats.read_failures += 1
                    self.last_error = f"{type(exc).__name__}: {exc}"
                    log.exception("camera %s: unexpected error, reopening", self.uri)
                    self._disconnect()
                else:
                    if frame is _SKIPPED:
                        continue
                    if frame is not None:
                        backoff = self.settings.backoff_initial_s
                        self.stats.count(frame)
                        self.ring.push(frame)
                        continue
                    # The device failed (unplugged, stalled): let it go, wait, reopen.
                    self.stats.read_failures += 1
                    self.last_error = f"read failed on {self.device}"
                    log.warning("camera %s: %s; reopening", self.uri, self.last_error)
                    self._disconnect()
                self._stop.wait(backoff)  # sleeps; close() wakes it at once
                backoff = min(2 * backoff, self.settings.backoff_max_s)
        finally:
            self._disconnect()

    def _grab(self) -> Frame | object | None:
        """One frame from the device: a Frame, _SKIPPED for a buffer that is not a JPEG,
        or None when the device failed."""
        capture = self._capture
        try:
            if not capture.grab():
                return None
            clocks = sample_clocks()  # the bytes are ours now: this is t_host
            stamp_ms = float(capture.get(cv2.CAP_PROP_POS_MSEC))
            ok, buffer = capture.retrieve()
        except cv2.error:
            return None
        if not ok or buffer is None:
            return None
        jpeg = compressed_bytes(buffer)
        if jpeg is None and buffer.ndim == 3:
            jpeg = self._reencode(buffer)
        if jpeg is None or not looks_like_jpeg(jpeg):
            self.stats.malformed += 1
            return _SKIPPED
        t_capture = capture_time_ns(
            stamp_ms, clocks, round(self.settings.max_latency_ms * 1_000_000)
        )
        if t_capture is None:
            self.stats.timestamp_fallbacks += 1
            t_capture = clocks.realtime_ns
        self._count_missed(t_capture)
        frame = Frame(jpeg, clocks.realtime_ns, t_capture, self._sequence)
        self._sequence += 1
        return frame

    def _reencode(self, image: np.ndarray) -> bytes:
        """The stated fallback for a device or backend that hands over decoded images
        (CONVERT_RGB ignored, or a non-JPEG format): encode once, count every frame."""
        if self.stats.reencoded == 0:
            log.warning(
                "camera %s: frames arrive decoded, not as MJPG bytes; re-encoding each as "
                "JPEG (quality %d): costs CPU, and the recording no longer holds the "
                "camera's own bytes",
                self.device,
                self.settings.jpeg_quality,
            )
        self.jpeg_path = "reencoded"
        self.stats.reencoded += 1
        return encode_jpeg(image, self.settings.jpeg_quality)

    def _count_missed(self, t_capture: int) -> None:
        """Frames the camera should have delivered between two captures, from the gap
        and the negotiated rate (USB or kernel drops, the thread stalled)."""
        fps = self.negotiation.fps if self.negotiation else 0.0
        if self._last_capture is not None and fps > 0:
            gap_frames = round((t_capture - self._last_capture) * fps / 1e9)
            if gap_frames > 1:
                self.stats.missed += gap_frames - 1
        self._last_capture = t_capture


_SKIPPED = object()
