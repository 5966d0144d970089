"""VLP-16 data packets from arrays (the inverse of `packet.view_packets`) and position
packets, for the digital twin and for tests. Vectorised: one structured array filled
field by field."""

from __future__ import annotations

import struct

import numpy as np

from treetraits.drivers.velodyne import models as m
from treetraits.drivers.velodyne.packet import PACKET_DTYPE


def encode_packets(
    azimuth_centideg: np.ndarray,
    distance_2mm: np.ndarray,
    reflectivity: np.ndarray,
    toh_us: np.ndarray,
    return_mode: int = m.RETURN_STRONGEST,
    product: int = m.PRODUCT_VLP16,
) -> bytes:
    """P packets, back to back (P x 1206 bytes).

    `azimuth_centideg`: (P, 12) block azimuths, 0..35999; `distance_2mm`: (P, 12, 32)
    distances in 2 mm units (0 = no return); `reflectivity`: (P, 12, 32); `toh_us`: (P,)
    microseconds past the hour of each packet's first firing. In dual mode the caller
    fills both blocks of each pair (even: last return, odd: strongest) with one azimuth.
    """
    azimuth = np.asarray(azimuth_centideg)
    count = azimuth.shape[0]
    if azimuth.shape != (count, m.BLOCKS_PER_PACKET):
        raise ValueError(f"azimuth must be (P, 12), got {azimuth.shape}")
    shape = (count, m.BLOCKS_PER_PACKET, m.RECORDS_PER_BLOCK)
    if np.shape(distance_2mm) != shape or np.shape(reflectivity) != shape:
        raise ValueError(f"distance and reflectivity must be {shape}")
    if azimuth.min(initial=0) < 0 or azimuth.max(initial=0) >= 36000:
        raise ValueError("azimuth must be in 0..35999 centidegrees")
    if return_mode not in m.RETURN_MODE_NAMES:
        raise ValueError(f"unknown return mode 0x{return_mode:02x}")
    packets = np.zeros(count, dtype=PACKET_DTYPE)
    blocks = packets["blocks"]
    blocks["flag"] = m.BLOCK_FLAG
    blocks["azimuth"] = azimuth
    blocks["records"]["distance"] = distance_2mm
    blocks["records"]["reflectivity"] = reflectivity
    packets["toh"] = np.asarray(toh_us) % (m.HOUR_NS // 1000)
    packets["return_mode"] = return_mode
    packets["product"] = product
    return packets.tobytes()


def encode_position(toh_us: int, pps_status: int, nmea: str | None) -> bytes:
    """One 512-byte position packet (port 8308): the ToH at 198, the PPS status at 202 and
    the NMEA sentence (with its CR LF) at 206..333, every other byte 0 (as a sensor without
    temperature fields sends it). The inverse of `telemetry.decode_telemetry`."""
    payload = bytearray(m.POSITION_PACKET_SIZE)
    struct.pack_into("<I", payload, 198, toh_us % (m.HOUR_NS // 1000))
    payload[202] = pps_status
    if nmea:
        text = (nmea + "\r\n").encode("ascii")
        if len(text) > 334 - 206:
            raise ValueError(f"NMEA sentence too long for a position packet: {len(text)} bytes")
        payload[206 : 206 + len(text)] = text
    return bytes(payload)
