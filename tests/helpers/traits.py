"""Reference formulations of the traits' measures."""

from __future__ import annotations

import math

import numpy as np


def every_slice_width(points, slices, floor):
    """slice_width without its bounds: every slice of two points or more measured (the
    farthest pair, 3D, among its x-y hull's vertices)."""
    import cv2

    z = points[:, 2]
    span = max(float(z.max()) - float(z.min()), 1e-9)
    index = np.minimum(((z - z.min()) * (slices / span)).astype(np.int64), slices - 1)
    best = floor * floor
    for k in range(slices):
        members = points[index == k]
        if len(members) < 2:
            continue
        hull = cv2.convexHull(members[:, :2].astype(np.float32), returnPoints=False)
        vertices = members[hull.ravel()]
        gaps = vertices[:, None, :] - vertices[None, :, :]
        best = max(best, float(np.einsum("ijk,ijk->ij", gaps, gaps).max()))
    return math.sqrt(best)
