"""NMEA 0183 sentences: framing, checksum, and a pure parse into typed records.

`parse_sentence(raw)` takes one framed sentence (`$` ... `*hh` and its line end) and returns
a frozen record that keeps `raw` exactly as given, so a recorder can store what came. The
field layouts are data (`LAYOUTS`): one row per field, each row a name and a field kind that
converts the text (lat/lon kinds take the value and its hemisphere letter). Trailing fields
a receiver leaves out (older NMEA versions) are None; extra trailing fields are ignored.
Empty fields are None.

Decoded, from any talker (GP GN GL GA GB GQ BD GI ...): GGA, RMC, VTG, GST, HDT, THS, GSA,
ZDA. Every other sentence with a good checksum becomes an `OtherSentence` (address and raw
fields). Units: degrees (lat/lon signed: S and W negative), metres, knots and km/h as sent,
UTC time of day as int ns since midnight.
"""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from treetraits.errors import ParseError

# NMEA 0183: 82 characters from `$` to the line end inclusive. Real receivers exceed it
# (Trimble's 8-decimal GGA, SkyTraq's $PSTI, u-blox's $PUBX,03), so it is counted, not enforced.
NMEA_MAX_LENGTH = 82

# Printable ASCII except the delimiters `$`, `!` and `*`.
_BODY_CLASS = rb"[\x20\x22\x23\x25-\x29\x2b-\x7e]"
_FRAME = re.compile(rb"[$!](" + _BODY_CLASS + rb"*)\*([0-9A-Fa-f]{2})(?:\r\n|\r|\n)?")
_DECIMAL = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)")
_INTEGER = re.compile(r"[+-]?\d+")
_TIME = re.compile(r"(\d\d)(\d\d)(\d\d)(?:\.(\d{1,9}))?")
_DATE = re.compile(r"(\d\d)(\d\d)(\d\d)")
_DMM = re.compile(r"(\d+)(\d\d(?:\.\d*)?)")  # (d)ddmm.mmmm, any number of decimals
_KNOT_MPS = 1852.0 / 3600.0


def checksum(body: bytes) -> int:
    """The NMEA checksum: XOR of every byte between `$`/`!` and `*`."""
    value = 0
    for byte in body:
        value ^= byte
    return value


def sentence_type(address: str) -> str:
    """The type of a sentence from its address field: `GNGGA` -> `GGA`; a proprietary
    `P...` address is its own type (`PSTI`, `PASHR`)."""
    return address if address.startswith("P") else address[2:]


@dataclass(frozen=True, slots=True)
class Sentence:
    """One framed sentence as received: `raw` runs from `$` (or `!`) to the line end
    inclusive (`\\r\\n`, `\\n` or `\\r` as sent; none when the input ended right after the
    checksum). `checksum_ok` False: the checksum did not match; kept for the recorder,
    never decoded. `t_host`: host receive time, ns since the Unix epoch."""

    raw: bytes
    t_host: int
    checksum_ok: bool

    @property
    def address(self) -> str:
        """The address field (`GNGGA`, `PSTI`): the text up to the first comma."""
        end = self.raw.find(b"*")
        comma = self.raw.find(b",", 1, end)
        return self.raw[1 : end if comma < 0 else comma].decode("ascii", "replace")

    @property
    def kind(self) -> str:
        """The sentence type (`GGA`, `PSTI`), see `sentence_type`."""
        return sentence_type(self.address)


# ---------------------------------------------------------------------------- records


@dataclass(frozen=True, slots=True)
class NmeaRecord:
    """Fields every decoded sentence has: receive time, the raw bytes, the talker
    (`GP`, `GN`, ...; empty for proprietary and unknown addresses)."""

    t_host: int
    raw: bytes
    talker: str

    KIND: ClassVar[str] = ""

    @property
    def kind(self) -> str:
        return self.KIND


@dataclass(frozen=True, slots=True)
class GGA(NmeaRecord):
    """Fix data. `quality` as sent (0 invalid, 1 GPS, 2 DGPS/SBAS, 4 RTK fixed, 5 RTK
    float, 6 dead reckoning, ...); altitude above mean sea level; geoid separation =
    ellipsoid minus geoid (so ellipsoidal height = altitude + separation)."""

    KIND: ClassVar[str] = "GGA"
    tod_ns: int | None  # UTC time of day, ns since midnight
    lat: float | None
    lon: float | None
    quality: int | None
    satellites: int | None
    hdop: float | None
    altitude_m: float | None
    geoid_separation_m: float | None
    correction_age_s: float | None
    station_id: str | None


