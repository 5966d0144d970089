"""A ROS `sensor_msgs/PointCloud2` to scan points (`POINT_DTYPE`), for `/lidar/points`.

Pure NumPy on the message's fields (docs/import.md, "PointCloud2"): x y z (required),
`intensity` (any numeric type, rounded and clipped to 0..255), the beam as `ring` (ROS
velodyne_pointcloud) or `channel` (nebula, Hesai), and a per-point time as `time`
(velodyne_pointcloud, float32 s), `t` (Ouster, uint32 ns), `time_stamp` (nebula, uint32
ns), `timestamp` (Hesai, float64 s) or `offset_time` (Livox, uint32 ns). A float time is
in seconds, an integer one in ns; a value past 1e8 s (3 years) is since the Unix epoch,
a smaller one is relative to the header stamp. Points whose x, y or z is not finite (an
organised cloud's no-returns) are dropped and counted.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from treetraits.drivers.recording.points import PointsHeader, azimuth_of
from treetraits.drivers.records import POINT_DTYPE

# sensor_msgs/PointField datatypes.
_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
RING_NAMES = ("ring", "channel")
TIME_NAMES = ("time", "t", "time_stamp", "timestamp", "offset_time")
_ABSOLUTE_S = 1e8  # a time past this many seconds is since the epoch, not an offset
# Beams -> model name, for the scan record (a cloud does not say which sensor made it).
_MODEL_BY_BEAMS = {16: "VLP-16"}


class CloudError(ValueError):
    """A PointCloud2 whose layout cannot be read (skipped and counted by the importer)."""


@dataclass(frozen=True, slots=True)
class Cloud:
    header: PointsHeader
    points: np.ndarray  # POINT_DTYPE
    dropped: int  # points without finite x, y, z


def _dtype(fields: Sequence[Any], point_step: int, big_endian: bool) -> np.dtype:
    names, formats, offsets = [], [], []
    order = ">" if big_endian else "<"
    for f in fields:
        code = _TYPES.get(int(f.datatype))
        if code is None:
            raise CloudError(f"field {f.name} has unknown datatype {f.datatype}")
        if str(f.name) in names:
            continue
        names.append(str(f.name))
        formats.append(order + code)
        offsets.append(int(f.offset))
    if any(o + np.dtype(t).itemsize > point_step for o, t in zip(offsets, formats, strict=True)):
        raise CloudError(f"a field lies past point_step {point_step}")
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )


def _rows(msg: Any, dtype: np.dtype) -> np.ndarray:
    width, height = int(msg.width), int(msg.height)
    row_step, step = int(msg.row_step), int(msg.point_step)
    raw = np.asarray(msg.data, dtype=np.uint8)
    if step <= 0 or row_step < width * step or raw.size < height * row_step:
        raise CloudError("data shorter than height x row_step")
    rows = raw[: height * row_step].reshape(height, row_step)[:, : width * step]
    return np.ascontiguousarray(rows).reshape(-1).view(dtype)


def point_times(values: np.ndarray, stamp: int) -> np.ndarray:
    """Per-point times (ns since the epoch) from a cloud's time field (module docstring)."""
    if values.dtype.kind == "f":
        seconds = np.nan_to_num(values.astype(np.float64))
        absolute = len(seconds) and np.nanmax(np.abs(seconds)) > _ABSOLUTE_S
        ns = np.round(seconds * 1e9).astype(np.int64)
        return ns if absolute else stamp + ns
    ns = values.astype(np.int64)
    return ns if len(ns) and np.abs(ns).max() > _ABSOLUTE_S * 1e9 else stamp + ns


def cloud_points(msg: Any, stamp: int) -> Cloud:
    """A PointCloud2 message (rosbags' deserialised object) as scan points."""
    dtype = _dtype(msg.fields, int(msg.point_step), bool(msg.is_bigendian))
    names = set(dtype.names or ())
    if not {"x", "y", "z"} <= names:
        raise CloudError("no x, y, z fields")
    rows = _rows(msg, dtype)
    x, y, z = (rows[n].astype(np.float32) for n in ("x", "y", "z"))
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    rows, x, y, z = rows[finite], x[finite], y[finite], z[finite]
    points = np.zeros(len(rows), dtype=POINT_DTYPE)
    points["x"], points["y"], points["z"] = x, y, z
    points["azimuth"] = azimuth_of(x, y)
    kept = ["x", "y", "z"]
    if "intensity" in names:
        values = np.nan_to_num(rows["intensity"].astype(np.float64))
        points["intensity"] = np.clip(np.round(values), 0, 255).astype(np.uint8)
        kept.append("intensity")
    ring = next((n for n in RING_NAMES if n in names), None)
    model = "unknown"
    if ring is not None:
        beams = rows[ring].astype(np.int64)
        points["ring"] = np.clip(beams, 0, 255).astype(np.uint8)
        kept.append("ring")
        if len(beams):
            model = _MODEL_BY_BEAMS.get(int(beams.max()) + 1, "unknown")
    time = next((n for n in TIME_NAMES if n in names), None)
    if time is not None:
        points["t"] = point_times(rows[time], stamp)
        kept.append("t")
    else:
        points["t"] = stamp
    frame = str(msg.header.frame_id)
    header = PointsHeader(frame, stamp, tuple(kept), len(points), model)
    return Cloud(header, points, int((~finite).sum()))
