"""The sensors' records, made by the drivers and read by every layer above
(docs/architecture.md, Data that crosses module boundaries). The pose is localisation's
(`pipeline/localization/pose.py`), the output tree the outputs' (`pipeline/trees.py`).

Bulk points are NumPy structured arrays with `POINT_DTYPE`; everything else is a frozen
dataclass.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# One LiDAR point. x, y, z in metres in the `lidar` frame (x forward, y left, z up);
# azimuth = the sensor's rotation angle (clockwise seen from above, 0 = +x) in radians;
# t = firing time, int64 ns since the Unix epoch; return_type 0 strongest, 1 last;
# duplicate = 1 on the strongest return of a dual-return firing whose distance equals the
# last return's (the sensor repeats a single echo in both blocks): keep it for "all
# strongest returns", drop it for "distinct returns".
POINT_DTYPE = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("azimuth", "<f4"),
        ("t", "<i8"),
        ("intensity", "u1"),
        ("ring", "u1"),
        ("return_type", "u1"),
        ("duplicate", "u1"),
    ]
)


def row_items(array: np.ndarray) -> np.ndarray:
    """The array's rows (along its first axis) as a 1-D array of opaque items over the
    same memory: a mask or an index then copies each row as one block of bytes. NumPy
    copies a packed structured dtype field by field, record by record (many times the
    cost of copying the same bytes: docs/performance.md), and a 2-D array's rows value by
    value. A plain 1-D
    array is returned as it is: its items are copied natively already. A 2-D array must be
    C-contiguous (a copy otherwise, which writes would not reach)."""
    if array.ndim == 1 and array.dtype.fields is None:
        return array
    rows = array if array.ndim == 1 else np.ascontiguousarray(array)
    width = rows.itemsize * (rows.shape[1] if rows.ndim == 2 else 1)
    return rows.view(np.dtype((np.void, width))).reshape(-1)


def take_points(points: np.ndarray, index: np.ndarray | slice) -> np.ndarray:
    """`points[index]` (a new array) for a structured array such as `POINT_DTYPE`, copied
    as whole records (`row_items`), not field by field as NumPy would."""
    taken = row_items(points)[index]
    if isinstance(index, slice):
        taken = taken.copy()  # a slice is a view
    return taken.view(points.dtype)


@dataclass(frozen=True, slots=True)
class Scan:
    """One LiDAR rotation.

    `t_start`/`t_end` are the device firing times (ns since the epoch) of the first and
    last firing in the scan; `t_host` is the host receive time of its last packet.
    `complete` is True when the scan began and ended at the cut angle (a whole rotation),
    False for the partial first and last scans of a stream and after a time jump.
    """

    points: np.ndarray
    t_start: int
    t_end: int
    t_host: int
    complete: bool
    packets: int
    lost_packets: int
    model: str
    return_mode: str

    @property
    def distinct(self) -> np.ndarray:
        """The points without the dual-return duplicates (each echo once)."""
        return take_points(self.points, self.points["duplicate"] == 0)


@dataclass(frozen=True, slots=True)
class Fix:
    """One GNSS epoch, assembled from the sentences that share its UTC time.

    Angles in degrees; `heading_deg` and `course_deg` clockwise from true north (not grid
    north: apply the UTM convergence); heights in metres. Fields a receiver did not send
    are None. `quality` is GGA's fix quality as sent (0 invalid, 1 GPS, 2 DGPS/SBAS,
    4 RTK fixed, 5 RTK float, 6 dead reckoning, ...).
    """

    t_host: int  # receive time of the epoch's first sentence, ns since the Unix epoch
    utc_ns: int | None  # the epoch's UTC, ns since the Unix epoch (None until a date is known)
    lat: float | None
    lon: float | None
    altitude_msl_m: float | None
    geoid_separation_m: float | None
    quality: int
    satellites: int | None
    hdop: float | None
    std_lat_m: float | None = None  # GST
    std_lon_m: float | None = None
    std_alt_m: float | None = None
    heading_deg: float | None = None  # HDT / THS (valid modes only)
    course_deg: float | None = None  # RMC / VTG course over ground
    speed_mps: float | None = None
    correction_age_s: float | None = None

    @property
    def altitude_ellipsoid_m(self) -> float | None:
        if self.altitude_msl_m is None or self.geoid_separation_m is None:
            return None
        return self.altitude_msl_m + self.geoid_separation_m


@dataclass(frozen=True, slots=True)
class WheelSample:
    """Cumulative wheel travel of the left and right side, as the robot reports it.

    `unit` is "rad" (the Jackal MCU reports wheel rotation) or "ticks" (an encoder board);
    the localisation turns it into metres with the calibration's `wheels` section.
    """

    t_host: int  # ns since the Unix epoch
    left: float
    right: float
    unit: str
    t_device_us: int | None = None  # the board's own clock, where it has one
    left_velocity: float | None = None  # same unit per second, where reported
    right_velocity: float | None = None


# libjpeg's warning when the data ends before the image (JWRN_JPEG_EOF).
_CUT_SHORT = "Premature end of JPEG file"


@dataclass(frozen=True, slots=True)
class Frame:
    """One camera image: the JPEG bytes as the camera sent them, decoded only on demand.

    `t_capture` is the exposure start the driver reports (the V4L2 buffer timestamp turned
    into ns since the Unix epoch) where known, else `t_host`.
    """

    jpeg: bytes
    t_host: int
    t_capture: int
    sequence: int = 0

    def decode(self, reduction: int = 1) -> np.ndarray:
        """The image as an OpenCV BGR uint8 array. Raises ParseError for a JPEG that is not
        one or whose data ends before the image does.

        `reduction` 2, 4 or 8: decoded at 1/2, 1/4 or 1/8 of the size (ceil(W / r) x
        ceil(H / r)), each pixel about the mean of the r x r pixels it stands for; the JPEG
        decoder scales in its inverse DCT, so this is cheaper than decoding and resizing.

        libjpeg-turbo through simplejpeg: the same pixels as OpenCV's `imdecode` (its
        libjpeg-turbo, the same accurate DCT and smooth chroma upsampling; a test holds them
        equal) in less time, with no OpenCV layer in between (docs/performance.md).
        Damage is taken as `imdecode` takes it: a frame cut short (the decoder runs out of
        data: its lower rows would be filler) is refused, other damage the decoder recovers
        from (a flipped bit, a frame cut and closed) is decoded."""
        import simplejpeg

        from treetraits.errors import ParseError

        if reduction not in (1, 2, 4, 8):
            raise ValueError(f"reduction must be 1, 2, 4 or 8, got {reduction}")
        try:
            height, width, _, _ = simplejpeg.decode_jpeg_header(self.jpeg)
            size = {"min_height": -(-height // reduction), "min_width": -(-width // reduction)}
            try:  # strict: any warning stops it, so intact frames are decoded once
                return simplejpeg.decode_jpeg(self.jpeg, "BGR", **size)
            except ValueError as exc:
                if _CUT_SHORT in str(exc):
                    raise
                return simplejpeg.decode_jpeg(self.jpeg, "BGR", strict=False, **size)
        except ValueError as exc:
            raise ParseError(
                f"frame {self.sequence}: not a decodable JPEG ({len(self.jpeg)} bytes: {exc})"
            ) from exc