@dataclass(frozen=True, slots=True)
class RMC(NmeaRecord):
    """Recommended minimum. `status` A valid / V void; `mode` (NMEA 2.3+) A autonomous,
    D differential, E estimated, F RTK float, R RTK fixed, M manual, S simulator, N none;
    `magnetic_variation_deg` east positive; `nav_status` (NMEA 4.1+)."""

    KIND: ClassVar[str] = "RMC"
    tod_ns: int | None
    status: str | None
    lat: float | None
    lon: float | None
    speed_kn: float | None
    course_deg: float | None  # over ground, true
    date: dt.date | None
    magnetic_variation_deg: float | None
    mode: str | None
    nav_status: str | None

    @property
    def speed_mps(self) -> float | None:
        return None if self.speed_kn is None else self.speed_kn * _KNOT_MPS


@dataclass(frozen=True, slots=True)
class VTG(NmeaRecord):
    """Course and speed over ground. `mode` (NMEA 2.3+) as in RMC; N means not valid."""

    KIND: ClassVar[str] = "VTG"
    course_true_deg: float | None
    course_magnetic_deg: float | None
    speed_kn: float | None
    speed_kmh: float | None
    mode: str | None

    @property
    def speed_mps(self) -> float | None:
        if self.speed_kn is not None:
            return self.speed_kn * _KNOT_MPS
        return None if self.speed_kmh is None else self.speed_kmh / 3.6


@dataclass(frozen=True, slots=True)
class GST(NmeaRecord):
    """Pseudorange error statistics: 1-sigma errors in metres; the error ellipse's
    orientation in degrees from true north."""

    KIND: ClassVar[str] = "GST"
    tod_ns: int | None
    rms_m: float | None
    semi_major_m: float | None
    semi_minor_m: float | None
    orientation_deg: float | None
    std_lat_m: float | None
    std_lon_m: float | None
    std_alt_m: float | None


@dataclass(frozen=True, slots=True)
class HDT(NmeaRecord):
    """True heading, degrees clockwise from true north (empty: no heading)."""

    KIND: ClassVar[str] = "HDT"
    heading_deg: float | None


@dataclass(frozen=True, slots=True)
class THS(NmeaRecord):
    """True heading and status: `mode` A autonomous, E estimated (dead reckoning),
    M manual, S simulator, V not valid."""

    KIND: ClassVar[str] = "THS"
    heading_deg: float | None
    mode: str | None


@dataclass(frozen=True, slots=True)
class GSA(NmeaRecord):
    """DOP and active satellites. `op_mode` M manual / A automatic; `fix_mode` 1 none,
    2 2-D, 3 3-D; `system_id` (NMEA 4.1+) the constellation of this GSA."""

    KIND: ClassVar[str] = "GSA"
    op_mode: str | None
    fix_mode: int | None
    satellite_ids: tuple[int, ...]
    pdop: float | None
    hdop: float | None
    vdop: float | None
    system_id: int | None


@dataclass(frozen=True, slots=True)
class ZDA(NmeaRecord):
    """UTC time and date, and the local zone offset."""

    KIND: ClassVar[str] = "ZDA"
    tod_ns: int | None
    day: int | None
    month: int | None
    year: int | None
    zone_hours: int | None
    zone_minutes: int | None

    @property
    def date(self) -> dt.date | None:
        if self.day is None or self.month is None or self.year is None:
            return None
        try:
            return dt.date(self.year, self.month, self.day)
        except ValueError:
            return None


@dataclass(frozen=True, slots=True)
class OtherSentence(NmeaRecord):
    """A sentence with a good checksum of a type not decoded here (GSV, GLL, $PSTI, ...)."""

    address: str
    fields: tuple[str, ...]

    @property
    def kind(self) -> str:
        return sentence_type(self.address)


# ------------------------------------------------------------------------ field kinds


@dataclass(frozen=True, slots=True)
class FieldKind:
    """How to read `width` consecutive fields into one value (None when all are empty)."""

    name: str
    width: int
    convert: Callable[[Sequence[str]], Any]


def _one(convert: Callable[[str], Any]) -> Callable[[Sequence[str]], Any]:
    def read(values: Sequence[str]) -> Any:
        return convert(values[0]) if values[0] else None

    return read


