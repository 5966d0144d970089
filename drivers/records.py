"""Records that cross module boundaries (ARCHITECTURE.md, "Data that crosses module boundaries").

Defined once here and used everywhere. Bulk points are NumPy structured arrays with
`POINT_DTYPE`; everything else is a frozen dataclass.
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
        return self.points[self.points["duplicate"] == 0]
