"""The points channel of recording format v1.1: a LiDAR scan that reaches treetraits as a
decoded point cloud (a ROS `sensor_msgs/PointCloud2`, `rosbag_import`), not as the
packets the VLP-16 sends (docs/recording.md, "Format 1.1").

`/lidar/points` (`treetraits-points`), one message per scan:

- u32 little-endian: n, the length of the JSON header;
- n bytes of UTF-8 JSON: `frame_id` (the cloud's frame), `stamp` (its header stamp, ns),
  `fields` (the `POINT_DTYPE` fields the source carried: `x y z` always, `intensity`,
  `ring`, `t` when it had them; the others are derived, see below), `count`, `model`
  (e.g. "VLP-16", "unknown"), `return_mode` ("unknown" unless the source said);
- `count` rows of `POINT_DTYPE` (28 bytes each, little-endian), in the cloud's order.

Derived fields: `azimuth` from x and y (clockwise seen from above, 0 = +x, as the packet
decoder's); `t` = `stamp` for every point when the cloud had no per-point time;
`intensity` and `ring` 0 when absent; `return_type` and `duplicate` 0 (each point of a
cloud is one point).

`decode_points` turns a message into the `Scan` the packet path makes: `t_start`/`t_end`
the first and last point time, `t_host` = `t_end` (a ROS driver stamps points on the host
clock), `complete` True (a driver publishes whole rotations), `packets` 0.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass

import numpy as np

from treetraits.drivers.records import POINT_DTYPE, Scan
from treetraits.errors import ParseError

_LENGTH = struct.Struct("<I")
# Fields a source can give; the rest of POINT_DTYPE is derived.
SOURCE_FIELDS = ("x", "y", "z", "intensity", "ring", "t")


@dataclass(frozen=True, slots=True)
class PointsHeader:
    frame_id: str
    stamp: int  # the cloud's header stamp, ns since the Unix epoch
    fields: tuple[str, ...]  # POINT_DTYPE fields taken from the source
    count: int
    model: str = "unknown"
    return_mode: str = "unknown"


def azimuth_of(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The rotor angle of points in the lidar frame, as the packet decoder gives it:
    clockwise seen from above, 0 = +x, in [0, 2 pi)."""
    angle = np.arctan2(-np.asarray(y, np.float64), np.asarray(x, np.float64))
    return np.mod(angle, 2 * np.pi).astype(np.float32)


def encode_points(header: PointsHeader, points: np.ndarray) -> bytes:
    if points.dtype != POINT_DTYPE or len(points) != header.count:
        raise ValueError("points must be POINT_DTYPE rows, as many as header.count")
    text = json.dumps(
        {
            "frame_id": header.frame_id,
            "stamp": header.stamp,
            "fields": list(header.fields),
            "count": header.count,
            "model": header.model,
            "return_mode": header.return_mode,
        },
        separators=(",", ":"),
    ).encode()
    return _LENGTH.pack(len(text)) + text + points.tobytes()


def decode_header(data: bytes) -> tuple[PointsHeader, int]:
    """The header and the offset of the first row; ParseError for a malformed message."""
    if len(data) < _LENGTH.size:
        raise ParseError(f"points message of {len(data)} bytes")
    (length,) = _LENGTH.unpack_from(data)
    end = _LENGTH.size + length
    try:
        meta = json.loads(bytes(data[_LENGTH.size : end]))
        header = PointsHeader(
            str(meta["frame_id"]),
            int(meta["stamp"]),
            tuple(str(f) for f in meta["fields"]),
            int(meta["count"]),
            str(meta.get("model", "unknown")),
            str(meta.get("return_mode", "unknown")),
        )
    except (ValueError, KeyError, TypeError) as error:
        raise ParseError(f"points message header unreadable ({error})") from None
    if header.count < 0 or len(data) - end != header.count * POINT_DTYPE.itemsize:
        raise ParseError(
            f"points message holds {len(data) - end} bytes of rows for {header.count} points"
        )
    return header, end


def decode_points(data: bytes) -> Scan:
    """A `/lidar/points` message as the `Scan` the packet path makes (module docstring)."""
    header, offset = decode_header(data)
    points = np.frombuffer(data, dtype=POINT_DTYPE, offset=offset, count=header.count).copy()
    if len(points):
        t_start, t_end = int(points["t"].min()), int(points["t"].max())
    else:
        t_start = t_end = header.stamp
    return Scan(
        points=points,
        t_start=t_start,
        t_end=t_end,
        t_host=t_end,
        complete=True,
        packets=0,
        lost_packets=0,
        model=header.model,
        return_mode=header.return_mode,
    )
