"""Camera frames from files: a folder of JPEGs with a timestamp list, a video file, or a
recording (format v1, topic `/camera/jpeg`).

Every replay source reads its input once, front to back, and offers what the live camera
offers: iteration, `frame_near` (which reads forward just far enough and keeps the newest
few frames in a ring, as the live grabber does), `decode` and counters. Nothing is decoded
while reading: a corrupt JPEG is counted when someone decodes it.

- Folder: `*.jpg` files plus `timestamps.csv` with rows `file,t_capture_ns[,t_host_ns]`
  (ns since the Unix epoch; a header row is optional; t_host defaults to t_capture). The
  JPEG bytes are kept verbatim. `FolderWriter` writes this layout.
- Video (`.mp4 .avi .mkv .mov`): an MJPG video's packets are JPEG images and are kept
  verbatim; any other codec has no JPEG bytes, so each frame is decoded and re-encoded to
  JPEG once, on read (`reencoded` counts them). Times are the file's frame times plus
  `start_ns`.
- Recording: `log_time` is `t_host`, `publish_time` is `t_capture`, the message is the JPEG.
"""

from __future__ import annotations

import abc
import csv
import io
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import cv2
import numpy as np

from treetraits.drivers.camera.frames import (
    DEFAULT_RING_SIZE,
    CameraStats,
    FrameRing,
    compressed_bytes,
    decode_frame,
    encode_jpeg,
    looks_like_jpeg,
)
from treetraits.drivers.camera.v4l2 import fourcc_text
from treetraits.drivers.records import Frame
from treetraits.errors import SourceError

TIMESTAMPS_CSV = "timestamps.csv"
CSV_HEADER = ("file", "t_capture_ns", "t_host_ns")
JPEG_SUFFIXES = (".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov")
_MIN_REPLAY_RING = 3  # frame_near needs the frames either side of t plus the one past the window


@dataclass(frozen=True, slots=True)
class TimestampRow:
    """One line of timestamps.csv."""

    file: str
    t_capture: int
    t_host: int


def _is_int(text: str) -> bool:
    return text.strip().lstrip("-").isdigit()


def parse_timestamps(lines: Iterable[str]) -> tuple[list[TimestampRow], int]:
    """The rows of a timestamps.csv and the number of bad rows.

    A row is `file,t_capture_ns[,t_host_ns]`; blank lines and `#` comments are skipped; a
    first row whose second field is not a number is the header. A row is bad when it has
    the wrong number of fields, a time that is not a non-negative integer, or a file name
    that leaves the folder (absolute, or with `..`).
    """
    rows: list[TimestampRow] = []
    bad = 0
    first = True
    for fields in csv.reader(lines):
        if not fields or not "".join(fields).strip() or fields[0].lstrip().startswith("#"):
            continue
        if first and len(fields) >= 2 and not _is_int(fields[1]):
            first = False
            continue  # the header
        first = False
        fields = [f.strip() for f in fields]
        name = fields[0]
        if (
            len(fields) not in (2, 3)
            or not all(_is_int(f) and int(f) >= 0 for f in fields[1:])
            or not name
            or Path(name).is_absolute()
            or ".." in Path(name).parts
        ):
            bad += 1
            continue
        t_capture = int(fields[1])
        rows.append(
            TimestampRow(name, t_capture, int(fields[2]) if len(fields) == 3 else t_capture)
        )
    return rows, bad


