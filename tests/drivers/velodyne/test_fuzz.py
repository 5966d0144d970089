"""Property tests: arbitrary and damaged bytes never crash the VLP-16 path.

- `ScanBatcher`: any stream (random byte strings, real packets with flipped bytes, random
  ToH, random factory bytes, packets dropped, repeated or moved) never raises, and every
  pushed packet is accounted for exactly once: decoded into an emitted scan, or counted
  `malformed`, `unsupported_model`, `duplicates` or `late`.
- `open_source` over random files raises `SourceError` or yields cleanly.
- `decode_telemetry` over random 512-byte payloads returns or raises `ParseError`.

The real packets come from the einride raw file (single return) and the nebula capture
(dual return), so that long enough runs still close real scans.
"""

from __future__ import annotations

import functools
import struct
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from tests.helpers.captures import VLP16_DIR
from treetraits.drivers.velodyne.batcher import ScanBatcher
from treetraits.drivers.velodyne.reader import LidarReader
from treetraits.drivers.velodyne.sources import open_source
from treetraits.drivers.velodyne.telemetry import decode_telemetry
from treetraits.errors import ParseError, SourceError

HOUR_US = 3_600_000_000
HOUR_NS = HOUR_US * 1000
FACTORY_BYTES = [0x21, 0x22, 0x24, 0x28, 0x37, 0x38, 0x39, 0x00, 0xFF]
FUZZ = settings(
    max_examples=200,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


@functools.cache
def real_packets() -> dict[str, tuple[bytes, ...]]:
    raw = (VLP16_DIR / "einride_vlp16_strongest_1000pkts.bin").read_bytes()
    source = open_source(VLP16_DIR / "nebula_vlp16_dual_10hz.pcap")
    dual = tuple(p.payload for p in source if p.is_data)
    source.close()
    return {
        "single": tuple(raw[i : i + 1206] for i in range(0, len(raw), 1206)),
        "dual": dual,
    }


def toh_of(payload: bytes) -> int | None:
    return struct.unpack_from("<I", payload, 1200)[0] if len(payload) >= 1204 else None


def patched(payload: bytes, offset: int, new: bytes) -> bytes:
    return payload[:offset] + new + payload[offset + len(new) :]


# --- batcher ------------------------------------------------------------------------

flips = st.lists(st.tuples(st.integers(0, 1205), st.integers(1, 255)), min_size=1, max_size=8)
edits = st.one_of(
    st.tuples(st.just("random"), st.integers(0, 10**6), st.binary(max_size=1300)),
    st.tuples(st.just("flip"), st.integers(0, 10**6), flips),
    st.tuples(st.just("toh"), st.integers(0, 10**6), st.integers(0, 2**32 - 1)),
    st.tuples(
        st.just("factory"),
        st.integers(0, 10**6),
        st.tuples(
            st.sampled_from([1204, 1205]),
            st.one_of(st.sampled_from(FACTORY_BYTES), st.integers(0, 255)),
        ),
    ),
    st.tuples(st.just("drop"), st.integers(0, 10**6), st.none()),
    st.tuples(st.just("repeat"), st.integers(0, 10**6), st.integers(0, 20)),
    st.tuples(st.just("move"), st.integers(0, 10**6), st.integers(-20, 20)),
)


def apply_edit(packets: list[bytes], edit) -> None:
    kind, where, arg = edit
    if kind == "random":
        packets.insert(where % (len(packets) + 1), arg)
        return
    if not packets:
        return
    i = where % len(packets)
    p = packets[i]
    if kind == "flip" and len(p) == 1206:
        buffer = bytearray(p)
        for offset, mask in arg:
            buffer[offset] ^= mask
        packets[i] = bytes(buffer)
    elif kind == "toh" and len(p) == 1206:
        packets[i] = patched(p, 1200, struct.pack("<I", arg))
    elif kind == "factory" and len(p) == 1206:
        offset, value = arg
        packets[i] = patched(p, offset, bytes([value]))
    elif kind == "drop":
        del packets[i]
    elif kind == "repeat":
        packets.insert(min(i + 1 + arg, len(packets)), p)
    elif kind == "move":
        del packets[i]
        packets.insert(max(0, min(i + arg, len(packets))), p)


@st.composite
def damaged_streams(draw) -> list[tuple[bytes, int]]:
    """A run of real packets (long enough to close scans), damaged by random edits,
    with a host clock that follows the device clock or is random."""
    real = real_packets()[draw(st.sampled_from(["single", "dual"]))]
    start = draw(st.integers(0, len(real) - 1))
    packets = list(real[start : start + draw(st.integers(0, 260))])
    for edit in draw(st.lists(edits, max_size=25)):
        apply_edit(packets, edit)
    if draw(st.booleans()):
        hour = draw(st.integers(0, 500_000))
        jitter = draw(st.integers(-5_000_000, 5_000_000))
        stream, t = [], hour * HOUR_NS
        for p in packets:
            toh = toh_of(p)
            t = t if toh is None else hour * HOUR_NS + toh * 1000 + jitter
            stream.append((p, t))
        return stream
    t_hosts = draw(st.lists(st.integers(0, 2**62), min_size=len(packets), max_size=len(packets)))
    return list(zip(packets, t_hosts, strict=True))


@FUZZ
@given(
    stream=damaged_streams(),
    model=st.sampled_from(["auto", "vlp16", "puck-hires"]),
    cut_angle=st.sampled_from([0.0, 90.5, 180.0, 359.99]),
    max_gap_s=st.sampled_from([1.0, 0.05]),
)
def test_batcher_never_raises_and_accounts_for_every_packet(stream, model, cut_angle, max_gap_s):
    batcher = ScanBatcher(model=model, cut_angle_deg=cut_angle, max_gap_s=max_gap_s)
    scans = [s for s in (batcher.push(p, t) for p, t in stream) if s is not None]
    last = batcher.flush()
    if last is not None:
        scans.append(last)
    assert batcher.flush() is None  # nothing left behind

    stats = batcher.stats
    decoded = sum(s.packets for s in scans)
    accounted = decoded + stats.malformed + stats.unsupported_model + stats.duplicates + stats.late
    assert accounted == len(stream) == stats.data_packets, stats
    assert stats.scans == len(scans) and stats.complete_scans == sum(s.complete for s in scans)
    assert stats.lost >= 0 and stats.out_of_order >= 0
    for name, value in [("scans", len(scans)), *stats.as_dict().items()]:
        if value and name not in ("data_packets", "points", "complete_scans"):
            event(f"{name} > 0")  # shown by --hypothesis-show-statistics
    points = sum(len(s.points) for s in scans)
    assert stats.points + stats.duplicate_returns == points
    for scan in scans:
        assert scan.packets >= 1 and scan.lost_packets >= 0
        assert (scan.points["ring"] < 16).all()
        assert np.isin(scan.points["return_type"], [0, 1]).all()
        # Whatever the host clock does, a scan's times run forward (its hour is read once).
        assert scan.t_start <= scan.t_end
        assert (np.diff(scan.points["t"]) >= 0).all() or scan.return_mode == "dual"


@FUZZ
@given(packets=st.lists(st.binary(max_size=1300), max_size=60))
def test_batcher_never_raises_on_pure_noise(packets):
    batcher = ScanBatcher()
    emitted = [batcher.push(p, i * 1_327_000) for i, p in enumerate(packets)]
    emitted.append(batcher.flush())
    stats = batcher.stats
    decoded = sum(s.packets for s in emitted if s is not None)
    accounted = decoded + stats.malformed + stats.unsupported_model + stats.duplicates + stats.late
    assert accounted == len(packets) == stats.data_packets


# --- sources ------------------------------------------------------------------------

PCAP_HEADER = struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)
PREFIXES = [
    b"",
    PCAP_HEADER,
    PCAP_HEADER[:4],
    b"\x0a\x0d\x0d\x0a",
    b"\x89MCAP0\r\n",
    b"\xff\xee",
]


