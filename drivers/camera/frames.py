"""Camera frames between a source and the pipeline: counters, the ring of newest frames, the
nearest-in-time lookup and the conversion of V4L2 buffer timestamps to Unix time.

Nothing here decodes an image unless asked: a `Frame` carries the JPEG bytes as the camera
sent them, and the pipeline decodes only the frame it picks for a scan (`decode_frame`),
so grabbing 30 fps of 720p costs no JPEG decoding at all.
"""

from __future__ import annotations

import itertools
import statistics
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from treetraits.drivers.records import Frame
from treetraits.errors import ParseError

JPEG_SOI = b"\xff\xd8"  # every JPEG starts with the start-of-image marker
DEFAULT_RING_SIZE = 4
DEFAULT_MAX_LATENCY_NS = 200_000_000  # exposure start to dequeue; more means a bad stamp


@dataclass
class CameraStats:
    """What a camera source read, made and skipped. Every frame is accounted for."""

    frames: int = 0  # frames accepted (into the ring or yielded)
    bytes: int = 0  # JPEG bytes of the accepted frames
    decoded: int = 0  # frames decoded on request (`decode`)
    corrupt: int = 0  # of those, not decodable: counted when decoded, never when read
    reencoded: int = 0  # frames with no JPEG bytes of their own, encoded here (stated fallback)
    malformed: int = 0  # live buffers that were not a JPEG (empty, no SOI marker): dropped
    overwritten: int = 0  # frames pushed out of the ring by newer ones
    dropped: int = 0  # of those, never handed to a consumer
    missed: int = 0  # live: frames the camera should have sent, from gaps in capture time
    near_misses: int = 0  # frame_near() calls with no frame within the allowed skew
    timestamp_fallbacks: int = 0  # live: buffer time missing or implausible, t_capture = t_host
    read_failures: int = 0  # live: grab()/retrieve() failed (unplugged, stalled)
    open_failures: int = 0  # live: attempts to open the device that failed
    reopens: int = 0  # live: successful opens after a failure
    missing: int = 0  # folder: files listed in timestamps.csv that are not there
    unlisted: int = 0  # folder: JPEG files present but not listed in timestamps.csv
    bad_rows: int = 0  # folder: rows of timestamps.csv that are not `file,t_capture_ns[,t_host]`
    bad_times: int = 0  # video: frame times that did not increase (replaced from the frame rate)
    truncated: bool = False  # recording: the file ended inside a record

    def count(self, frame: Frame) -> None:
        self.frames += 1
        self.bytes += len(frame.jpeg)

    def as_dict(self) -> dict[str, int | bool]:
        return asdict(self)


def decode_frame(frame: Frame, stats: CameraStats) -> np.ndarray:
    """Decode one frame (BGR uint8), counting it; a corrupt JPEG is counted and re-raised
    as ParseError, so the caller decides whether to skip it."""
    import cv2

    stats.decoded += 1
    try:
        return frame.decode()
    except ParseError:
        stats.corrupt += 1
        raise
    except cv2.error as exc:  # OpenCV raises rather than returning None for an empty buffer
        stats.corrupt += 1
        raise ParseError(
            f"frame {frame.sequence}: not a decodable JPEG ({len(frame.jpeg)} bytes; {exc.err})"
        ) from exc


def nearest_index(times: Sequence[int], t_ns: int, max_skew_ns: int) -> int | None:
    """Index of the time nearest `t_ns` (the earlier one on a tie), or None when the
    nearest is more than `max_skew_ns` away or there is none."""
    best: int | None = None
    best_skew = max_skew_ns
    for i, t in enumerate(times):
        skew = abs(t - t_ns)
        if skew < best_skew or (skew == best_skew and best is None):
            best, best_skew = i, skew
    return best


def interval_summary(times_ns: Sequence[int]) -> dict[str, float | None]:
    """Frame rate facts from capture times: mean rate over the span, the rate from the
    median interval (robust to a few drops) and the longest gap."""
    if len(times_ns) < 2:
        return {"fps_mean": None, "fps_median": None, "max_interval_ms": None}
    ordered = sorted(times_ns)
    intervals = [b - a for a, b in itertools.pairwise(ordered)]
    span = ordered[-1] - ordered[0]
    median = statistics.median(intervals)
    return {
        "fps_mean": (len(ordered) - 1) * 1e9 / span if span > 0 else None,
        "fps_median": 1e9 / median if median > 0 else None,
        "max_interval_ms": max(intervals) / 1e6,
    }


# --- clocks ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ClockSample:
    """The monotonic and the realtime clock read at (nearly) the same instant, in ns."""

    monotonic_ns: int
    realtime_ns: int


