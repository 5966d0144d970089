"""Retrofit board protocol v1: CRC, COBS, frames, and the push reader's resync and counters.

Frames are built here independently of the module under test: `struct` for the layouts
and a small bitwise CRC-32C and split-based COBS written below, so a mistake shared by the
encoder and the decoder in `protocol.py` cannot pass unnoticed.
"""

from __future__ import annotations

import random
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from treetraits.drivers.records import WheelSample
from treetraits.errors import ParseError
from treetraits.firmware_bridge.retrofit import protocol as p
from treetraits.firmware_bridge.retrofit.reader import BridgeDecoder, BridgeReader, TickOdometer

# ---------------------------------------------------------------- reference implementation


def ref_crc32c(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1
    return crc ^ 0xFFFFFFFF


def ref_cobs(data: bytes) -> bytes:
    """COBS by zero-separated parts: every part but the last ends with an implied zero."""
    out = bytearray()
    parts = data.split(b"\x00")
    for index, part in enumerate(parts):
        last = index == len(parts) - 1
        while len(part) > 254 or (not last and len(part) >= 254):
            out += b"\xff" + part[:254]
            part = part[254:]
        if last and not part and data and len(parts) == 1:
            break  # data ended exactly on a full block
        out += bytes([len(part) + 1]) + part
    return bytes(out)


def ref_frame(msg_type, seq, t_us, payload, boot_id=0, version=1) -> bytes:
    body = struct.pack("<BBHHQ", version, msg_type, seq, boot_id, t_us) + payload
    return b"\x00" + ref_cobs(body + struct.pack("<I", ref_crc32c(body))) + b"\x00"


def ref_ticks(seq, t_us, left, right, lerr=0, rerr=0, boot_id=0) -> bytes:
    return ref_frame(1, seq, t_us, struct.pack("<iiII", left, right, lerr, rerr), boot_id)


def ref_heartbeat(seq, t_us, faults, dropped=0, fw=(1, 0, 0), board=0, boot_id=0) -> bytes:
    return ref_frame(2, seq, t_us, struct.pack("<IIBBBB", faults, dropped, *fw, board), boot_id)


def ref_config(seq, t_us, tpr, rate=100, hb_ms=1000, flags=0, boot_id=0) -> bytes:
    return ref_frame(3, seq, t_us, struct.pack("<IHHB", tpr, rate, hb_ms, flags), boot_id)


def ticks_stream(n: int, start_seq: int = 0, boot_id: int = 0) -> list[bytes]:
    return [
        ref_ticks((start_seq + i) & 0xFFFF, 10_000 * (i + 1), 7 * i, -3 * i, boot_id=boot_id)
        for i in range(n)
    ]


def fields(message) -> tuple:
    """Everything a message says, less the receive time."""
    return (type(message).__name__, message.seq, message.t_device_us, message.wire)


# ---------------------------------------------------------------- CRC and COBS


def test_crc32c_check_value():
    assert p.crc32c(b"123456789") == 0xE3069283 == ref_crc32c(b"123456789")
    assert p.crc32c(b"") == 0


def test_crc32c_matches_the_bitwise_reference():
    rng = random.Random(1)
    for size in (1, 2, 17, 250, 1000):
        data = rng.randbytes(size)
        assert p.crc32c(data) == ref_crc32c(data)


# The published COBS examples (Cheshire & Baker; the Wikipedia article's table).
COBS_VECTORS = [
    ("00", "0101"),
    ("0000", "010101"),
    ("001100", "01021101"),
    ("11220033", "0311220233"),
    ("11223344", "0511223344"),
    ("11000000", "0211010101"),
    (bytes(range(1, 255)).hex(), "ff" + bytes(range(1, 255)).hex()),
    (bytes(range(255)).hex(), "01ff" + bytes(range(1, 255)).hex()),
    (bytes(range(1, 256)).hex(), "ff" + bytes(range(1, 255)).hex() + "02ff"),
    ((bytes(range(2, 256)) + b"\x00").hex(), "ff" + bytes(range(2, 256)).hex() + "0101"),
    ((bytes(range(3, 256)) + b"\x00\x01").hex(), "fe" + bytes(range(3, 256)).hex() + "0201"),
]


@pytest.mark.parametrize(("raw", "encoded"), COBS_VECTORS)
def test_cobs_published_vectors(raw, encoded):
    raw, encoded = bytes.fromhex(raw), bytes.fromhex(encoded)
    assert p.cobs_encode(raw) == encoded == ref_cobs(raw)
    assert p.cobs_decode(encoded) == raw


def test_cobs_decode_accepts_a_code_byte_after_a_final_full_block():
    raw = bytes(range(1, 255))
    assert p.cobs_decode(b"\xff" + raw + b"\x01") == raw


@pytest.mark.parametrize(
    "data",
    [b"", b"\x00" * 300, b"\x00\x01" * 200, b"\x01" * 600, bytes(253) + b"\x05", b"\xff" * 254],
)
def test_cobs_round_trips_zero_heavy_and_long_data(data):
    encoded = p.cobs_encode(data)
    assert 0 not in encoded
    assert encoded == ref_cobs(data)
    assert p.cobs_decode(encoded) == data


@given(st.binary(max_size=1200))
def test_cobs_round_trip_property(data):
    encoded = p.cobs_encode(data)
    assert 0 not in encoded
    assert len(encoded) <= len(data) + len(data) // 254 + 1
    assert p.cobs_decode(encoded) == data


@pytest.mark.parametrize("bad", [b"\x05\x01\x02", b"\x02\x00", b"\x03\x01"])
def test_cobs_rejects_broken_blocks(bad):
    with pytest.raises(p.FrameError) as info:
        p.cobs_decode(bad)
    assert info.value.reason == "bad_cobs"
    assert isinstance(info.value, ParseError)


# ---------------------------------------------------------------- frames


def test_encoders_match_the_independent_reference():
    assert p.encode_ticks(3, 123_456, -5, 2**31 - 1, 2, 9) == ref_ticks(
        3, 123_456, -5, 2**31 - 1, 2, 9
    )
    assert p.encode_heartbeat(4, 2_000_000, 0x11, 7, (1, 2, 3), 1, boot_id=77) == ref_heartbeat(
        4, 2_000_000, 0x11, 7, (1, 2, 3), 1, boot_id=77
    )
    assert p.encode_config_echo(0, 0, 4096, 100, 1000, True, False) == ref_config(
        0, 0, 4096, flags=1
    )
    # Counts wrap to int32 as the board's counters do.
    assert p.encode_ticks(0, 0, 2**31, -(2**31) - 1) == ref_ticks(0, 0, -(2**31), 2**31 - 1)


def test_reference_frames_decode_exactly():
    stream = (
        ref_config(0, 0, 2048, 50, 500, flags=2, boot_id=513)
        + ref_heartbeat(1, 0, faults=0x31, dropped=12, fw=(1, 4, 2), board=1, boot_id=513)
        + ref_ticks(2, 20_000, -(2**31), 2**31 - 1, 3, 4, boot_id=513)
    )
    reader = BridgeReader()
    config, heartbeat, ticks = reader.push(stream, t_host=42)
    assert config == p.ConfigEcho(42, 0, 513, 0, 2048, 50, 500, 2, config.wire)
    assert not config.invert_left and config.invert_right
    assert heartbeat == p.Heartbeat(42, 1, 513, 0, 0x31, 12, 1, 4, 2, 1, heartbeat.wire)
    assert heartbeat.fault_names == ["LEFT_GLITCH", "WATCHDOG_RESET", "BROWNOUT_RESET"]
    assert heartbeat.firmware == "1.4.2" and heartbeat.board_name == "rp2040"
    assert ticks == p.Ticks(42, 2, 513, 20_000, -(2**31), 2**31 - 1, 3, 4, ticks.wire)
    # Each record keeps the bytes it came in, between its delimiters.
    assert b"\x00" + ticks.wire + b"\x00" == stream[-len(ticks.wire) - 2 :]
    assert reader.stats.frames == 3 and reader.stats.lost == 0 and reader.stats.resyncs == 0


def test_worked_example_in_protocol_md():
    """The byte string PROTOCOL.md shows for its TICKS example."""
    wire = p.encode_ticks(7, 1_000_000, 1234, -2, 0, 1, boot_id=0xBEEF)
    assert wire.hex(" ") == (
        "00 04 01 01 07 06 ef be 40 42 0f 01 01 01 01 03 d2 04 01 05 fe ff ff ff 01 01 01 "
        "02 01 01 01 05 60 67 d2 6d 00"
    )
    assert ref_crc32c(p.cobs_decode(wire[1:-1])[:-4]) == 0x6DD26760


def test_unknown_fault_bits_are_named_by_position():
    message = p.decode_message(p.decode_frame(ref_heartbeat(0, 0, 1 << 9 | 1)[1:-1]), 0)
    assert message.fault_names == ["LEFT_GLITCH", "bit9"]


def test_longest_frame_round_trips_and_longer_is_refused():
    payload = bytes(range(1, p.MAX_PAYLOAD + 1))
    wire = p.encode_frame(0x7E, 1, 2, payload)
    assert len(wire) == p.MAX_ENCODED + 2
    frame = p.decode_frame(wire[1:-1])
    assert frame.payload == payload and frame.type == 0x7E
    with pytest.raises(ValueError, match="at most"):
        p.encode_frame(0x7E, 1, 2, payload + b"\x01")
    with pytest.raises(p.FrameError) as info:
        p.decode_frame(b"\x01" * (p.MAX_ENCODED + 1))
    assert info.value.reason == "oversize"


# ---------------------------------------------------------------- resync


def decode_all(stream: bytes, reader: BridgeReader | None = None):
    reader = reader or BridgeReader()
    return reader.push(stream, 0), reader


def test_resync_after_garbage_between_frames():
    frames = ticks_stream(4)
    garbage = bytes([0x13, 0x00, 0xFF, 0x42, 0x00, 0x07, 0x07, 0x07, 0x00])
    stream = frames[0] + frames[1] + garbage + frames[2] + frames[3]
    messages, reader = decode_all(stream)
    assert [m.seq for m in messages] == [0, 1, 2, 3]
    s = reader.stats
    assert s.resyncs == 3 and s.bad_cobs + s.bad_crc + s.too_short == 3
    assert s.lost == 0


def test_resync_after_a_long_run_without_delimiters():
    frames = ticks_stream(2)
    noise = bytes(random.Random(5).randrange(1, 256) for _ in range(1000))
    messages, reader = decode_all(frames[0] + noise + frames[1])
    assert [m.seq for m in messages] == [0, 1]
    assert reader.stats.oversize == 1 and reader.stats.resyncs == 1
    assert reader.stats.discarded_bytes == len(noise)


@pytest.mark.parametrize("cut", [1, 2, 5, 20, -2])
def test_truncated_frame_costs_only_itself(cut):
    frames = ticks_stream(3)
    stream = frames[0] + frames[1][:cut] + frames[2]
    messages, reader = decode_all(stream)
    assert [m.seq for m in messages] == [0, 2]
    assert reader.stats.lost == 1


def test_every_single_bit_flip_costs_at_most_the_frame_it_hits():
    frames = ticks_stream(3)
    stream = bytearray(b"".join(frames))
    start, end = len(frames[0]), len(frames[0]) + len(frames[1])
    good = [fields(m) for m in decode_all(bytes(stream))[0]]
    for position in range(start, end):
        for bit in range(8):
            damaged = bytearray(stream)
            damaged[position] ^= 1 << bit
            messages, reader = decode_all(bytes(damaged))
            got = [fields(m) for m in messages]
            # Never a corrupted message, and the neighbours always survive.
            assert got in (good, [good[0], good[2]]), (position, bit)
            if len(got) == 2:
                assert reader.stats.lost == 1
                assert reader.stats.resyncs >= 1 or damaged[position] == 0


def test_leading_partial_frame_is_not_an_error():
    frames = ticks_stream(3)
    stream = frames[0][7:] + frames[1] + frames[2]  # the port was opened mid-frame
    messages, reader = decode_all(stream)
    assert [m.seq for m in messages] == [1, 2]
    assert reader.stats.leading == 1 and reader.stats.resyncs == 0


def test_split_reads_and_t_host_of_the_closing_read():
    frames = ticks_stream(3)
    stream = b"".join(frames)
    reader = BridgeReader()
    got = []
    for i in range(len(stream)):  # one byte per read
        got += reader.push(stream[i : i + 1], t_host=i)
    assert [m.seq for m in got] == [0, 1, 2]
    ends = [len(b"".join(frames[: k + 1])) - 1 for k in range(3)]
    assert [m.t_host for m in got] == ends
    assert reader.stats.bytes == len(stream)


def test_discontinuity_drops_the_partial_frame():
    frames = ticks_stream(3)
    reader = BridgeReader()
    assert len(reader.push(frames[0] + frames[1][:10], 0)) == 1
    reader.discontinuity()  # the port closed; the rest of frame 1 never comes
    assert [m.seq for m in reader.push(frames[2], 1)] == [2]
    assert reader.stats.truncated == 1 and reader.stats.lost == 1


# ---------------------------------------------------------------- sequence, versions, types


def seqs_lost(seqs, boot_ids=None):
    boot_ids = boot_ids or [0] * len(seqs)
    stream = b"".join(
        ref_ticks(s, 1000 * (i + 1), 0, 0, boot_id=b)
        for i, (s, b) in enumerate(zip(seqs, boot_ids, strict=True))
    )
    messages, reader = decode_all(stream)
    assert len(messages) == len(seqs)
    return reader.stats


def test_lost_frames_from_sequence_gaps():
    assert seqs_lost([0, 1, 2, 5, 6, 10]).lost == 5
    assert seqs_lost([65534, 65535, 0, 1]).lost == 0  # wrap
    assert seqs_lost([65535, 2]).lost == 2
    stats = seqs_lost([5, 3])  # backwards in one boot: not a loss
    assert stats.lost == 0 and stats.sequence_jumps == 1


def test_a_new_boot_is_a_restart_not_a_loss():
    stats = seqs_lost([100, 101, 0, 1], boot_ids=[7, 7, 8, 8])
    assert stats.lost == 0 and stats.device_restarts == 1
    # The board clock going back also marks a restart (same boot id by chance).
    stream = ref_ticks(500, 9_000_000, 0, 0) + ref_ticks(0, 1_000, 0, 0)
    assert decode_all(stream)[1].stats.device_restarts == 1


def test_unknown_version_is_counted_and_skipped():
    stream = ticks_stream(1)[0] + ref_frame(1, 1, 1, b"\x00" * 16, version=2) + ticks_stream(3)[2]
    messages, reader = decode_all(stream)
    assert [m.seq for m in messages] == [0, 2]
    assert reader.stats.unknown_version == 1 and reader.stats.resyncs == 0
    assert reader.stats.lost == 1  # a v2 header is not read, so its sequence is not known


def test_unknown_type_is_counted_skipped_and_keeps_the_sequence():
    stream = ticks_stream(1)[0] + ref_frame(0x42, 1, 15_000, b"new") + ticks_stream(3)[2]
    messages, reader = decode_all(stream)
    assert [m.seq for m in messages] == [0, 2]
    assert reader.stats.unknown_type == 1 and reader.stats.lost == 0


def test_longer_payload_is_read_shorter_is_counted():
    longer = ref_frame(1, 0, 5, struct.pack("<iiII", 9, 8, 0, 0) + b"\x01\x02appended")
    shorter = ref_frame(1, 1, 6, struct.pack("<ii", 9, 8))
    messages, reader = decode_all(longer + shorter)
    assert [(m.left, m.right) for m in messages] == [(9, 8)]
    assert reader.stats.bad_length == 1 and reader.stats.frames == 2


# ---------------------------------------------------------------- odometer


def make_ticks(seq, t_us, left, right, boot_id=0):
    return p.Ticks(t_us * 1000, seq, boot_id, t_us, left, right, 0, 0, b"")


def test_odometer_runs_on_across_int32_wrap():
    odo = TickOdometer()
    samples = [
        odo.sample(make_ticks(0, 10, 2**31 - 2, -(2**31) + 1)),
        odo.sample(make_ticks(1, 20, -(2**31) + 3, 2**31 - 4)),
    ]
    assert samples[0] == WheelSample(10_000, 2**31 - 2, -(2**31) + 1, "ticks", t_device_us=10)
    assert samples[1].left - samples[0].left == 5
    assert samples[1].right - samples[0].right == -5


def test_odometer_adds_a_restarted_boards_counts():
    odo = TickOdometer()
    odo.sample(make_ticks(0, 5_000_000, 1000, 500, boot_id=1))
    after = odo.sample(make_ticks(0, 2_000, 30, -10, boot_id=2))
    assert (after.left, after.right) == (1030, 490) and odo.restarts == 1


def test_decoder_yields_samples_and_keeps_the_last_config_and_heartbeat():
    stream = ref_config(0, 0, 4096) + ref_heartbeat(1, 0, 0) + ref_ticks(2, 0, 5, 6)
    decoder = BridgeDecoder()
    items = decoder.push(stream, 99)
    assert [type(i).__name__ for i in items] == ["ConfigEcho", "Heartbeat", "WheelSample"]
    assert items[2] == WheelSample(99, 5.0, 6.0, "ticks", t_device_us=0)
    assert decoder.config.ticks_per_rev == 4096 and decoder.heartbeat.seq == 1


# ---------------------------------------------------------------- fuzz


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=3000), st.lists(st.integers(1, 400), max_size=20))
def test_fuzz_never_raises_and_counts_every_byte(data, cuts):
    reader = BridgeReader()
    position = 0
    for size in cuts:
        reader.push(data[position : position + size], 0)
        position += size
    reader.push(data[position:], 0)
    reader.flush()
    assert reader.stats.bytes == len(data)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.binary(max_size=400), min_size=1, max_size=8),
    st.randoms(use_true_random=False),
)
def test_fuzz_every_frame_inserted_into_noise_is_recovered(noises, rnd):
    frames = [
        p.encode_ticks(i, 10_000 * i, rnd.randint(-(2**31), 2**31 - 1), i)
        if i % 3
        else p.encode_heartbeat(i, 10_000 * i, rnd.getrandbits(32))
        for i in range(len(noises))
    ]
    stream = b"".join(noise + frame for noise, frame in zip(noises, frames, strict=True))
    reader = BridgeReader()
    got = []
    position = 0
    while position < len(stream):  # random read sizes, as a serial port gives them
        size = rnd.randint(1, 64)
        got += reader.push(stream[position : position + size], 0)
        position += size
    assert [m.wire for m in got] == [f[1:-1] for f in frames]
    assert reader.stats.lost == 0
