"""NMEA 0183 sentences built from numbers: for the twin's receiver (`sim/gnss.py`) and for
fixes that arrive as numbers rather than sentences (a ROS `NavSatFix`, `rosbag_import`),
so that both reach the pipeline through the same NMEA path as a real receiver's bytes."""

from __future__ import annotations

import datetime as dt
import math

from treetraits.drivers.gnss.sentences import checksum

# RMC's mode letter (NMEA 2.3) for each GGA quality.
RMC_MODE = {4: "R", 5: "F", 2: "D", 1: "A"}


def sentence(body: str) -> bytes:
    """`$body*hh\\r\\n` with the XOR checksum."""
    return f"${body}*{checksum(body.encode('ascii')):02X}\r\n".encode("ascii")


def lat_field(lat: float) -> tuple[str, str]:
    hemisphere = "N" if lat >= 0 else "S"
    lat = abs(lat)
    degrees = int(lat)
    return f"{degrees:02d}{(lat - degrees) * 60:011.8f}", hemisphere


def lon_field(lon: float) -> tuple[str, str]:
    hemisphere = "E" if lon >= 0 else "W"
    lon = abs(lon)
    degrees = int(lon)
    return f"{degrees:03d}{(lon - degrees) * 60:011.8f}", hemisphere


KNOT_MPS = 1852.0 / 3600.0


def _number(value: float | None, digits: int) -> str:
    """A field, empty when the value is unknown (None or not finite)."""
    return "" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def fix_sentences(
    utc_ns: int,
    lat: float,
    lon: float,
    altitude_m: float,
    quality: int,
    *,
    geoid_separation_m: float = 0.0,
    std_east_m: float | None = None,
    std_north_m: float | None = None,
    std_up_m: float | None = None,
    talker: str = "GN",
    course_deg: float | None = None,
    speed_mps: float | None = None,
) -> list[bytes]:
    """One epoch as GGA, RMC (for the date) and, when a standard deviation is known, GST,
    at `utc_ns` rounded to the millisecond. Satellites and HDOP are left empty (unknown),
    speed and course too unless given (RMC: knots, degrees from true north). A non-finite
    lat/lon leaves the position empty. GST's RMS and error
    ellipse are left empty: the localiser reads only its per-axis sigmas."""
    utc_ns = round(utc_ns / 1e6) * 1_000_000
    utc = dt.datetime.fromtimestamp(utc_ns // 1_000_000_000, dt.timezone.utc)
    hhmmss = f"{utc:%H%M%S}.{utc_ns // 1_000_000 % 1000:03d}"
    if math.isfinite(lat) and math.isfinite(lon):
        lat_text, ns = lat_field(lat)
        lon_text, ew = lon_field(lon)
    else:
        lat_text = ns = lon_text = ew = ""
        quality = 0
    position = f"{lat_text},{ns},{lon_text},{ew}"
    out = [
        sentence(
            f"{talker}GGA,{hhmmss},{position},{quality},,,{_number(altitude_m, 3)},M,"
            f"{geoid_separation_m:.3f},M,,"
        ),
        sentence(
            f"{talker}RMC,{hhmmss},{'A' if quality else 'V'},{position},"
            f"{_number(None if speed_mps is None else speed_mps / KNOT_MPS, 3)},"
            f"{_number(course_deg, 2)},{utc:%d%m%y},,,"
            f"{RMC_MODE.get(quality, 'N')}"
        ),
    ]
    if quality and (std_east_m is not None or std_north_m is not None):
        out.append(
            sentence(
                f"{talker}GST,{hhmmss},,,,,{_number(std_north_m, 3)},"
                f"{_number(std_east_m, 3)},{_number(std_up_m, 3)}"
            )
        )
    return out