def _decimal(text: str) -> float:
    if not _DECIMAL.fullmatch(text):
        raise ValueError(f"expected a decimal number, got {text!r}")
    return float(text)


def _integer(text: str) -> int:
    if not _INTEGER.fullmatch(text):
        raise ValueError(f"expected an integer, got {text!r}")
    return int(text)


def _hex_integer(text: str) -> int:
    try:
        return int(text, 16)
    except ValueError:
        raise ValueError(f"expected a hex digit, got {text!r}") from None


def _text(text: str) -> str:
    return text


def time_of_day(text: str) -> int:
    """hhmmss(.s...) -> ns since midnight (exact: no float)."""
    match = _TIME.fullmatch(text)
    if match is None:
        raise ValueError(f"expected a UTC time hhmmss.ss, got {text!r}")
    hh, mm, ss, fraction = match.groups()
    if int(hh) > 23 or int(mm) > 59 or int(ss) > 60:  # 60: a leap second
        raise ValueError(f"UTC time {text!r} out of range")
    nanos = int((fraction or "").ljust(9, "0"))
    return ((int(hh) * 60 + int(mm)) * 60 + int(ss)) * 1_000_000_000 + nanos


def _date(text: str) -> dt.date:
    """ddmmyy; two-digit years 80-99 are 1980-1999 (GPS began in 1980), else 20yy."""
    match = _DATE.fullmatch(text)
    if match is None:
        raise ValueError(f"expected a date ddmmyy, got {text!r}")
    day, month, year = (int(g) for g in match.groups())
    try:
        return dt.date(1900 + year if year >= 80 else 2000 + year, month, day)
    except ValueError:
        raise ValueError(f"date {text!r} is not a calendar date") from None


def _angle(limit: int, positive: str, negative: str) -> Callable[[Sequence[str]], Any]:
    """(d)ddmm.mmmm plus a hemisphere letter -> signed decimal degrees, full precision."""

    def read(values: Sequence[str]) -> float | None:
        text, hemisphere = values
        if not text:
            return None
        match = _DMM.fullmatch(text)
        if match is None:
            raise ValueError(f"expected (d)ddmm.mmmm, got {text!r}")
        minutes = float(match.group(2))
        degrees = int(match.group(1)) + minutes / 60.0
        if minutes >= 60.0 or degrees > limit:
            raise ValueError(f"{text!r} out of range")
        if hemisphere == positive:
            return degrees
        if hemisphere == negative:
            return -degrees
        raise ValueError(f"{text!r} needs a hemisphere {positive}/{negative}, got {hemisphere!r}")

    return read


def _variation(values: Sequence[str]) -> float | None:
    text, direction = values
    if not text:
        return None
    value = _decimal(text)
    if direction == "W":
        return -value
    if direction in ("E", ""):  # some receivers leave the letter out
        return value
    raise ValueError(f"magnetic variation direction E/W expected, got {direction!r}")


def _group(convert: Callable[[str], Any]) -> Callable[[Sequence[str]], Any]:
    def read(values: Sequence[str]) -> tuple:
        return tuple(convert(v) for v in values if v)

    return read


TIME = FieldKind("time", 1, _one(time_of_day))
DATE = FieldKind("date", 1, _one(_date))
LAT = FieldKind("lat", 2, _angle(90, "N", "S"))
LON = FieldKind("lon", 2, _angle(180, "E", "W"))
FLOAT = FieldKind("float", 1, _one(_decimal))
INT = FieldKind("int", 1, _one(_integer))
HEX = FieldKind("hex", 1, _one(_hex_integer))
CHAR = FieldKind("char", 1, _one(_text))
TEXT = FieldKind("text", 1, _one(_text))
VARIATION = FieldKind("variation", 2, _variation)
SATELLITES_12 = FieldKind("satellites", 12, _group(_integer))
SKIP = FieldKind("skip", 1, lambda values: None)  # unit letters (M, T, N, K)