class _ReplaySource(abc.ABC):
    """Iteration, `frame_near`, `decode` and counters over a subclass's `_frames()`."""

    is_live = False
    kind = "replay"

    def __init__(self, uri: str, ring_size: int = DEFAULT_RING_SIZE):
        self.uri = uri
        self.stats = CameraStats()
        self.ring = FrameRing(max(ring_size, _MIN_REPLAY_RING), self.stats)
        self._stream: Iterator[Frame] | None = None
        self._exhausted = False

    @abc.abstractmethod
    def _frames(self) -> Iterator[Frame]:
        """The source's frames, in order (each replay kind reads its own format)."""

    def _counted(self) -> Iterator[Frame]:
        for frame in self._frames():
            self.stats.count(frame)
            yield frame

    def _next(self) -> Frame | None:
        if self._stream is None:
            self._stream = self._counted()
        frame = next(self._stream, None)
        self._exhausted = frame is None
        return frame

    def __iter__(self) -> Iterator[Frame]:
        """Every frame, in time order. A source is read once: iterate it, or call
        `frame_near` with rising times, not both."""
        while (frame := self._next()) is not None:
            yield frame

    def frame_near(self, t_ns: int, max_skew_ns: int) -> Frame | None:
        """The frame whose capture time is nearest `t_ns`, within `max_skew_ns`.

        Reads forward until a frame lies beyond `t_ns + max_skew_ns` (or the input ends),
        keeping the newest few frames, so calls must come with rising times (as scans do).
        """
        while not self._exhausted:
            newest = self.ring.newest_capture_time()
            if newest is not None and newest > t_ns + max_skew_ns:
                break
            frame = self._next()
            if frame is not None:
                self.ring.push(frame)
        return self.ring.frame_near(t_ns, max_skew_ns)

    def decode(self, frame: Frame) -> np.ndarray:
        """The frame as a BGR image (counted); ParseError for a corrupt JPEG (counted)."""
        return decode_frame(frame, self.stats)

    def close(self) -> None:
        self._exhausted = True
        if self._stream is not None:
            self._stream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class ImageFolderSource(_ReplaySource):
    """A folder of JPEG files listed, with their times, in `timestamps.csv`.

    Rows are replayed in capture-time order. A listed file that is missing is counted
    (`missing`) and skipped; files not listed are counted (`unlisted`) and ignored; bytes
    are never checked while reading (a corrupt file shows up in `corrupt` when decoded).
    """

    kind = "folder"

    def __init__(self, path: str | os.PathLike[str], ring_size: int = DEFAULT_RING_SIZE):
        super().__init__(os.fspath(path), ring_size)
        self.path = Path(path)
        listing = self.path / TIMESTAMPS_CSV
        try:
            text = listing.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise SourceError(
                f"{self.path}: no {TIMESTAMPS_CSV}; a folder of images needs one row per "
                f"image: file,t_capture_ns[,t_host_ns] (ns since the Unix epoch), as "
                f"`treetraits camera grab` writes it"
            ) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise SourceError(f"{listing}: cannot read ({exc})") from exc
        rows, self.stats.bad_rows = parse_timestamps(io.StringIO(text))
        self.rows = sorted(rows, key=lambda row: row.t_capture)  # stable: ties keep file order
        listed = {row.file for row in rows}
        self.stats.unlisted = sum(
            1
            for entry in self.path.iterdir()
            if entry.suffix.lower() in JPEG_SUFFIXES and entry.name not in listed
        )

    def _frames(self) -> Iterator[Frame]:
        for sequence, row in enumerate(self.rows):
            try:
                data = (self.path / row.file).read_bytes()
            except OSError:
                self.stats.missing += 1
                continue
            yield Frame(data, row.t_host, row.t_capture, sequence)


