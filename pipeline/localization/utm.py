"""WGS84 <-> the UTM zone of the first good fix, and the grid convergence there.

The zone is fixed at the datum (as robot_localization does), so a field that straddles a
zone edge stays one continuous grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pyproj


@dataclass(frozen=True)
class UtmGrid:
    zone: int
    north: bool
    _to_utm: pyproj.Transformer = field(repr=False, compare=False)
    _to_wgs84: pyproj.Transformer = field(repr=False, compare=False)
    _proj: pyproj.Proj = field(repr=False, compare=False)

    @classmethod
    def for_position(cls, lat: float, lon: float) -> UtmGrid:
        """The UTM zone that holds (lat, lon) (plain 6-degree zones)."""
        zone = int((lon + 180.0) // 6.0) % 60 + 1
        north = lat >= 0.0
        return cls.for_zone(zone, north)

    @classmethod
    def for_zone(cls, zone: int, north: bool) -> UtmGrid:
        import pyproj

        epsg = (32600 if north else 32700) + zone
        return cls(
            zone=zone,
            north=north,
            _to_utm=pyproj.Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True),
            _to_wgs84=pyproj.Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True),
            _proj=pyproj.Proj(proj="utm", zone=zone, south=not north, ellps="WGS84"),
        )

    @property
    def name(self) -> str:
        """Like `11N`, as in trees.csv."""
        return f"{self.zone}{'N' if self.north else 'S'}"

    def forward(self, lat: float, lon: float) -> tuple[float, float]:
        """(easting, northing) in metres. Arrays too (one PROJ call for all, the same
        values as point by point)."""
        return self._to_utm.transform(lon, lat)

    def inverse(self, easting: float, northing: float) -> tuple[float, float]:
        """(lat, lon) in degrees. Arrays too, as `forward`."""
        lon, lat = self._to_wgs84.transform(easting, northing)
        return lat, lon

    def convergence_rad(self, lat: float, lon: float) -> float:
        """Angle from grid north to true north, counter-clockwise positive: a yaw measured
        from true east becomes a grid yaw by adding it."""
        return math.radians(self._proj.get_factors(lon, lat).meridian_convergence)


def true_heading_to_grid_yaw(heading_deg: float, convergence_rad: float) -> float:
    """NMEA heading (degrees clockwise from true north) to ENU yaw in the UTM grid
    (radians counter-clockwise from grid east)."""
    return wrap_angle(math.pi / 2 - math.radians(heading_deg) + convergence_rad)


def wrap_angle(angle: float) -> float:
    """Into [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi
