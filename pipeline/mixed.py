"""Mixed returns: a beam's footprint half on an object's edge and half on what stands
behind it gives one range between the two (the VLP-16's 3 mrad beam is 2-3 cm wide
at 8 m; its receiver averages the two echoes when they are closer than it can tell
apart). Such a return floats in the empty space between two surfaces, and it links
them: on the real einride capture one return on ring 8 (the wall at 8.14 m, then
7.98 m, then an object at 7.47 m) joined a 0.34 m object to 9 returns of the wall
0.67 m behind it, through the clustering's 0.5 m tolerance.

A return is mixed when, along its ring (consecutive firings, none missing):
- its two neighbours' ranges differ by more than the clustering tolerance: a smaller
  step joins the two sides anyway, so leaving the return out changes nothing;
- it lies between them, at least `offset_m` off each (three times the VLP-16's 3 cm
  range accuracy: not the noise of either surface);
- each side goes on as a surface: the next return beyond each neighbour lies within
  `offset_m` of it in range. In foliage consecutive beams fall on leaves decimetres
  apart in depth, so a crown's returns are never taken for mixed ones.

Measured on real returns (first 20 scans of each; docs/pipeline.md): 0.36-0.54 per
mille of the indoor captures' returns, 2.8 per mille of the orchard capture's (canopy
edges against the rows behind).
"""

from __future__ import annotations

import math

import numpy as np

from treetraits.drivers.records import POINT_DTYPE
from treetraits.jit import kernel, warm_up

# Two returns of a ring are consecutive firings when their azimuths are at most this
# many median firing steps apart: half way between one step and two (a firing with no
# return). On the real captures (first 20 scans) 95-98 % of a ring's steps are within
# 1.1x the median, 0.01-1.3 % between 1.1 and 1.5x, 1.2-1.8 % near 2x.
_CONSECUTIVE_STEPS = 1.5


def mixed_returns(points: np.ndarray, tolerance_m: float, offset_m: float) -> np.ndarray:
    """Which of a scan's returns (POINT_DTYPE, `lidar`) are mixed (module docstring):
    a bool per return. A dual-return sensor's last echoes are read (one per firing), a
    single-return sensor's every return; returns out of firing order (a converted bag)
    are put in order by their time first. `offset_m` 0 leaves nothing out."""
    mixed = np.zeros(len(points), dtype=bool)
    if offset_m <= 0 or len(points) < 5:
        return mixed
    last = points["return_type"] == 1
    read = np.flatnonzero(last) if last.any() else np.arange(len(points))
    times = points["t"][read]
    if np.any(times[1:] < times[:-1]):
        read = read[np.argsort(times, kind="stable")]
    ring = points["ring"][read]
    by_ring = np.argsort(ring, kind="stable")  # a radix sort: uint8 keys
    read, ring = read[by_ring], ring[by_ring]
    x, y, z = (points[axis][read].astype(float) for axis in ("x", "y", "z"))
    reach = np.sqrt(x * x + y * y + z * z)
    azimuth = points["azimuth"][read].astype(float)
    flags = np.zeros(len(read), dtype=np.bool_)
    _flag(ring, azimuth, reach, float(tolerance_m), float(offset_m), flags)
    mixed[read[flags]] = True
    return mixed


@kernel
def _flag(ring, azimuth, reach, tolerance, offset, flags):  # fmt: skip
    """Over returns sorted by ring, each in firing order: `flags` set on the mixed ones
    (`mixed_returns`); returns how many."""
    n = ring.shape[0]
    if n < 5:
        return 0
    step = np.empty(n - 1)  # the azimuth from each return to the next on its ring
    moving = np.zeros(n - 1, dtype=np.bool_)
    for k in range(n - 1):
        d = azimuth[k + 1] - azimuth[k]
        if d < -math.pi:  # across the sensor's 0/2 pi seam
            d += 2 * math.pi
        elif d >= math.pi:
            d -= 2 * math.pi
        step[k] = d
        moving[k] = ring[k + 1] == ring[k] and d > 0
    if not moving.any():
        return 0
    limit = _CONSECUTIVE_STEPS * np.median(step[moving])
    linked = moving & (step <= limit)  # consecutive firings, none missing
    count = 0
    for k in range(2, n - 2):
        if not (linked[k - 2] and linked[k - 1] and linked[k] and linked[k + 1]):
            continue
        before, here, after = reach[k - 1], reach[k], reach[k + 1]
        near, far = min(before, after), max(before, after)
        if far - near <= tolerance or here < near + offset or here > far - offset:
            continue
        # Each side goes on as a surface beyond its neighbour.
        if abs(reach[k - 2] - before) <= offset and abs(reach[k + 2] - after) <= offset:
            flags[k] = True
            count += 1
    return count


@warm_up
def compile_kernels() -> None:
    """The kernel compiled for the types a scan gives it, on a made-up ring."""
    points = np.zeros(8, dtype=POINT_DTYPE)
    points["azimuth"] = np.arange(8) * 0.003
    points["x"] = [2.0, 2.0, 2.0, 2.5, 3.0, 3.0, 3.0, 3.0]
    mixed_returns(points, 0.5, 0.1)
