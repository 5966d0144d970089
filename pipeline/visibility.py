"""Whether a cluster's top was in the LiDAR's view in a scan.

A spinning LiDAR sees nothing above its top beam (+15 deg on a VLP-16, 0.4 m up on a
Jackal: 3 m is in reach from 9.5 m away only). A crown taller than the top beam reaches
at its range is cut flat there, and its measured height is a lower bound.

The top of a cluster is *seen* in a scan when the whole cluster lies under the beam just
above the highest ring that hit it: across every bearing the cluster spans (widened by
`window_rad`), that beam returned nothing nearer than the cluster's farthest return plus
`reach_m` (it went on into the sky or onto something behind, farther than the clustering
joins to the object). A nearer return of that beam means something hid what lies above
(a neighbour's crown along a hedgerow, a branch, a person) or the object goes on upward:
not seen. A cluster the sensor's top ring hit has no beam above: not seen.

The whole span, not the top return's bearing alone: along a hedgerow the topmost return
of a far crown is often on its near flank, where the beam above grazes past, while the
crown's apex, at another bearing, is hidden by the nearer crowns.

Rings are ordered by elevation (0 = lowest beam, docs/architecture.md); bearings are
taken from the returns' own x, y in the `lidar` frame, which every source has.
"""

from __future__ import annotations

import math

import numpy as np

from treetraits.jit import kernel, kernel_layout, warm_up
from treetraits.pipeline.medians import median_of_groups

# The sensor's top beam, not the highest that hit something in a scan (over a young
# grove the top beams may see only sky): every model read has 16 beams
# (`drivers.velodyne.models`); a cloud with more rings raises it to its highest.
TOP_RING = 15
# A ring's elevation is read off its returns from this far out. Each laser sits up to
# ~1 cm above or below the sensor's origin, so a near return's angle from the origin is
# off its beam's: on the six real VLP-16 captures (indoor, and the orchard) the rings'
# median elevations over all returns were up to 0.97 deg off the datasheet's, over the
# returns 6 m away or more within 0.1 deg (2.6 cm at 15 m) on every ring that had them,
# and a line through those about as close to every ring's (tests/pipeline/test_visibility.py).
_FAR_FOR_ELEVATION_M = 6.0