# Sentence type -> (record class, fields in order). A None name is read and dropped.
LAYOUTS: dict[str, tuple[type[NmeaRecord], tuple[tuple[str | None, FieldKind], ...]]] = {
    "GGA": (
        GGA,
        (
            ("tod_ns", TIME),
            ("lat", LAT),
            ("lon", LON),
            ("quality", INT),
            ("satellites", INT),
            ("hdop", FLOAT),
            ("altitude_m", FLOAT),
            (None, SKIP),  # M
            ("geoid_separation_m", FLOAT),
            (None, SKIP),  # M
            ("correction_age_s", FLOAT),
            ("station_id", TEXT),
        ),
    ),
    "RMC": (
        RMC,
        (
            ("tod_ns", TIME),
            ("status", CHAR),
            ("lat", LAT),
            ("lon", LON),
            ("speed_kn", FLOAT),
            ("course_deg", FLOAT),
            ("date", DATE),
            ("magnetic_variation_deg", VARIATION),
            ("mode", CHAR),
            ("nav_status", CHAR),
        ),
    ),
    "VTG": (
        VTG,
        (
            ("course_true_deg", FLOAT),
            (None, SKIP),  # T
            ("course_magnetic_deg", FLOAT),
            (None, SKIP),  # M
            ("speed_kn", FLOAT),
            (None, SKIP),  # N
            ("speed_kmh", FLOAT),
            (None, SKIP),  # K
            ("mode", CHAR),
        ),
    ),
    "GST": (
        GST,
        (
            ("tod_ns", TIME),
            ("rms_m", FLOAT),
            ("semi_major_m", FLOAT),
            ("semi_minor_m", FLOAT),
            ("orientation_deg", FLOAT),
            ("std_lat_m", FLOAT),
            ("std_lon_m", FLOAT),
            ("std_alt_m", FLOAT),
        ),
    ),
    "HDT": (HDT, (("heading_deg", FLOAT), (None, SKIP))),
    "THS": (THS, (("heading_deg", FLOAT), ("mode", CHAR))),
    "GSA": (
        GSA,
        (
            ("op_mode", CHAR),
            ("fix_mode", INT),
            ("satellite_ids", SATELLITES_12),
            ("pdop", FLOAT),
            ("hdop", FLOAT),
            ("vdop", FLOAT),
            ("system_id", HEX),
        ),
    ),
    "ZDA": (
        ZDA,
        (
            ("tod_ns", TIME),
            ("day", INT),
            ("month", INT),
            ("year", INT),
            ("zone_hours", INT),
            ("zone_minutes", INT),
        ),
    ),
}


# ------------------------------------------------------------------------------ parse


def split_frame(raw: bytes) -> tuple[bytes, bool]:
    """The body (between `$`/`!` and `*`) of one framed sentence and whether its checksum
    matches. Raises ParseError when `raw` is not exactly one framed sentence."""
    match = _FRAME.fullmatch(raw)
    if match is None:
        raise ParseError(
            f"not one NMEA sentence: expected $<printable ASCII>*hh and an optional line "
            f"end, got {raw[:100]!r}"
        )
    body = match.group(1)
    return body, checksum(body) == int(match.group(2), 16)


def parse_sentence(raw: bytes, t_host: int = 0) -> NmeaRecord:
    """Decode one framed sentence into its record; `raw` is kept as given.

    Raises ParseError for a bad frame, a checksum mismatch, or a field that does not
    read as its layout says (e.g. letters in a number, minutes >= 60).
    """
    body, ok = split_frame(raw)
    if not ok:
        raise ParseError(
            f"checksum mismatch in {raw[:100]!r}: computed {checksum(body):02X}; "
            "the sentence was corrupted on the wire"
        )
    text = body.decode("ascii")
    address, *fields = text.split(",")
    kind = sentence_type(address)
    talker = address[:2] if len(address) == 5 and address[:2].isalpha() else ""
    layout = LAYOUTS.get(kind) if talker and not address.startswith("P") else None
    if layout is None:
        return OtherSentence(t_host, raw, talker, address, tuple(fields))
    record_type, rows = layout
    values: dict[str, Any] = {}
    index = 0
    for name, field_kind in rows:
        chunk = fields[index : index + field_kind.width]
        index += field_kind.width
        if len(chunk) < field_kind.width:
            chunk = [*chunk, *[""] * (field_kind.width - len(chunk))]  # older NMEA versions
        if name is None:
            continue
        try:
            values[name] = field_kind.convert(chunk)
        except ValueError as exc:
            raise ParseError(f"{address} field {name}: {exc} in {raw[:100]!r}") from None
    return record_type(t_host, raw, talker, **values)


def decode(sentence: Sentence) -> NmeaRecord | None:
    """The record of a framed sentence, or None when its checksum is bad (never used).
    Raises ParseError for a good checksum over fields that do not fit the layout."""
    if not sentence.checksum_ok:
        return None
    return parse_sentence(sentence.raw, sentence.t_host)
