"""The VLP-16 batcher, decoder and telemetry parser on damaged real packets.

Every stream starts from real captures (mostly the einride raw file: 1000 back-to-back
single-return payloads, `t_host` = ToH x 1000 ns) and is damaged on purpose: packets
lost, repeated, reordered, delivered late, malformed, re-timed, re-labelled. Expected
values come from the undamaged decode, from the reference JSONs, from the VLP-16 user
manual (Velodyne 63-9243) or from arithmetic on the packet list, never from
the code under test on the same damaged input.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import struct

import numpy as np
import pytest

from tests.helpers.captures import VLP16_DIR, decode_file, reference
from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne.batcher import BatcherStats, ScanBatcher
from treetraits.drivers.velodyne.sources import LidarPacket, open_source
from treetraits.drivers.velodyne.telemetry import decode_telemetry
from treetraits.errors import ParseError

EINRIDE = "einride_vlp16_strongest_1000pkts.bin"
HDL32E = VLP16_DIR / "secondary" / "hdl32e_monterey_gprmc_short.pcap"
VLP32C = VLP16_DIR / "secondary" / "nebula_vlp32c_10hz.pcap"
HDL32E_SENTENCE = "$GPRMC,214616,A,3708.3443,N,12139.4299,W,009.7,040.6,111212,013.8,E,D*0E"

HOUR_US = 3_600_000_000
HOUR_NS = HOUR_US * 1000
# The manual's timing: last firing of a single-return packet (block 11, 2nd sequence, laser 15)
# is 1306.368 us after the packet's ToH; the next packet comes >= 1327 us later.
LAST_FIRING_NS = 11 * 110_592 + 55_296 + 15 * 2_304
# Manual Table 9-1, by ring (rank of the elevation, 0 = lowest): elevation in degrees and the
# vertical offset of the beam origin in mm.
VLP16_ELEVATION_BY_RING = [-15 + 2 * ring for ring in range(16)]
VLP16_OFFSET_MM_BY_RING = [11.2, 9.7, 8.1, 6.6, 5.1, 3.7, 2.2, 0.7]
VLP16_OFFSET_MM_BY_RING += [-v for v in reversed(VLP16_OFFSET_MM_BY_RING)]
HIRES_ELEVATION_BY_RING = [-10.00, -8.67, -7.33, -6.00, -4.67, -3.33, -2.00, -0.67]
HIRES_ELEVATION_BY_RING += [-v for v in reversed(HIRES_ELEVATION_BY_RING)]
HIRES_OFFSET_MM_BY_RING = [7.4, 6.5, 5.5, 4.6, 3.7, 2.7, 1.8, 0.9]
HIRES_OFFSET_MM_BY_RING += [-v for v in reversed(HIRES_OFFSET_MM_BY_RING)]

Stream = list[tuple[bytes, int]]


# --- packet bytes -------------------------------------------------------------------


@functools.cache
def einride() -> tuple[bytes, ...]:
    data = (VLP16_DIR / EINRIDE).read_bytes()
    return tuple(data[i : i + 1206] for i in range(0, len(data), 1206))


def toh_of(payload: bytes) -> int:
    return struct.unpack_from("<I", payload, 1200)[0]


def last_block_azimuth(payload: bytes) -> int:
    return struct.unpack_from("<H", payload, 1100 + 2)[0]


def patched(payload: bytes, offset: int, new: bytes) -> bytes:
    return payload[:offset] + new + payload[offset + len(new) :]


def with_toh(payload: bytes, toh_us: int) -> bytes:
    return patched(payload, 1200, struct.pack("<I", toh_us))


def stream_of(packets) -> Stream:
    """The raw file's convention: the host clock is the device clock."""
    return [(p, toh_of(p) * 1000) for p in packets]


def capture_packets(path) -> list[LidarPacket]:
    source = open_source(path)
    try:
        return list(source)
    finally:
        source.close()


def json_facts(path) -> dict:
    """The reference facts of a secondary capture (a different layout from VLP-16's)."""
    return json.loads(path.with_name(path.name + ".reference.json").read_text())


def data_stream(path) -> Stream:
    return [(p.payload, p.t_host) for p in capture_packets(path) if p.is_data]


# --- running the batcher ------------------------------------------------------------


