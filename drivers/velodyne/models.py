"""VLP-16 family facts as data: angle tables, factory bytes and firing timing.

Sources: VLP-16 manual 63-9243 Rev D, Table 9-1 (angles, vertical corrections), Table 9-2
(factory bytes), section 9.3.1 (timing). See `docs/lidar.md` for the conventions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

DATA_PACKET_SIZE = 1206
POSITION_PACKET_SIZE = 512
BLOCKS_PER_PACKET = 12
RECORDS_PER_BLOCK = 32
LASERS = 16
BLOCK_FLAG = 0xEEFF  # bytes FF EE on the wire, read as a little-endian uint16

# Firing timing in integer nanoseconds (2.304 us per laser slot, 55.296 us per sequence).
LASER_SLOT_NS = 2_304
SEQUENCE_NS = 55_296
BLOCK_NS = 2 * SEQUENCE_NS
PACKET_NS_SINGLE = BLOCKS_PER_PACKET * BLOCK_NS  # 1327.104 us
PACKET_NS_DUAL = PACKET_NS_SINGLE // 2  # 663.552 us: both blocks of a pair are one firing
HOUR_NS = 3_600 * 1_000_000_000

DISTANCE_UNIT_M = 0.002

# Byte 1204: return mode.
RETURN_STRONGEST = 0x37
RETURN_LAST = 0x38
RETURN_DUAL = 0x39
RETURN_MODE_NAMES = {RETURN_STRONGEST: "strongest", RETURN_LAST: "last", RETURN_DUAL: "dual"}

# Byte 1205: product ID. 0x21 is the HDL-32E, but early VLP-16 firmware sends it too.
PRODUCT_HDL32E = 0x21
PRODUCT_VLP16 = 0x22
PRODUCT_PUCK_HIRES = 0x24
PRODUCT_NAMES = {
    0x21: "HDL-32E",
    0x22: "VLP-16",
    0x24: "Puck Hi-Res",
    0x28: "VLP-32C",
    0x31: "Velarray",
    0x63: "VLS-128",
    0xA1: "VLS-128",
}

# Point `return_type` values (docs/architecture.md): 0 strongest, 1 last.
RETURN_TYPE_STRONGEST = 0
RETURN_TYPE_LAST = 1


@dataclass(frozen=True, slots=True)
class LaserModel:
    """One sensor model's optics: per laser id (0..15, firing order) the elevation
    angle and the vertical offset of the beam origin."""

    name: str
    elevation_deg: tuple[float, ...]
    vertical_offset_mm: tuple[float, ...]
    # Ring of each laser id: the rank of its elevation, 0 = lowest beam.
    ring: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        ranks = np.argsort(np.argsort(self.elevation_deg, kind="stable"), kind="stable")
        object.__setattr__(self, "ring", ranks.astype(np.uint8))


VLP16 = LaserModel(
    name="VLP-16",
    elevation_deg=(-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15),
    vertical_offset_mm=(
        11.2,
        -0.7,
        9.7,
        -2.2,
        8.1,
        -3.7,
        6.6,
        -5.1,
        5.1,
        -6.6,
        3.7,
        -8.1,
        2.2,
        -9.7,
        0.7,
        -11.2,
    ),
)
# Same optics and same product byte as the VLP-16: packets cannot tell them apart.
PUCK_LITE = LaserModel("Puck LITE", VLP16.elevation_deg, VLP16.vertical_offset_mm)
PUCK_HIRES = LaserModel(
    name="Puck Hi-Res",
    elevation_deg=(
        -10.00,
        0.67,
        -8.67,
        2.00,
        -7.33,
        3.33,
        -6.00,
        4.67,
        -4.67,
        6.00,
        -3.33,
        7.33,
        -2.00,
        8.67,
        -0.67,
        10.00,
    ),
    vertical_offset_mm=(
        7.4,
        -0.9,
        6.5,
        -1.8,
        5.5,
        -2.7,
        4.6,
        -3.7,
        3.7,
        -4.6,
        2.7,
        -5.5,
        1.8,
        -6.5,
        0.9,
        -7.4,
    ),
)

# Names accepted by the `model` setting (case-insensitive); "auto" reads byte 1205.
MODELS_BY_NAME = {
    "vlp16": VLP16,
    "vlp-16": VLP16,
    "puck": VLP16,
    "pucklite": PUCK_LITE,
    "puck-lite": PUCK_LITE,
    "puckhires": PUCK_HIRES,
    "puck-hires": PUCK_HIRES,
    "hi-res": PUCK_HIRES,
}
MODEL_BY_PRODUCT = {PRODUCT_VLP16: VLP16, PRODUCT_PUCK_HIRES: PUCK_HIRES}


def model_by_name(name: str) -> LaserModel | None:
    """The model a user named, or None for "auto". Raises ValueError for an unknown name."""
    key = name.strip().lower()
    if key == "auto":
        return None
    try:
        return MODELS_BY_NAME[key]
    except KeyError:
        known = ", ".join(["auto", "vlp16", "puck-lite", "puck-hires"])
        raise ValueError(f"unknown LiDAR model {name!r}; expected one of: {known}") from None


def packet_period_ns(return_mode: int) -> int:
    """Device time between consecutive data packets in this return mode."""
    return PACKET_NS_DUAL if return_mode == RETURN_DUAL else PACKET_NS_SINGLE


_TIMING_TOLERANCE_US = 30
HDL32E_PACKET_US = 552.96  # 12 blocks of one 46.08 us firing cycle


def looks_like_vlp16_timing(toh_step_us: float) -> bool:
    """True when a ToH step between packets fits a 16-laser sensor (1327 us single,
    664 us dual): settles the ambiguous product byte 0x21 for a VLP-16."""
    periods = (PACKET_NS_SINGLE / 1000, PACKET_NS_DUAL / 1000)
    return any(abs(toh_step_us - p) < _TIMING_TOLERANCE_US for p in periods)


def looks_like_hdl32e_timing(toh_step_us: float) -> bool:
    """True when a ToH step fits an HDL-32E (553 us): byte 0x21 then means what it says."""
    return abs(toh_step_us - HDL32E_PACKET_US) < _TIMING_TOLERANCE_US
