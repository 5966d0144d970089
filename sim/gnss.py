"""A GNSS receiver emulator: NMEA 0183 sentences for the antenna's true position, as a
receiver would send them (GGA, RMC, GST and, with two antennas, HDT), each epoch with its
own noise, RTK or degraded, with outages.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass

import numpy as np

from treetraits.drivers.gnss.compose import lat_field, lon_field, sentence

QUALITY_SIGMA_M = {4: 0.02, 5: 0.25, 2: 0.6, 1: 2.0}  # RTK fixed, float, DGPS, autonomous


@dataclass(frozen=True)
class GnssSettings:
    rate_hz: float = 10.0
    quality: int = 4  # GGA quality while not in an outage
    dual_antenna: bool = False  # sends HDT (true heading) when True
    heading_sigma_deg: float = 0.3
    outages: tuple[tuple[float, float], ...] = ()  # (start s, end s) from the run's start
    # A receiver still converging: RTK float (quality 5) until this many seconds from the
    # start, then `quality` (None: `quality` throughout).
    converge_s: float | None = None
    # A float, DGPS or autonomous solution's error is not white: it wanders with the
    # satellite geometry and the atmosphere over minutes. Modelled as a first-order
    # Gauss-Markov process of this time constant with the quality's sigma; RTK fixed
    # stays white (centimetres, the ambiguities resolved).
    error_time_constant_s: float = 60.0
    satellites: int = 18
    hdop: float = 0.7
    geoid_separation_m: float = -32.5  # California-like


def epoch_sentences(
    utc: dt.datetime,
    lat: float,
    lon: float,
    altitude: float,
    quality: int,
    settings: GnssSettings,
    course_deg: float,
    speed_mps: float,
    heading_deg: float | None,
    sigma: float,
) -> list[bytes]:
    """One epoch's sentences, in the order a receiver sends them."""
    hhmmss = utc.strftime("%H%M%S.") + f"{utc.microsecond // 10000:02d}"
    lat_text, ns = lat_field(lat)
    lon_text, ew = lon_field(lon)
    out = [
        sentence(
            f"GNGGA,{hhmmss},{lat_text},{ns},{lon_text},{ew},{quality},"
            f"{settings.satellites:02d},{settings.hdop:.1f},{altitude:.3f},M,"
            f"{settings.geoid_separation_m:.1f},M,{'1.0' if quality in (4, 5) else ''},"
            f"{'0001' if quality in (4, 5) else ''}"
        ),
        sentence(
            f"GNRMC,{hhmmss},{'A' if quality else 'V'},{lat_text},{ns},{lon_text},{ew},"
            f"{speed_mps / 0.514444:.3f},{course_deg:.2f},{utc.strftime('%d%m%y')},,,"
            f"{ {4: 'R', 5: 'F', 2: 'D', 1: 'A'}.get(quality, 'N') },V"
        ),
        sentence(
            f"GNGST,{hhmmss},{sigma:.3f},{sigma:.3f},{sigma:.3f},0.0,{sigma:.3f},"
            f"{sigma:.3f},{2 * sigma:.3f}"
        ),
    ]
    if heading_deg is not None:
        out.append(sentence(f"GNHDT,{heading_deg % 360:.2f},T"))
    return out


class UtmZone:
    """The twin's own small UTM helper (sim/ may not import pipeline/): grid to WGS84 and
    the grid convergence (PROJ)."""

    def __init__(self, zone: int, north: bool = True):
        import pyproj

        epsg = (32600 if north else 32700) + zone
        self._to_wgs84 = pyproj.Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True)
        self._proj = pyproj.Proj(proj="utm", zone=zone, south=not north, ellps="WGS84")
        self.name = f"{zone}{'N' if north else 'S'}"

    def inverse(self, easting: float, northing: float) -> tuple[float, float]:
        lon, lat = self._to_wgs84.transform(easting, northing)
        return lat, lon

    def convergence_rad(self, lat: float, lon: float) -> float:
        return math.radians(self._proj.get_factors(lon, lat).meridian_convergence)


class GnssEmulator:
    """Turns true base poses into the sentences of a receiver whose antenna sits at
    `T_base_gnss` on the robot."""

    def __init__(
        self,
        grid: UtmZone,
        origin_utm: tuple[float, float],
        T_base_gnss: np.ndarray,
        settings: GnssSettings | None = None,
        rng: np.random.Generator | None = None,
    ):
        self.grid = grid
        self.origin = origin_utm
        self.lever = np.asarray(T_base_gnss, dtype=float)[:3, 3]
        self.settings = settings or GnssSettings()
        self.rng = rng or np.random.default_rng(0)
        self._wander: tuple[float, np.ndarray] | None = None  # (t_s, east-north error)

    def _wandering_error(self, t_s: float, sigma: float) -> np.ndarray:
        """The next value of the error's Gauss-Markov process (drawn afresh, stationary,
        at the first epoch of a non-fixed stretch)."""
        if self._wander is None:
            error = self.rng.normal(0, sigma, 2)
        else:
            decay = math.exp(-(t_s - self._wander[0]) / self.settings.error_time_constant_s)
            error = decay * self._wander[1] + math.sqrt(1 - decay**2) * self.rng.normal(0, sigma, 2)
        self._wander = (t_s, error)
        return error

    def epoch(
        self,
        t_s: float,
        utc: dt.datetime,
        x: float,
        y: float,
        yaw: float,
        speed: float,
        attitude: tuple[float, float, float] | None = None,
    ) -> list[bytes]:
        """`attitude` (z, pitch, roll) of the base on uneven ground: the antenna's lever
        arm turns with the robot's tilt and its height follows the ground (None: level, at
        z = 0, the paper's twin)."""
        s = self.settings
        if any(start <= t_s < end for start, end in s.outages):
            return []  # no sentences at all: the receiver lost the sky (or its link)
        quality = s.quality if s.converge_s is None or t_s >= s.converge_s else 5
        sigma = QUALITY_SIGMA_M[quality]
        c, si = math.cos(yaw), math.sin(yaw)
        if attitude is None:
            lever = self.lever
        else:
            from treetraits.sim.lidar import rotation_matrices

            z, pitch, roll = attitude
            lever = rotation_matrices(yaw, pitch, roll)[0] @ self.lever
            # Back into the yaw-only form below: the tilted lever, expressed along the
            # heading, plus the ground's height.
            lever = np.array(
                [c * lever[0] + si * lever[1], -si * lever[0] + c * lever[1], lever[2] + z]
            )
        east = self.origin[0] + x + c * lever[0] - si * lever[1]
        north = self.origin[1] + y + si * lever[0] + c * lever[1]
        if quality == 4:
            east += self.rng.normal(0, sigma)
            north += self.rng.normal(0, sigma)
            self._wander = None
        else:
            error = self._wandering_error(t_s, sigma)
            east, north = east + error[0], north + error[1]
        lat, lon = self.grid.inverse(east, north)
        convergence = self.grid.convergence_rad(lat, lon)
        true_heading = (90.0 - math.degrees(yaw - convergence)) % 360.0
        heading = None
        if s.dual_antenna:
            heading = true_heading + self.rng.normal(0, s.heading_sigma_deg)
        course = (true_heading + self.rng.normal(0, 1.0)) % 360.0
        altitude = 300.0 + lever[2] + self.rng.normal(0, 2 * sigma)
        return epoch_sentences(utc, lat, lon, altitude, quality, s, course, speed, heading, sigma)
