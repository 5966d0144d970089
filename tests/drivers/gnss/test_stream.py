"""The NMEA splitter and parser on hostile input: binary interleaved, NULs, glued and cut
sentences, checksum storms, over-long sentences, and random bytes (hypothesis).

Sentences are real ones from the fixture logs; checksums of the few made-up sentences are
computed here with an XOR of our own, not with the code under test.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import operator
import tracemalloc

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers.paths import FIXTURES
from treetraits.drivers.gnss import (
    GGA,
    RMC,
    NmeaSummary,
    OtherSentence,
    SentenceSplitter,
    decode,
    parse_sentence,
)
from treetraits.errors import ParseError

NMEA_DIR = FIXTURES / "nmea"
MT3339 = (NMEA_DIR / "mt3339.nmea").read_bytes()  # clean CRLF, GGA GSA GSV RMC ZDA
LINES = MT3339.splitlines(keepends=True)
GGA_LINE = b"$GPGGA,202640.000,4404.1306,N,12118.8515,W,2,10,0.98,1127.7,M,-19.6,M,0000,0000*6C\r\n"
RMC_LINE = b"$GPRMC,202640.000,A,4404.1306,N,12118.8515,W,0.03,225.97,130415,,,D*73\r\n"
# A UBX NAV-PVT-sized frame whose payload holds NMEA delimiters, CR/LF and NULs.
UBX = b"\xb5\x62\x01\x07\x5c\x00" + bytes(range(256))[:92] + b"$\r\n*\x00!" + b"\x8e\x1f"


def nmea(body: bytes, line_end: bytes = b"\r\n") -> bytes:
    """A sentence with a correct checksum, computed independently."""
    return b"$%s*%02X%s" % (body, functools.reduce(operator.xor, body, 0), line_end)


def split(data: bytes, chunk: int | None = None, **options) -> tuple[list, SentenceSplitter]:
    splitter = SentenceSplitter(**options)
    out = []
    pieces = [data] if chunk is None else [data[i : i + chunk] for i in range(0, len(data), chunk)]
    for number, piece in enumerate(pieces):
        out += splitter.push(piece, t_host=number)
    out += splitter.flush()
    return out, splitter


def accounted(data: bytes, out: list, splitter: SentenceSplitter) -> bool:
    stats = splitter.stats
    return (
        stats.bytes == len(data)
        and sum(len(s.raw) for s in out) + stats.garbage_bytes + splitter.pending == len(data)
        and stats.sentences == len(out) == stats.valid + stats.bad_checksum
    )


def test_clean_log_in_any_chunking_gives_the_same_sentences():
    whole, _ = split(MT3339)
    assert [s.raw for s in whole] == LINES
    for chunk in (1, 2, 3, 7, 64, 1000):
        out, splitter = split(MT3339, chunk)
        assert [s.raw for s in out] == LINES
        assert accounted(MT3339, out, splitter)
        assert splitter.stats.garbage_bytes == 0


def test_t_host_is_the_read_that_held_the_line_end():
    splitter = SentenceSplitter()
    assert splitter.push(GGA_LINE[:40], t_host=1) == []
    assert splitter.push(GGA_LINE[40:-1], t_host=2) == []  # up to CR: the LF may follow
    [sentence] = splitter.push(GGA_LINE[-1:] + RMC_LINE[:5], t_host=3)
    assert sentence.raw == GGA_LINE and sentence.t_host == 2  # the CR came with read 2
    [rmc] = splitter.push(RMC_LINE[5:], t_host=4)
    assert rmc.raw == RMC_LINE and rmc.t_host == 4


def test_line_ends_lf_cr_and_none():
    lf, cr, bare = (
        nmea(b"GPHDT,274.07,T", b"\n"),
        nmea(b"GPHDT,274.04,T", b"\r"),
        nmea(b"GPHDT,1,T", b""),
    )
    out, splitter = split(lf + cr + b"junk" + bare)
    assert [s.raw for s in out] == [lf, cr, bare]  # the input may end right after `*hh`
    assert splitter.stats.garbage_bytes == 4
    # Lower-case hex digits are accepted; `!` starts a sentence too (AIS encapsulation).
    lower = GGA_LINE.replace(b"*6C", b"*6c")
    ais = nmea(b"AIVDM,1,1,,A,13u?etPv2;0n:dDPwUM1U1Cb069D,0")
    out, _ = split(lower + b"!" + ais[1:])
    assert [s.checksum_ok for s in out] == [True, True]
    assert out[1].raw.startswith(b"!AIVDM") and isinstance(decode(out[1]), OtherSentence)


def test_ubx_binary_interleaved():
    data = b"".join(UBX + line for line in LINES) + UBX
    for chunk in (None, 1, 17):
        out, splitter = split(data, chunk)
        assert [s.raw for s in out] == LINES
        assert splitter.stats.garbage_bytes == len(UBX) * (len(LINES) + 1)
        assert accounted(data, out, splitter)
        # Each UBX frame starts four candidates, all counted: `!"#` cut by `$`,
        # `$%&'()*+,` with no hex after `*`, `$` cut by CR, `!` cut by a binary byte.
        frames = len(LINES) + 1
        assert splitter.stats.truncated == 3 * frames
        assert splitter.stats.unterminated == frames


def test_nul_padded_cut_sentence_then_recovery():
    # From gp-320fw: a sentence cut by a receiver reboot, padded with NULs and spaces.
    cut = b"$GPRMC,000346.03,A,4808" + b"\x00" * 12 + b" " * 18 + b"\r\n"
    data = cut + b"$PLCS,REV,PLN012054S07,070312,145743\r\n" + RMC_LINE
    out, splitter = split(data)
    assert [s.raw for s in out] == [RMC_LINE]
    assert splitter.stats.truncated == 2  # the cut RMC, and $PLCS without a checksum
    assert accounted(data, out, splitter)


def test_glued_sentences():
    gsa = b"$GPGSA,A,1,,,,,,,,,,,,,,,*1E"
    rmc = b"$GPRMC,235949.00,V,0000.0000,N,00000.0000,E,,,161206,,,N*44\r\n"
    # `*1E` followed by `$`: no line end, so the GSA is not a sentence; the RMC is.
    out, splitter = split(gsa + rmc)
    assert [s.raw for s in out] == [rmc] and out[0].checksum_ok
    assert splitter.stats.unterminated == 1
    # A GSV cut by the next sentence's `$` (gp-320fw): the GGA is found.
    gsv = b"$GPGSV,3,3,12,06,08,270,,16,01,090,,02,16,270,"
    gga = b"$GPGGA,000410.00,0000.0000,N,00000.0000,E,0,00,0.0,,M,,M,,*58\r\n"
    out, splitter = split(gsv + gga, chunk=5)
    assert [s.raw for s in out] == [gga] and out[0].checksum_ok
    assert splitter.stats.truncated == 1
    # A sentence injected into another (isync's packet collision): the injected one is
    # found, the other is lost.
    injected = b"$PTNTA,20160203131539,2,T4,000000066,+107,3,0,3*18\n"
    data = b"$GPGSV,4,1,15,02,11,115,36,0" + injected + b"5,34,060,48,07,00,023,,13,56,090,49*71\n"
    out, splitter = split(data)
    assert [s.raw for s in out] == [injected]
    assert accounted(data, out, splitter)


def test_truncated_at_end_of_input_is_counted_not_returned():
    out, splitter = split(LINES[0] + LINES[1][:30])
    assert [s.raw for s in out] == [LINES[0]]
    assert splitter.stats.truncated == 1 and splitter.pending == 0
    assert splitter.stats.garbage_bytes == 30


def test_bad_checksum_storm_is_counted_never_used_and_memory_bounded():
    bad_gga = GGA_LINE.replace(b"*6C", b"*6D")
    bad_rmc = RMC_LINE.replace(b"*73", b"*00")
    storm = (bad_gga + bad_rmc) * 10_000  # 20 000 bad sentences, 1.5 MB
    splitter = SentenceSplitter()
    summary = NmeaSummary()  # counts, decodes and assembles epochs like `nmea info`
    returned = fixes = 0
    tracemalloc.start()
    try:
        reads = (storm[start : start + 4096] for start in range(0, len(storm), 4096))
        for number, data in enumerate(itertools.chain(reads, [None])):  # None: the end
            out = splitter.flush() if data is None else splitter.push(data, t_host=number)
            for sentence in out:
                returned += 1
                assert not sentence.checksum_ok and decode(sentence) is None
                fixes += summary.add(sentence) is not None
            assert splitter.pending <= splitter.max_length
        fixes += summary.finish() is not None
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1_000_000  # a few chunks' worth, not the storm
    assert returned == splitter.stats.bad_checksum == 20_000
    assert splitter.stats.valid == 0 and fixes == 0 and summary.assembler.stats.records == 0
    facts = summary.as_dict({})
    assert facts["bad_checksum"] == 20_000 and facts["valid"] == 0
    assert facts["epochs"] == 0 and facts["first_fix"] is None
    assert facts["gga_quality_histogram"] == {}


def test_sentences_longer_than_nmea_allows():
    long_ok = nmea(b"PSTI,032," + b"1.5," * 40)  # 175 bytes: over NMEA's 82, kept
    too_long = nmea(b"PSTI,032," + b"1.5," * 300)  # over max_length: dropped
    data = long_ok + too_long + GGA_LINE
    out, splitter = split(data, chunk=50, max_length=512)
    assert [s.raw for s in out] == [long_ok, GGA_LINE]
    assert splitter.stats.over_nmea_limit == 2  # long_ok, and this GGA at 84 bytes
    assert splitter.stats.too_long == 1
    assert accounted(data, out, splitter)
    # A `$` followed by endless printable text never grows the buffer past max_length.
    splitter = SentenceSplitter(max_length=256)
    splitter.push(b"$GPGGA,", 0)
    for _ in range(10_000):
        splitter.push(b"1234567890" * 10, 0)
        assert splitter.pending <= 256
    assert splitter.push(b"\r\n" + GGA_LINE, 0)[0].raw == GGA_LINE
    assert splitter.stats.too_long == 1


def test_parse_sentence_errors_are_typed_and_say_what_came():
    with pytest.raises(ParseError, match="checksum mismatch"):
        parse_sentence(GGA_LINE.replace(b"*6C", b"*6D"))
    with pytest.raises(ParseError, match="not one NMEA sentence"):
        parse_sentence(b"$GPGGA,1,2,3\r\n")
    with pytest.raises(ParseError, match="not one NMEA sentence"):
        parse_sentence(GGA_LINE + RMC_LINE)
    with pytest.raises(ParseError, match="lat"):
        parse_sentence(nmea(b"GPGGA,202640.000,4461.0000,N,12118.8515,W,1,10,0.98,1,M,1,M,,"))
    with pytest.raises(ParseError, match="hemisphere"):
        parse_sentence(nmea(b"GPGGA,202640.000,4404.1306,X,12118.8515,W,1,10,0.98,1,M,1,M,,"))
    with pytest.raises(ParseError, match="decimal"):
        parse_sentence(nmea(b"GPGGA,202640.000,4404.1306,N,12118.8515,W,1,10,nan,1,M,1,M,,"))
    with pytest.raises(ParseError, match="calendar"):
        parse_sentence(nmea(b"GPRMC,202640.000,A,4404.1306,N,12118.8515,W,0.0,0.0,310215,,,A"))


def test_parse_sentence_layouts():
    gga = parse_sentence(GGA_LINE, t_host=7)
    assert isinstance(gga, GGA) and gga.raw is GGA_LINE and gga.t_host == 7
    assert (gga.talker, gga.kind, gga.quality, gga.satellites) == ("GP", "GGA", 2, 10)
    assert gga.tod_ns == (20 * 3600 + 26 * 60 + 40) * 10**9
    # NMEA 2.0 RMC (no mode field) and an empty GGA from a receiver without a fix.
    old = parse_sentence(b"$GPRMC,005947.00,A,3715.6616,N,12157.6709,W,0.0,0.0,080710,,*2F\r\n")
    assert isinstance(old, RMC) and old.mode is None and old.nav_status is None
    empty = parse_sentence(b"$GPGGA,,,,,,0,,,,M,,M,,*66\n")
    assert (empty.tod_ns, empty.lat, empty.quality, empty.altitude_m) == (None, None, 0, None)
    # Any talker; proprietary and unknown sentences are kept as fields.
    for talker in (b"GN", b"GL", b"GA", b"GB", b"GQ", b"BD"):
        assert parse_sentence(nmea(talker + GGA_LINE[3:-5])).talker == talker.decode()
    psti = parse_sentence(b"$PSTI,036,003832.000,290322,244.28,2.77,0.00,R*5D\r\n")
    assert isinstance(psti, OtherSentence) and psti.kind == "PSTI" and psti.fields[0] == "036"


# -------------------------------------------------------------------------- hypothesis

SAMPLES = [*LINES[:20], b"$GNTHS,244.28,A*11\r\n", b"$GPHDT,,T*1B\n"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=2000), cuts=st.lists(st.integers(0, 2000), max_size=8))
def test_random_bytes_never_raise_and_every_byte_is_accounted_for(data, cuts):
    splitter = SentenceSplitter(max_length=128)
    out = []
    bounds = sorted({0, len(data), *(c for c in cuts if c <= len(data))})
    for a, b in itertools.pairwise(bounds):
        out += splitter.push(data[a:b], t_host=a)
        assert splitter.pending <= 128
    assert accounted(data, out, splitter)
    out += splitter.flush()
    assert splitter.pending == 0 and accounted(data, out, splitter)
    for sentence in out:
        with contextlib.suppress(ParseError):  # good checksum over garbage fields: typed
            decode(sentence)


@settings(max_examples=200, deadline=None)
@given(
    parts=st.lists(
        st.tuples(st.binary(max_size=200), st.sampled_from(SAMPLES)), min_size=1, max_size=10
    ),
    tail=st.binary(max_size=100),
    chunk=st.integers(1, 300),
)
def test_valid_sentences_among_garbage_are_all_found(parts, tail, chunk):
    data = b"".join(garbage + sentence for garbage, sentence in parts) + tail
    out, splitter = split(data, chunk)
    found = iter([s.raw for s in out if s.checksum_ok])
    for _, sentence in parts:  # in order, possibly with lucky garbage sentences between
        assert any(raw == sentence for raw in found)
    assert accounted(data, out, splitter)