class FolderWriter:
    """Writes frames as `frame_NNNNNN.jpg` (the JPEG bytes as they are) plus
    `timestamps.csv`, the layout `ImageFolderSource` reads. Refuses a folder that already
    has a timestamps.csv. Each image is written before its row, so a crash never lists a
    file that is not there."""

    def __init__(self, out: str | os.PathLike[str], prefix: str = "frame_"):
        self.out = Path(out)
        self.prefix = prefix
        self.count = 0
        self.out.mkdir(parents=True, exist_ok=True)
        try:
            self._file: IO[str] = open(  # noqa: SIM115 - closed by close()
                self.out / TIMESTAMPS_CSV, "x", newline="", encoding="utf-8"
            )
        except FileExistsError:
            raise SourceError(
                f"{self.out} already holds a {TIMESTAMPS_CSV}: choose an empty folder"
            ) from None
        self._csv = csv.writer(self._file)
        self._csv.writerow(CSV_HEADER)

    def write(self, frame: Frame) -> Path:
        path = self.out / f"{self.prefix}{self.count:06d}.jpg"
        path.write_bytes(frame.jpeg)
        self._csv.writerow([path.name, frame.t_capture, frame.t_host])
        self.count += 1
        return path

    def close(self) -> None:
        if not self._file.closed:
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()

    def __enter__(self) -> FolderWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class VideoFileSource(_ReplaySource):
    """A video file read with OpenCV's FFmpeg backend.

    MJPG video: the packets are read undecoded (CAP_PROP_FORMAT -1) and are the JPEG
    bytes, kept verbatim. Other codecs: frames are decoded and re-encoded to JPEG once, on
    read (`reencoded`), since the file holds no JPEG of them. `t_capture` = `start_ns` +
    the frame's presentation time; `t_host` = `t_capture` (a file has no receive time).
    """

    kind = "video"

    def __init__(
        self,
        path: str | os.PathLike[str],
        start_ns: int = 0,
        jpeg_quality: int = 95,
        ring_size: int = DEFAULT_RING_SIZE,
    ):
        super().__init__(os.fspath(path), ring_size)
        self.path = Path(path)
        self.start_ns = int(start_ns)
        self.jpeg_quality = jpeg_quality
        if not self.path.is_file():
            raise SourceError(f"{self.path}: no such video file")
        self.passthrough = self._probe_passthrough()
        self._capture = self._open(raw=self.passthrough)
        if not self._capture.isOpened():
            raise SourceError(
                f"{self.path}: OpenCV cannot read this video (FFmpeg backend); convert it, "
                f"e.g. ffmpeg -i {self.path.name} -c:v mjpeg -q:v 2 out.avi"
            )
        self.fps = float(self._capture.get(cv2.CAP_PROP_FPS))
        self.codec = fourcc_text(int(self._capture.get(cv2.CAP_PROP_FOURCC)))
        self.width = int(self._capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(self._capture.get(cv2.CAP_PROP_FRAME_HEIGHT))

    def _open(self, raw: bool) -> cv2.VideoCapture:
        if raw:
            return cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_FORMAT, -1])
        return cv2.VideoCapture(str(self.path))

    def _probe_passthrough(self) -> bool:
        """True when the undecoded packets of the file are JPEG images (an MJPG video)."""
        try:
            probe = self._open(raw=True)
        except cv2.error:
            return False
        try:
            ok, packet = probe.read() if probe.isOpened() else (False, None)
        finally:
            probe.release()
        if not ok or packet is None:
            return False
        data = compressed_bytes(packet)
        return data is not None and looks_like_jpeg(data)

    def _frames(self) -> Iterator[Frame]:
        capture = self._capture
        last: int | None = None
        step = round(1e9 / self.fps) if self.fps > 0 else 1
        sequence = 0
        try:
            while True:
                ok, data = capture.read()
                if not ok or data is None:
                    return
                offset = round(float(capture.get(cv2.CAP_PROP_POS_MSEC)) * 1000) * 1000
                t = self.start_ns + offset
                if last is not None and t <= last:  # no usable frame time: use the rate
                    self.stats.bad_times += 1
                    t = last + step
                last = t
                jpeg = compressed_bytes(data) if self.passthrough else None
                if jpeg is None:
                    jpeg = encode_jpeg(data, self.jpeg_quality)
                    self.stats.reencoded += 1
                yield Frame(jpeg, t, t, sequence)
                sequence += 1
        finally:
            capture.release()

    def close(self) -> None:
        super().close()
        self._capture.release()


class RecordingSource(_ReplaySource):
    """The `/camera/jpeg` channel of a recording (format v1); other topics are skipped.
    A truncated file yields its readable prefix and sets `truncated`."""

    kind = "recording"

    def __init__(self, path: str | os.PathLike[str], ring_size: int = DEFAULT_RING_SIZE):
        from treetraits.drivers import recording

        super().__init__(os.fspath(path), ring_size)
        self.path = Path(path)
        self._reader = recording.read_recording(path, topics=[recording.CAMERA_JPEG])

    def _frames(self) -> Iterator[Frame]:
        for message in self._reader:
            yield Frame(
                bytes(message.data), message.log_time, message.publish_time, message.sequence
            )
        # A chunk skipped as damaged is reported as a cut is: data was lost.
        self.stats.truncated = self._reader.truncated or self._reader.lost_data

    @property
    def recording(self):
        """The recording's reader: what of it could not be read (treetraits/damage.py)."""
        return self._reader

    def close(self) -> None:
        super().close()
        self._reader.close()