def sample_clocks() -> ClockSample:
    """Read CLOCK_MONOTONIC around CLOCK_REALTIME and pair the realtime reading with the
    midpoint, so the offset between the clocks is good to the time of one clock read."""
    before = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
    realtime = time.time_ns()
    after = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
    return ClockSample((before + after) // 2, realtime)


def capture_time_ns(
    buffer_ms: float, clocks: ClockSample, max_latency_ns: int = DEFAULT_MAX_LATENCY_NS
) -> int | None:
    """The capture time, ns since the Unix epoch, from a V4L2 buffer timestamp.

    `buffer_ms` is what OpenCV's V4L2 backend returns for CAP_PROP_POS_MSEC: the dequeued
    buffer's `timestamp` (a timeval: seconds and microseconds) in milliseconds, 0 before the
    first frame. uvcvideo stamps buffers on CLOCK_MONOTONIC at the start of exposure, so
    the stamp is moved to the realtime clock with the offset `clocks` measured right after
    the grab. A stamp already on the realtime clock (a driver set up that way) is used as
    it is. None when the stamp is missing or neither reading gives a latency in
    [0, max_latency_ns]: the caller then falls back to the receive time.
    """
    if not buffer_ms > 0:  # also NaN
        return None
    stamp = round(buffer_ms * 1000) * 1000  # the timeval had microseconds
    if 0 <= clocks.monotonic_ns - stamp <= max_latency_ns:
        return stamp + clocks.realtime_ns - clocks.monotonic_ns
    if 0 <= clocks.realtime_ns - stamp <= max_latency_ns:
        return stamp
    return None


# --- JPEG buffers ---------------------------------------------------------------------


def looks_like_jpeg(data: bytes) -> bool:
    """A cheap check without decoding: the buffer starts with the SOI marker."""
    return len(data) > 4 and data[:2] == JPEG_SOI


def compressed_bytes(buffer: np.ndarray) -> bytes | None:
    """The bytes of a compressed buffer as OpenCV returns it with CAP_PROP_CONVERT_RGB off
    (a 1xN or N uint8 array whose size changes per frame); None for a decoded image."""
    if buffer.dtype != np.uint8:
        return None
    if buffer.ndim == 1 or (buffer.ndim == 2 and buffer.shape[0] == 1):
        return buffer.tobytes()
    return None


def encode_jpeg(image: np.ndarray, quality: int) -> bytes:
    """Encode a BGR (or grey) image as a baseline JPEG."""
    import cv2

    ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ParseError(f"OpenCV could not encode a {image.shape} {image.dtype} image as JPEG")
    return encoded.tobytes()


# --- the ring -------------------------------------------------------------------------


class _Slot:
    __slots__ = ("frame", "used")

    def __init__(self, frame: Frame):
        self.frame = frame
        self.used = False


class FrameRing:
    """The newest `capacity` frames, oldest first, shared between one producer (the grab
    thread, or a replay reader) and any consumers.

    Pushing into a full ring evicts the oldest frame (`overwritten`; `dropped` when no
    consumer ever got it). Lookups hand out the `Frame` as stored: nothing is decoded.
    """

    def __init__(self, capacity: int = DEFAULT_RING_SIZE, stats: CameraStats | None = None):
        if capacity < 1:
            raise ValueError(f"ring capacity must be at least 1, got {capacity}")
        self.capacity = capacity
        self.stats = stats if stats is not None else CameraStats()
        self._slots: deque[_Slot] = deque()
        self._changed = threading.Condition()
        self._closed = False

    def push(self, frame: Frame) -> None:
        with self._changed:
            if len(self._slots) == self.capacity:
                evicted = self._slots.popleft()
                self.stats.overwritten += 1
                self.stats.dropped += not evicted.used
            self._slots.append(_Slot(frame))
            self._changed.notify_all()

    def close(self) -> None:
        """Wake every waiter; later waits return at once."""
        with self._changed:
            self._closed = True
            self._changed.notify_all()

    def __len__(self) -> int:
        with self._changed:
            return len(self._slots)

    def frames(self) -> list[Frame]:
        """The frames held, oldest first (not marked as used)."""
        with self._changed:
            return [slot.frame for slot in self._slots]

    def newest_capture_time(self) -> int | None:
        with self._changed:
            return self._slots[-1].frame.t_capture if self._slots else None

    def frame_near(self, t_ns: int, max_skew_ns: int) -> Frame | None:
        """The frame whose capture time is nearest `t_ns`, if within `max_skew_ns`."""
        with self._changed:
            index = nearest_index([s.frame.t_capture for s in self._slots], t_ns, max_skew_ns)
            if index is None:
                self.stats.near_misses += 1
                return None
            slot = self._slots[index]
            slot.used = True
            return slot.frame

    def latest(self) -> Frame | None:
        with self._changed:
            if not self._slots:
                return None
            self._slots[-1].used = True
            return self._slots[-1].frame

    def next_after(self, sequence: int | None, timeout: float | None = None) -> Frame | None:
        """The oldest frame held with a sequence number above `sequence` (any frame when
        None), waiting up to `timeout` seconds for one; None on timeout or close."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._changed:
            while True:
                for slot in self._slots:
                    if sequence is None or slot.frame.sequence > sequence:
                        slot.used = True
                        return slot.frame
                if self._closed:
                    return None
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._changed.wait(remaining)
