"""The camera's settings: what to ask the device for, what to lock, how to buffer and retry.

One frozen object, validated once; the live source reads all of it, replay sources only
`ring_size` and `jpeg_quality`.
"""

from __future__ import annotations

from dataclasses import dataclass

from treetraits.drivers.camera.frames import DEFAULT_RING_SIZE
from treetraits.errors import ConfigError


@dataclass(frozen=True, slots=True)
class CameraSettings:
    """Defaults: the Survey3N's 720p MJPG stream at 30 fps, exposure and white balance
    locked at whatever the camera had settled on when it was opened."""

    width: int = 1280
    height: int = 720
    fps: float = 30.0
    fourcc: str = "MJPG"
    lock: bool = True  # manual exposure and white balance (values below, or the current ones)
    exposure: int | None = None  # V4L2 exposure_time_absolute, 100 us units for UVC
    gain: int | None = None  # V4L2 gain, device units
    wb_temperature: int | None = None  # kelvin
    v4l2_buffers: int | None = None  # kernel buffers (1..10); None keeps OpenCV's 4
    ring_size: int = DEFAULT_RING_SIZE  # newest frames kept for the pipeline
    max_latency_ms: float = 200.0  # exposure start to dequeue, else the stamp is not trusted
    strict_mode: bool = False  # refuse a device that gives another format, size or rate
    jpeg_quality: int = 95  # only for frames that arrive without JPEG bytes
    backoff_initial_s: float = 0.5  # first wait before reopening a lost device
    backoff_max_s: float = 8.0  # the wait doubles up to this
    wait_for_device: bool = False  # start even when the camera is absent, and keep trying

    def __post_init__(self) -> None:
        checks = [
            (self.width > 0 and self.height > 0, "width and height must be positive"),
            (self.fps > 0, "fps must be positive"),
            (len(self.fourcc) == 4, f"fourcc must have 4 characters, got {self.fourcc!r}"),
            (
                self.v4l2_buffers is None or 1 <= self.v4l2_buffers <= 10,
                f"v4l2_buffers must be 1..10 (OpenCV's limit), got {self.v4l2_buffers}",
            ),
            (self.ring_size >= 1, f"ring_size must be at least 1, got {self.ring_size}"),
            (self.max_latency_ms > 0, "max_latency_ms must be positive"),
            (1 <= self.jpeg_quality <= 100, "jpeg_quality must be 1..100"),
            (
                0 < self.backoff_initial_s <= self.backoff_max_s,
                "backoff must satisfy 0 < backoff_initial_s <= backoff_max_s",
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"camera settings: {message}")
