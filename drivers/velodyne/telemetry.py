"""The 512-byte position ("telemetry") packet from UDP port 8308.

Payload offsets (VLP-16 manual Rev D, Tables 9-3/9-4, less the 42-byte frame header):
ToH at 198, PPS status at 202, the NMEA sentence ($GPRMC or $GPGGA) at 206..333.
Board temperatures (187..189) exist on newer firmware only and read 0 on older units.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from treetraits.drivers.velodyne.models import POSITION_PACKET_SIZE
from treetraits.errors import ParseError

PPS_STATUS_NAMES = {0: "absent", 1: "synchronizing", 2: "locked", 3: "error"}
PPS_LOCKED = 2  # the ToH counts on UTC (PPS and NMEA both received)
_TOH = struct.Struct("<I")
_NMEA_START, _NMEA_END = 206, 334


@dataclass(frozen=True, slots=True)
class Telemetry:
    """One decoded position packet; `raw` keeps the bytes as received."""

    toh_us: int
    pps_status: int
    nmea: str | None  # the sentence without its CR LF, None when the field is empty
    temp_top_c: int
    temp_bottom_c: int
    t_host: int
    raw: bytes

    @property
    def pps(self) -> str:
        return PPS_STATUS_NAMES.get(self.pps_status, f"unknown({self.pps_status})")


def decode_telemetry(payload: bytes, t_host: int) -> Telemetry:
    """Decode one 512-byte position packet. Raises ParseError for the wrong size or an
    NMEA field that is not printable ASCII starting with '$'."""
    if len(payload) != POSITION_PACKET_SIZE:
        raise ParseError(
            f"position packet must be {POSITION_PACKET_SIZE} bytes, got {len(payload)}"
        )
    (toh,) = _TOH.unpack_from(payload, 198)
    field = bytes(payload[_NMEA_START:_NMEA_END]).split(b"\x00", 1)[0].rstrip(b"\r\n")
    nmea: str | None = None
    if field:
        if not field.startswith(b"$") or not all(32 <= c < 127 for c in field):
            raise ParseError(f"position packet NMEA field is not an NMEA sentence: {field[:40]!r}")
        nmea = field.decode("ascii")
    return Telemetry(
        toh_us=toh,
        pps_status=payload[202],
        nmea=nmea,
        temp_top_c=payload[187],
        temp_bottom_c=payload[188],
        t_host=t_host,
        raw=bytes(payload),
    )