@functools.cache
def real_capture() -> bytes:
    return (VLP16_DIR / "lidarutils_vlp16_strongest_0x22.pcap").read_bytes()


@st.composite
def file_contents(draw) -> bytes:
    if draw(st.booleans()):
        data = bytearray(real_capture()[: draw(st.integers(0, 12_000))])
        for offset, mask in draw(st.lists(st.tuples(st.integers(0, 11_999), st.integers(1, 255)))):
            if offset < len(data):
                data[offset] ^= mask
        return bytes(data)
    return draw(st.sampled_from(PREFIXES)) + draw(st.binary(max_size=4000))


@FUZZ
@given(content=file_contents(), suffix=st.sampled_from([".pcap", ".bin", ".mcap", ".dat"]))
def test_open_source_on_random_files_raises_source_error_or_yields(content, suffix):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"capture{suffix}"
        path.write_bytes(content)
        try:
            source = open_source(path)
        except SourceError:
            return
        reader = LidarReader(source)  # what it yields goes through the whole path
        try:
            for packet in source:
                assert len(packet.payload) in (1206, 512)
                reader.handle(packet)
            reader.batcher.flush()
        finally:
            reader.close()


# --- telemetry ----------------------------------------------------------------------

nmea_fields = st.one_of(
    st.binary(max_size=128),
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=120).map(
        lambda s: ("$" + s + "\r\n").encode()
    ),
    st.just(b""),
)


@st.composite
def position_payloads(draw) -> bytes:
    payload = draw(st.binary(min_size=512, max_size=512))
    if draw(st.booleans()):
        field = draw(nmea_fields)[:128]
        payload = patched(payload, 206, field.ljust(128, b"\x00"))
    return payload


@FUZZ
@given(payload=position_payloads(), t_host=st.integers(0, 2**63 - 1))
def test_decode_telemetry_returns_or_raises_parse_error(payload, t_host):
    try:
        telemetry = decode_telemetry(payload, t_host)
    except ParseError:
        return
    assert telemetry.toh_us == struct.unpack_from("<I", payload, 198)[0]
    assert telemetry.pps_status == payload[202]
    assert telemetry.nmea is None or telemetry.nmea.startswith("$")
    assert telemetry.raw == payload
