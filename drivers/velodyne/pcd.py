"""Binary PCD (v0.7) files of a scan, readable by PCL, Open3D and CloudCompare.

Fields: x y z (float32, metres, lidar frame), intensity (uint8, calibrated reflectivity),
ring (uint8, 0 = lowest beam), t (float64, seconds since the Unix epoch: a double holds
epoch seconds to about 0.2 us).
"""

from __future__ import annotations

from pathlib import Path
from typing import IO

import numpy as np

from treetraits.files import write_atomically

PCD_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"), ("ring", "u1"), ("t", "<f8")]
)
_PCD_TYPES = {"f": "F", "u": "U", "i": "I"}


def pcd_header(dtype: np.dtype, count: int) -> bytes:
    names = dtype.names or ()
    sizes = " ".join(str(dtype[n].itemsize) for n in names)
    types = " ".join(_PCD_TYPES[dtype[n].kind] for n in names)
    return (
        "# .PCD v0.7 - written by treetraits\n"
        "VERSION 0.7\n"
        f"FIELDS {' '.join(names)}\n"
        f"SIZE {sizes}\n"
        f"TYPE {types}\n"
        f"COUNT {' '.join('1' for _ in names)}\n"
        f"WIDTH {count}\n"
        "HEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {count}\n"
        "DATA binary\n"
    ).encode("ascii")


def write_pcd(path: str | Path, points: np.ndarray) -> None:
    """Write scan points (`POINT_DTYPE`) as a binary PCD, atomically (treetraits.files)."""
    rows = np.empty(len(points), dtype=PCD_DTYPE)
    for name in ("x", "y", "z", "intensity", "ring"):
        rows[name] = points[name]
    rows["t"] = points["t"] / 1e9

    def write(f: IO[bytes]) -> None:
        f.write(pcd_header(PCD_DTYPE, len(rows)))
        f.write(rows.tobytes())

    write_atomically(path, write, binary=True)
