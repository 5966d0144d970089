"""Where camera frames come from, live or replayed, behind `open_camera_source(uri)`.

Every source yields `Frame`s (the JPEG bytes, `t_host`, `t_capture`, `sequence`), offers
`frame_near(t_ns, max_skew_ns)` for the pipeline (one frame per scan, nothing decoded),
`decode(frame)` for the frame it picked, `is_live` and `stats`.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from treetraits.drivers.camera.devices import DEV, SYSFS
from treetraits.drivers.camera.frames import CameraStats
from treetraits.drivers.camera.live import CaptureFactory, UvcCamera
from treetraits.drivers.camera.replay import (
    VIDEO_SUFFIXES,
    ImageFolderSource,
    RecordingSource,
    VideoFileSource,
)
from treetraits.drivers.camera.settings import CameraSettings
from treetraits.drivers.records import Frame
from treetraits.errors import SourceError

_MCAP_MAGIC = b"\x89MCAP0\r\n"


class CameraSource(Protocol):
    """What every camera source offers."""

    uri: str
    is_live: bool
    stats: CameraStats

    def __iter__(self) -> Iterator[Frame]: ...

    def frame_near(self, t_ns: int, max_skew_ns: int) -> Frame | None: ...

    def decode(self, frame: Frame) -> np.ndarray: ...

    def close(self) -> None: ...


def is_live_uri(uri: str) -> bool:
    """A device spec rather than a file: auto, usb:..., a number, or a path under /dev."""
    return uri == "auto" or uri.startswith(("usb:", "/dev/")) or uri.isdigit()


def open_camera_source(
    uri: str | os.PathLike[str],
    settings: CameraSettings | None = None,
    *,
    video_start_ns: int = 0,
    capture_factory: CaptureFactory | None = None,
    sysfs: Path = SYSFS,
    dev: Path = DEV,
) -> CameraSource:
    """Open a camera source.

    Live (`UvcCamera`): `auto`, `usb:VID:PID`, `N`, `/dev/videoN`, `/dev/v4l/by-id/...`,
    `/dev/survey3n`, or any character device. Replay: a folder with `timestamps.csv`
    (`ImageFolderSource`), a video file `.mp4/.avi/.mkv/.mov` (`VideoFileSource`, times
    from `video_start_ns`), an MCAP recording (`RecordingSource`, told by content).
    `capture_factory` replaces `cv2.VideoCapture` for the live source (tests).
    """
    settings = settings or CameraSettings()
    text = os.fspath(uri)
    path = Path(text)
    if is_live_uri(text) or (path.exists() and stat.S_ISCHR(path.stat().st_mode)):
        return UvcCamera(text, settings, capture_factory=capture_factory, sysfs=sysfs, dev=dev)
    if path.is_dir():
        return ImageFolderSource(path, settings.ring_size)
    if path.is_file():
        with open(path, "rb") as f:
            head = f.read(len(_MCAP_MAGIC))
        if head == _MCAP_MAGIC:
            return RecordingSource(path, settings.ring_size)
        if path.suffix.lower() in VIDEO_SUFFIXES:
            return VideoFileSource(path, video_start_ns, settings.jpeg_quality, settings.ring_size)
        raise SourceError(
            f"{text}: not a camera input (first bytes {head.hex()}); expected a recording "
            f"(.mcap), a video file ({' '.join(VIDEO_SUFFIXES)}) or a folder of JPEGs with "
            f"timestamps.csv"
        )
    raise SourceError(
        f"{text}: no such file or folder; a camera source is auto, usb:VID:PID, /dev/videoN, "
        f"/dev/v4l/by-id/..., a folder of JPEGs with timestamps.csv, a video file or a "
        f"recording (.mcap)"
    )


def record_frame(writer, frame: Frame) -> None:
    """Append one frame to a recording (`drivers.recording.RecordingWriter`): the JPEG on
    `/camera/jpeg`, `log_time` = `t_host`, `publish_time` = `t_capture`."""
    from treetraits.drivers.recording import CAMERA_JPEG

    writer.write(CAMERA_JPEG, frame.jpeg, frame.t_host, frame.t_capture)