class BeamsAbove:
    """One scan's returns grouped by ring, for the beam-above test."""

    def __init__(self, points: np.ndarray):
        ring = points["ring"].astype(np.int64)
        x = points["x"].astype(float)
        y = points["y"].astype(float)
        z = points["z"].astype(float)
        bearing = np.arctan2(y, x)  # NumPy's (SIMD) arctangent, not a kernel's
        self.top_ring = max(TOP_RING, int(ring.max()) if len(ring) else 0)
        # The ranges, the ring order (a stable counting sort: np.argsort(kind="stable")'s
        # order) and each ring's first return in it, in one kernel.
        span, self._bearing, self._range, self._starts = _by_ring(
            x, y, z, ring, bearing, self.top_ring
        )
        # Per return in the scan's order, for the clusters' own returns: what top_seen
        # worked out again for each cluster, the same values gathered.
        self._by_point = (x, y, z, bearing, span, ring)
        self._elevations: np.ndarray | None = None  # each ring's, once a top is seen

    def top_seen(self, members: np.ndarray, window_rad: float, reach_m: float) -> bool:
        """Whether the beam above the cluster `members` (indices into the scan this was
        built on) passed over all of it: see the module's docstring. Two kernels, to the
        bit `top_seen_numpy`; the arctangent of the top stays NumPy's."""
        members = kernel_layout(members, np.int64)
        top, ring = _top_and_ring(self._by_point[2], self._by_point[5], members)
        return ring < self.top_ring and self._over_all(members, top, ring, window_rad, reach_m)

    def _over_all(self, members, top: int, ring: int, window_rad: float, reach_m: float) -> bool:
        """`top_seen` for a cluster whose top return `top` is on `ring`, below the top ring."""
        x, y, _, bearing, span, _ = self._by_point
        centre = float(np.arctan2(y[top], x[top]))  # as before: the scalar arctangent
        start, end = self._starts[ring + 1], self._starts[ring + 2]
        return _passed_over(
            bearing, span, members, centre, window_rad, reach_m, self._bearing, self._range,
            start, end,
        )  # fmt: skip

    def top_view(
        self, members: np.ndarray, window_rad: float, reach_m: float
    ) -> tuple[np.ndarray | None, bool]:
        """The cluster `members`' top in this scan: where the beam above it pointed at its
        top's bearing (a unit vector, the LiDAR's frame) when it passed over all of it
        (`top_seen`), else None; and whether the sensor's top ring hit it (cut: no beam is
        above it, and it may go on above the top beam's reach, a crown too close for its
        top to be in view). The crown's top lies under the beam above: with its highest
        return below, the two bracket the top's height in this scan (`pipeline.mapper`,
        `height_top_seen`)."""
        members = kernel_layout(members, np.int64)
        x, y, z, _, _, rings = self._by_point
        top, ring = _top_and_ring(z, rings, members)
        if ring >= self.top_ring:
            return None, True
        if not self._over_all(members, top, ring, window_rad, reach_m):
            return None, False
        elevation = self._elevation_above(int(ring))
        if elevation is None:
            return None, False
        bearing = math.atan2(y[top], x[top])
        flat = math.cos(elevation)
        beam = np.array([flat * math.cos(bearing), flat * math.sin(bearing), math.sin(elevation)])
        return beam, False

    def _elevation_above(self, ring: int) -> float | None:
        """The elevation (rad, the LiDAR's frame) of the ring above `ring`. The beams are
        evenly spaced in elevation: a line through the rings' medians over their returns
        `_FAR_FOR_ELEVATION_M` away or more, where two rings or more have such returns
        (a ring that hit nothing far, or nothing at all, is read off the line). Else each
        ring's median over all its returns, and a ring that hit nothing continues the
        step between `ring` and the nearest ring below it that hit something. None when
        neither can be measured."""
        if self._elevations is None:
            x, y, z, _, span, rings = self._by_point
            order = np.argsort(rings, kind="stable")  # each ring's returns one slice
            elevation = np.arctan2(z[order], np.hypot(x[order], y[order]))
            everything = median_of_groups(elevation, rings[order], self.top_ring + 1)
            far = span[order] >= _FAR_FOR_ELEVATION_M
            far_only = median_of_groups(elevation[far], rings[order][far], self.top_ring + 1)
            measured = np.flatnonzero(np.isfinite(far_only))
            self._elevations = everything
            if len(measured) >= 2:  # the beams are evenly spaced: a line through them
                slope, at_zero = np.polyfit(measured, far_only[measured], 1)
                self._elevations = at_zero + slope * np.arange(self.top_ring + 1)
        above = self._elevations[ring + 1]
        if math.isfinite(above):
            return float(above)
        below = np.flatnonzero(np.isfinite(self._elevations[:ring]))
        here = self._elevations[ring]
        if not len(below) or not math.isfinite(here):
            return None
        lower = int(below[-1])
        return float(here + (here - self._elevations[lower]) / (ring - lower))

    def top_seen_numpy(self, members: np.ndarray, window_rad: float, reach_m: float) -> bool:
        """`top_seen` in NumPy calls: the formulation its kernels are held to (tests)."""
        x, y, z, bearing, span, rings = self._by_point
        # Gathered as needed: heights and rings first (the top ring has no beam above),
        # x and y at the top alone.
        top = members[int(np.argmax(z[members]))]
        ring = int(rings[members].max())  # the cluster's highest beam: the next one up
        if ring >= self.top_ring:
            return False
        # Bearings relative to the top's, so a span across the +-pi seam stays whole.
        centre = float(np.arctan2(y[top], x[top]))  # as before: the scalar arctangent
        offsets = _wrap(bearing[members] - centre)
        low, high = offsets.min() - window_rad, offsets.max() + window_rad
        farthest = float(span[members].max())
        start, end = self._starts[ring + 1], self._starts[ring + 2]
        above = _wrap(self._bearing[start:end] - centre)
        inside = (above >= low) & (above <= high)
        return not bool(np.any(self._range[start:end][inside] <= farthest + reach_m))