def run(stream: Stream, **options) -> tuple[list[Scan], BatcherStats]:
    """Push a whole stream, flush, and check the bookkeeping every run must satisfy."""
    batcher = ScanBatcher(**options)
    scans = [s for s in (batcher.push(p, t) for p, t in stream) if s is not None]
    last = batcher.flush()
    if last is not None:
        scans.append(last)
    stats = batcher.stats
    accounted = (
        sum(s.packets for s in scans)
        + stats.malformed
        + stats.unsupported_model
        + stats.duplicates
        + stats.late
    )
    assert accounted == len(stream) == stats.data_packets
    assert stats.scans == len(scans)
    return scans, stats


@functools.cache
def undamaged() -> tuple[Scan, ...]:
    scans, stats = run(stream_of(einride()))
    assert stats.lost == stats.malformed == stats.duplicates == 0
    return tuple(scans)


def scan_ranges(packets, cut_centideg: int = 0) -> list[range]:
    """Packet indices of each scan, by arithmetic on the last-block azimuths: a scan
    ends with (and includes) the first packet whose last block has crossed the cut."""
    coverage = [(last_block_azimuth(p) - cut_centideg) % 36000 for p in packets]
    ends = [i for i in range(1, len(packets)) if coverage[i] < coverage[i - 1]]
    bounds = [0, *(e + 1 for e in ends), len(packets)]
    return [range(a, b) for a, b in itertools.pairwise(bounds) if b > a]


def fired_during(points: np.ndarray, packets) -> np.ndarray:
    """Mask of the points fired by these packets (host clock = device clock)."""
    mask = np.zeros(len(points), dtype=bool)
    for p in packets:
        t0 = toh_of(p) * 1000
        mask |= (points["t"] >= t0) & (points["t"] <= t0 + LAST_FIRING_NS)
    return mask


def same_points(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.tobytes() == b.tobytes()


def point_rows(points: np.ndarray) -> set[bytes]:
    return {row.tobytes() for row in points}


def assert_scans_equal(got: Scan, want: Scan) -> None:
    assert same_points(got.points, want.points)
    assert (got.t_start, got.t_end, got.complete, got.packets, got.lost_packets) == (
        want.t_start,
        want.t_end,
        want.complete,
        want.packets,
        want.lost_packets,
    )


def middle_of_scan(scan_index: int, count: int = 1) -> range:
    """`count` packet indices from the middle of an undamaged scan (never its cut packet)."""
    r = scan_ranges(einride())[scan_index]
    start = r.start + len(r) // 2 - count // 2
    assert r.start < start and start + count < r.stop - 1
    return range(start, start + count)


def test_undamaged_decode_matches_arithmetic_and_reference():
    """The baseline every other test compares with."""
    cut0 = reference(EINRIDE)["velodyne_decoder"]["cut_angle_0"]
    ranges = scan_ranges(einride())
    scans = undamaged()
    assert [s.packets for s in scans] == [len(r) for r in ranges]
    assert [len(s.points) for s in scans] == cut0["points_per_scan_all"]
    assert [s.t_start for s in scans] == [toh_of(einride()[r.start]) * 1000 for r in ranges]
    assert [s.complete for s in scans] == [False] + [True] * (len(ranges) - 2) + [False]


# --- lost, duplicated, reordered and late packets -----------------------------------


@pytest.mark.parametrize(
    "drops",
    [{5: 1}, {5: 4}, {8: 12}, {3: 1, 9: 6}],
    ids=["single", "run-of-4", "run-of-12", "single-and-run-elsewhere"],
)
def test_lost_packets_are_counted_and_only_their_points_are_missing(drops):
    packets = list(einride())
    dropped = {scan: middle_of_scan(scan, k) for scan, k in drops.items()}
    gone = {i for r in dropped.values() for i in r}
    scans, stats = run(stream_of(p for i, p in enumerate(packets) if i not in gone))

    assert stats.lost == len(gone)
    assert len(scans) == len(undamaged())
    for index, (got, want) in enumerate(zip(scans, undamaged(), strict=True)):
        if index not in dropped:
            assert_scans_equal(got, want)
            continue
        assert got.lost_packets == len(dropped[index])
        assert got.packets == want.packets - len(dropped[index])
        assert point_rows(got.points) <= point_rows(want.points)
        missing = fired_during(want.points, [packets[i] for i in dropped[index]])
        assert missing.any()
        assert same_points(got.points, want.points[~missing])


def _duplicate(packets: list[bytes], index: int, later_by: int) -> list[bytes]:
    out = list(packets)
    out.insert(index + 1 + later_by, packets[index])
    return out


@pytest.mark.parametrize("later_by", [0, 1, 10], ids=["immediate", "after-1", "after-10"])
def test_duplicated_packets_are_counted_and_scans_unchanged(later_by):
    packets = list(einride())
    first, second = middle_of_scan(4)[0], middle_of_scan(10)[0]
    damaged = _duplicate(_duplicate(packets, second, later_by), first, later_by)
    scans, stats = run(stream_of(damaged))

    assert stats.duplicates == 2
    assert stats.lost == stats.out_of_order == stats.late == stats.malformed == 0
    assert len(scans) == len(undamaged())
    for got, want in zip(scans, undamaged(), strict=True):
        assert_scans_equal(got, want)


@pytest.mark.parametrize("delay", [1, 2, 5], ids=["swap-neighbours", "by-2", "by-5"])
def test_reordered_packets_are_put_back_in_place(delay):
    packets = list(einride())
    i = middle_of_scan(6)[0]
    damaged = list(packets)
    damaged.insert(i + delay, damaged.pop(i))  # packet i arrives `delay` packets late
    scans, stats = run(stream_of(damaged))

    assert stats.out_of_order == 1
    assert stats.lost == 0  # counted missing when the gap was seen, then found
    assert stats.duplicates == stats.late == stats.malformed == 0
    assert len(scans) == len(undamaged())
    for got, want in zip(scans, undamaged(), strict=True):
        assert_scans_equal(got, want)


def test_packet_arriving_after_its_scan_closed_is_late_and_dropped():
    packets = list(einride())
    i = middle_of_scan(3)[0]
    next_scan = scan_ranges(packets)[4]
    damaged = list(packets)
    damaged.insert(next_scan.start + 3, damaged[i])  # 3 packets into the next scan
    del damaged[i]
    scans, stats = run(stream_of(damaged))

    assert stats.late == 1
    assert stats.out_of_order == stats.duplicates == stats.malformed == 0
    assert len(scans) == len(undamaged())
    for index, (got, want) in enumerate(zip(scans, undamaged(), strict=True)):
        if index != 3:
            assert_scans_equal(got, want)
            continue
        assert got.lost_packets == 1 and got.packets == want.packets - 1
        missing = fired_during(want.points, [packets[i]])
        assert missing.any()
        assert same_points(got.points, want.points[~missing])
    assert stats.lost == sum(s.lost_packets for s in scans) == 1


# --- malformed packets --------------------------------------------------------------


def _block_flag(payload: bytes, block: int, flag: bytes) -> bytes:
    return patched(payload, 100 * block, flag)


def _block_azimuth(payload: bytes, block: int, centideg: int) -> bytes:
    return patched(payload, 100 * block + 2, struct.pack("<H", centideg))


DAMAGE = {
    "truncated-1205": lambda p: p[:1205],
    "oversized-1207": lambda p: p + b"\x00",
    "wrong-flag-block-5": lambda p: _block_flag(p, 5, b"\xff\xdd"),
    "wrong-flag-last-block": lambda p: _block_flag(p, 11, b"\x00\x00"),
    "azimuth-36001-block-5": lambda p: _block_azimuth(p, 5, 36001),
    "azimuth-65535-last-block": lambda p: _block_azimuth(p, 11, 65535),
    "unknown-return-mode": lambda p: patched(p, 1204, b"\x40"),
    "random-1206-bytes": lambda p: np.random.default_rng(1206).bytes(1206),
}


@pytest.mark.parametrize("kind", list(DAMAGE))
def test_malformed_packet_in_place_is_counted_and_its_neighbours_decoded(kind):
    packets = list(einride())
    i = middle_of_scan(6)[0]
    damaged = list(packets)
    damaged[i] = DAMAGE[kind](packets[i])
    # The host clock comes from the undamaged packets: the damage may hit the ToH.
    scans, stats = run([(d, t) for d, (_, t) in zip(damaged, stream_of(packets), strict=True)])

    assert stats.malformed == 1
    assert stats.duplicates == stats.late == stats.unsupported_model == 0
    assert len(scans) == len(undamaged())
    for index, (got, want) in enumerate(zip(scans, undamaged(), strict=True)):
        if index != 6:
            assert_scans_equal(got, want)
            continue
        assert got.packets == want.packets - 1
        missing = fired_during(want.points, [packets[i]])
        assert same_points(got.points, want.points[~missing])


def test_malformed_packets_between_good_ones_leave_every_scan_intact():
    """Each damaged packet is an extra one, re-timed between two real packets, so that
    wherever it is checked (at push or at decode) nothing else may change."""
    packets = list(einride())
    ranges = scan_ranges(packets)
    stream = stream_of(packets)
    # Insert from the back so earlier indices stay valid.
    for n, kind in reversed(list(enumerate(DAMAGE))):
        i = ranges[1 + n].start + 20
        extra = DAMAGE[kind](with_toh(packets[i], toh_of(packets[i]) + 600))
        stream.insert(i + 1, (extra, (toh_of(packets[i]) + 600) * 1000))
    scans, stats = run(stream)

    assert stats.malformed == len(DAMAGE)
    assert stats.lost == stats.duplicates == stats.late == stats.unsupported_model == 0
    assert len(scans) == len(undamaged())
    for got, want in zip(scans, undamaged(), strict=True):
        assert_scans_equal(got, want)


# --- device time --------------------------------------------------------------------


def test_toh_rolling_over_the_hour_is_seamless():
    packets = list(einride())
    roll = middle_of_scan(5)[0]  # first packet after the top of the hour
    base = toh_of(packets[roll]) - 700  # it lands 700 us past the hour
    hour0 = 480_000  # an hour of 2024, counted from the epoch
    latency_ns = 250_000
    stream = []
    for p in packets:
        unwrapped = toh_of(p) - base + HOUR_US  # us since the start of hour0 (may pass 1 h)
        stream.append(
            (with_toh(p, unwrapped % HOUR_US), hour0 * HOUR_NS + unwrapped * 1000 + latency_ns)
        )
    assert toh_of(stream[roll - 1][0]) > HOUR_US - 1327 and toh_of(stream[roll][0]) == 700
    scans, stats = run(stream)

    assert stats.time_jumps == stats.lost == stats.malformed == stats.late == 0
    assert len(scans) == len(undamaged())
    delta_ns = (hour0 * HOUR_US + HOUR_US - base) * 1000  # how far device time moved
    for got, want in zip(scans, undamaged(), strict=True):
        assert got.complete == want.complete and got.packets == want.packets
        assert np.array_equal(got.points["t"], want.points["t"] + delta_ns)
        for name in ("x", "y", "z", "azimuth", "intensity", "ring"):
            assert np.array_equal(got.points[name], want.points[name])
    t = np.concatenate([s.points["t"] for s in scans])
    steps = np.diff(t)
    assert (steps > 0).all()
    assert steps.max() < 10_000_000  # no 1 h step anywhere: at most a few ms of no returns


@pytest.mark.parametrize("jump_s", [-420, 600], ids=["back-7-min", "forward-10-min"])
def test_device_clock_jump_closes_the_open_scan_as_partial(jump_s):
    packets = list(einride())
    j = middle_of_scan(6)[0]  # the sensor restarts here; the host clock carries on
    stream = [
        (with_toh(p, toh_of(p) + jump_s * 1_000_000) if i >= j else p, toh_of(p) * 1000)
        for i, p in enumerate(packets)
    ]
    scans, stats = run(stream)

    assert stats.time_jumps == 1
    assert stats.lost == stats.late == stats.duplicates == 0
    before = undamaged()
    assert len(scans) == len(before) + 1
    for got, want in zip(scans[:6], before[:6], strict=True):
        assert_scans_equal(got, want)
    r = scan_ranges(packets)[6]
    cut_short, restarted = scans[6], scans[7]
    assert not cut_short.complete and cut_short.packets == j - r.start
    assert not restarted.complete and restarted.packets == r.stop - j
    first_part = fired_during(before[6].points, packets[r.start : j])
    assert same_points(cut_short.points, before[6].points[first_part])
    assert [s.complete for s in scans[8:]] == [s.complete for s in before[7:]]
    for got, want in zip(scans[8:], before[7:], strict=True):
        assert np.array_equal(got.points["t"], want.points["t"] + jump_s * 1_000_000_000)


# --- sensor model -------------------------------------------------------------------


def test_hdl32e_capture_is_unsupported_under_auto():
    stream = data_stream(HDL32E)
    facts = json_facts(HDL32E)
    assert len(stream) == facts["data_packets"]
    scans, stats = run(stream, model="auto")
    assert scans == []
    assert stats.unsupported_model == facts["data_packets"]
    assert stats.malformed == 0


def test_hdl32e_capture_decodes_when_the_model_is_forced():
    stream = data_stream(HDL32E)
    scans, stats = run(stream, model="vlp16")
    assert stats.unsupported_model == stats.malformed == 0
    assert sum(s.packets for s in scans) == len(stream)
    assert all(s.model == "VLP-16" and len(s.points) > 0 for s in scans)


def test_vlp32c_capture_is_unsupported():
    stream = data_stream(VLP32C)
    scans, stats = run(stream)
    assert scans == []
    assert stats.unsupported_model == json_facts(VLP32C)["data_packets"] == len(stream)


@pytest.mark.parametrize(
    "name",
    ["veloview_vlp16_20hz_strongest.pcap", "lidarutils_vlp16_strongest_0x21_with_position.pcap"],
)
def test_early_firmware_vlp16_with_hdl32e_byte_decodes_as_vlp16(name):
    ref = reference(name)
    assert list(ref["raw"]["factory_bytes"]) == ["0x37/0x21"]
    cut0 = ref["velodyne_decoder"]["cut_angle_0"]
    scans, reader = decode_file(VLP16_DIR / name, model="auto")
    assert reader.batcher.stats.unsupported_model == 0
    assert len(scans) == cut0["scans_emitted"]
    assert sum(len(s.points) for s in scans) == cut0["total_points_all_scans"]
    assert {s.model for s in scans} == {"VLP-16"}


def returns_in(payload: bytes) -> int:
    """Records with a return (distance != 0) in a data packet, read from the bytes."""
    offsets = (100 * block + 4 + 3 * j for block in range(12) for j in range(32))
    return sum(1 for o in offsets if payload[o] or payload[o + 1])


START_DAMAGE = {
    "second-lost": lambda s: s[:1] + s[2:],
    "first-repeated": lambda s: s[:1] + s,
    "second-and-third-swapped": lambda s: [s[0], s[2], s[1], *s[3:]],
}


@pytest.mark.parametrize("damage", list(START_DAMAGE))
def test_early_firmware_vlp16_survives_damage_at_the_start(damage):
    """Byte 0x21 is settled by packet timing; one lost, repeated or reordered packet
    right at the start must not make the whole stream look like an HDL-32E."""
    name = "veloview_vlp16_20hz_strongest.pcap"
    stream = data_stream(VLP16_DIR / name)
    scans, stats = run(START_DAMAGE[damage](stream))
    assert stats.unsupported_model == 0
    expected = reference(name)["velodyne_decoder"]["cut_angle_0"]["total_points_all_scans"]
    if damage == "second-lost":
        expected -= returns_in(stream[1][0])
        assert stats.lost == 1
    assert sum(len(s.points) for s in scans) == expected
    assert {s.model for s in scans} == {"VLP-16"}


@pytest.mark.parametrize("damage", list(START_DAMAGE))
def test_hdl32e_stays_refused_with_damage_at_the_start(damage):
    stream = START_DAMAGE[damage](data_stream(HDL32E))
    scans, stats = run(stream)
    assert scans == []
    assert stats.unsupported_model + stats.duplicates + stats.late == len(stream)


def _elevation_deg(points: np.ndarray, offset_mm_by_ring) -> np.ndarray:
    offset = np.asarray(offset_mm_by_ring)[points["ring"]] / 1000
    z = points["z"].astype(np.float64) - offset
    return np.degrees(np.arctan2(z, np.hypot(points["x"], points["y"])))


@pytest.mark.parametrize(
    ("product", "elevation_by_ring", "offset_by_ring", "model"),
    [
        (None, VLP16_ELEVATION_BY_RING, VLP16_OFFSET_MM_BY_RING, "VLP-16"),
        (0x24, HIRES_ELEVATION_BY_RING, HIRES_OFFSET_MM_BY_RING, "Puck Hi-Res"),
    ],
    ids=["vlp16-as-sent", "patched-0x24-puck-hires"],
)
def test_each_point_lies_on_its_rings_elevation(product, elevation_by_ring, offset_by_ring, model):
    packets = einride()
    if product is not None:
        packets = [patched(p, 1205, bytes([product])) for p in packets]
    scans, stats = run(stream_of(packets))
    assert stats.unsupported_model == stats.malformed == 0
    assert {s.model for s in scans} == {model}
    points = np.concatenate([s.points for s in scans])
    assert len(points) == reference(EINRIDE)["raw"]["nonzero_returns_total"]
    expected = np.asarray(elevation_by_ring)[points["ring"]]
    error = np.abs(_elevation_deg(points, offset_by_ring) - expected)
    assert error.max() < 0.01  # the table is rounded to 0.01 deg


def test_last_return_byte_marks_every_point_last():
    scans, stats = run(stream_of(patched(p, 1204, b"\x38") for p in einride()))
    assert stats.malformed == 0
    assert {s.return_mode for s in scans} == {"last"}
    assert len(scans) == len(undamaged())
    for got, want in zip(scans, undamaged(), strict=True):
        assert (got.points["return_type"] == 1).all()
        for name in want.points.dtype.names:
            if name != "return_type":
                assert np.array_equal(got.points[name], want.points[name])


# --- cut angle ----------------------------------------------------------------------


def test_cut_angle_180_moves_the_seams_not_the_points():
    packets = einride()
    index_of_toh = {toh_of(p) * 1000: i for i, p in enumerate(packets)}
    azimuth = [last_block_azimuth(p) for p in packets]
    scans, stats = run(stream_of(packets), cut_angle_deg=180)

    assert stats.lost == stats.malformed == 0
    assert sum(len(s.points) for s in scans) == reference(EINRIDE)["raw"]["nonzero_returns_total"]
    assert [s.packets for s in scans] == [len(r) for r in scan_ranges(packets, 18000)]
    complete = [s for s in scans if s.complete]
    assert len(complete) >= 10
    for scan in complete:
        first = index_of_toh[scan.t_start]
        last = index_of_toh[scan.t_end - LAST_FIRING_NS]
        # It ends with the packet whose last block crossed 180 deg...
        sweep = azimuth[last] - azimuth[last - 1]
        assert azimuth[last - 1] < 18000 <= azimuth[last] < 18000 + sweep
        # ...and began right after the previous crossing: its first packet's last block
        # lies past 180 deg by less than that packet's sweep plus one more.
        before = first - 1
        assert azimuth[before - 1] < 18000 <= azimuth[before]
        sweep = azimuth[first] - azimuth[before]
        assert 18000 < azimuth[first] < 18000 + 2 * sweep


@pytest.mark.parametrize("angle", [360, -1, 360.5, -0.01, math.nan])
def test_invalid_cut_angle_is_refused(angle):
    with pytest.raises(ValueError, match="cut angle"):
        ScanBatcher(cut_angle_deg=angle)


# --- telemetry ----------------------------------------------------------------------


def test_hdl32e_position_packets_carry_the_real_gprmc_sentence():
    position = [p for p in capture_packets(HDL32E) if not p.is_data]
    assert len(position) == json_facts(HDL32E)["position_packets"]
    for packet in position:
        telemetry = decode_telemetry(packet.payload, packet.t_host)
        assert telemetry.nmea == HDL32E_SENTENCE
        assert telemetry.pps_status == 0 and telemetry.pps == "absent"
        assert telemetry.toh_us == struct.unpack_from("<I", packet.payload, 198)[0]
        assert telemetry.raw == packet.payload
    assert (
        decode_telemetry(position[0].payload, 0).toh_us
        == json_facts(HDL32E)["position_toh_first_us"]
    )


def test_vlp16_position_packets_without_gps_have_no_sentence():
    name = "veloview_vlp16_20hz_strongest.pcap"
    position = [p for p in capture_packets(VLP16_DIR / name) if not p.is_data]
    assert len(position) == reference(name)["raw"]["position_packets"]
    decoded = [decode_telemetry(p.payload, p.t_host) for p in position]
    assert all(t.nmea is None and t.pps_status == 0 for t in decoded)
    toh = np.array([t.toh_us for t in decoded])
    assert (np.diff(toh) > 0).all()


@pytest.mark.parametrize("size", [0, 511, 513, 1206])
def test_position_packet_of_the_wrong_size_is_a_parse_error(size):
    payload = (capture_packets(HDL32E)[0].payload * 3)[:size]
    with pytest.raises(ParseError, match="512"):
        decode_telemetry(payload, 0)


@pytest.mark.parametrize(
    "field",
    [b"GPRMC,214616,A*0E\r\n", b"$GPRMC,\x01\x02\x03\r\n", b"\xff\xfe$GPRMC", b"$GPRMC,\xc3\xa9"],
    ids=["no-dollar", "control-bytes", "binary-prefix", "non-ascii"],
)
def test_garbage_nmea_field_is_a_parse_error(field):
    real = next(p for p in capture_packets(HDL32E) if not p.is_data).payload
    payload = patched(real, 206, field.ljust(128, b"\x00"))
    with pytest.raises(ParseError, match="NMEA"):
        decode_telemetry(payload, 0)