@kernel
def _by_ring(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, ring: np.ndarray, bearing: np.ndarray, top: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each return's range (`np.sqrt(x * x + y * y + z * z)`, summed in that order), and
    the bearings and ranges sorted by ring (stable), with the start of each ring 0 to
    `top` + 1 in them (`np.searchsorted` of the sorted rings, side left)."""
    n = len(x)
    span = np.empty(n)
    starts = np.zeros(top + 2, dtype=np.int64)
    for i in range(n):
        span[i] = math.sqrt(x[i] * x[i] + y[i] * y[i] + z[i] * z[i])
        starts[ring[i] + 1] += 1
    for r in range(1, top + 2):
        starts[r] += starts[r - 1]
    at = starts.copy()
    sorted_bearing, sorted_range = np.empty(n), np.empty(n)
    for i in range(n):
        k = at[ring[i]]
        sorted_bearing[k], sorted_range[k] = bearing[i], span[i]
        at[ring[i]] = k + 1
    return span, sorted_bearing, sorted_range, starts


@kernel
def _top_and_ring(z: np.ndarray, rings: np.ndarray, members: np.ndarray) -> tuple[int, int]:
    """The member highest up (the first of equals, or the first NaN, as np.argmax) and
    the highest ring among the members."""
    top, ring = members[0], rings[members[0]]
    for i in members[1:]:
        if z[i] > z[top] or (math.isnan(z[i]) and not math.isnan(z[top])):
            top = i
        ring = max(ring, rings[i])
    return top, ring


@kernel
def _passed_over(
    bearing: np.ndarray,
    span: np.ndarray,
    members: np.ndarray,
    centre: float,
    window_rad: float,
    reach_m: float,
    beam_bearing: np.ndarray,
    beam_range: np.ndarray,
    start: int,
    end: int,
) -> bool:
    """No return of the beam above (`start`:`end` of the ring-sorted returns) within the
    members' bearings (from `centre`, widened by the window) nearer than their farthest
    return plus `reach_m`. NaN bearings or ranges make the bounds NaN, as NumPy's min and
    max do (then no return is inside)."""
    low, high, farthest = math.inf, -math.inf, -math.inf
    for i in members:
        offset = _wrap_one(bearing[i] - centre)
        low = offset if offset < low or math.isnan(offset) or math.isnan(low) else low
        high = offset if offset > high or math.isnan(offset) or math.isnan(high) else high
        far = span[i]
        farthest = far if far > farthest or math.isnan(far) or math.isnan(farthest) else farthest
    low, high = low - window_rad, high + window_rad
    for j in range(start, end):
        above = _wrap_one(beam_bearing[j] - centre)
        if above >= low and above <= high and beam_range[j] <= farthest + reach_m:
            return False
    return True


@kernel
def _wrap_one(angle: float) -> float:
    """`_wrap` of one angle: numba's float % is Python's, as NumPy's remainder (fmod,
    then the divisor's sign)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def _wrap(angles: np.ndarray) -> np.ndarray:
    """Angles into [-pi, pi)."""
    return (angles + np.pi) % (2 * np.pi) - np.pi


@warm_up
def compile_kernels() -> None:
    """The kernels compiled for the types a scan gives them: float32 returns, uint8 rings
    (`POINT_DTYPE`), int64 member indices."""
    points = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ring", "u1")])
    points["x"], points["z"], points["ring"] = 5.0, (0.0, 0.5, 1.0), (0, 1, 2)
    BeamsAbove(points).top_seen(np.arange(2), 0.01, 0.5)
    _wrap_one(0.5)  # a helper too: a caller loaded from the cache compiles none
