"""The GNSS driver on 13 real receiver logs (tests/fixtures/nmea, from gpsd's regression suite).

`treetraits nmea info --json` is checked against expected_counts.json, whose numbers were
computed independently of this code (the counting rules are in PROVENANCE.md); every GGA and
RMC is decoded field by field by pynmeagps too and compared; and a few values are read
straight from the raw text (with `Decimal`, not through the code under test).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import subprocess
import sys
from collections import Counter
from decimal import Decimal
from pathlib import Path

import pytest
from pynmeagps import NMEAReader

from tests.helpers.paths import FIXTURES
from treetraits.cli import main
from treetraits.drivers import recording
from treetraits.drivers.gnss import (
    GGA,
    GSA,
    RMC,
    ZDA,
    EpochAssembler,
    LogSource,
    RecordingSource,
    assemble,
    decode,
    open_gnss_source,
)
from treetraits.drivers.records import Fix

NMEA_DIR = FIXTURES / "nmea"
EXPECTED = json.loads((NMEA_DIR / "expected_counts.json").read_text())["files"]
LOGS = sorted(EXPECTED)


def sentences_of(name: str) -> list:
    source = open_gnss_source(NMEA_DIR / name)
    try:
        return list(source)
    finally:
        source.close()


def records_of(name: str) -> list:
    return [decode(s) for s in sentences_of(name) if s.checksum_ok]


def fixes_of(name: str, **options) -> list[Fix]:
    return list(assemble(records_of(name), **options))


def info_json(capsys, path: Path, *extra: str) -> dict:
    assert main(["nmea", "info", str(path), "--json", *extra]) == 0
    return json.loads(capsys.readouterr().out)


def by_type(by_address: dict[str, int]) -> dict[str, int]:
    """PROVENANCE.md: type = address minus its 2-letter talker; `P...` is its own type."""
    counts: Counter = Counter()
    for address, count in by_address.items():
        counts[address if address.startswith("P") else address[2:]] += count
    return dict(counts)


def tod_text(utc: str) -> str:
    """`003956.00` (the fixtures' form) -> `00:39:56.000` (ours)."""
    whole, _, fraction = utc.partition(".")
    return f"{whole[:2]}:{whole[2:4]}:{whole[4:6]}.{fraction.ljust(3, '0')[:3]}"


def dmm(text: str, hemisphere: str) -> Decimal:
    """(d)ddmm.mmmm -> decimal degrees, exactly."""
    dot = text.index(".")
    value = Decimal(text[: dot - 2]) + Decimal(text[dot - 2 :]) / 60
    return -value if hemisphere in "SW" else value


@pytest.mark.parametrize("name", LOGS)
def test_fixture_is_the_documented_file(name):
    """Guards against a checkout that rewrote line ends or stripped NULs."""
    data = (NMEA_DIR / name).read_bytes()
    assert len(data) == EXPECTED[name]["bytes"]
    assert hashlib.sha256(data).hexdigest() == EXPECTED[name]["sha256"]


@pytest.mark.parametrize("name", LOGS)
def test_info_json_matches_the_stream_counts(name, capsys):
    expected = EXPECTED[name]
    facts = info_json(capsys, NMEA_DIR / name)

    assert facts["valid_by_type"] == by_type(expected["valid_by_address_stream"])
    assert facts["valid_by_address"] == expected["valid_by_address_stream"]
    assert facts["valid"] == expected["valid_total_stream"]
    assert facts["talkers"] == expected["talkers"]
    # The fixtures count bad checksums per line (line-strict); on these logs every
    # bad-checksum sentence is alone on its line, so the stream count is the same.
    assert facts["bad_checksum"] == expected["bad_checksum_lines"]
    assert facts["sentences"] == facts["valid"] + facts["bad_checksum"]
    assert facts["undecodable"] == 0
    assert facts["hdt_with_value"] == expected["hdt_with_value"]
    assert facts["ths_with_value"] == expected["ths_with_value"]
    assert facts["bytes"] == expected["bytes"]
    assert facts["is_live"] is False

    # The fixtures' histogram is line-strict; it equals ours wherever both rules see the
    # same GGAs (gp-320fw is the exception, see the next test).
    stream_gga = by_type(expected["valid_by_address_stream"]).get("GGA", 0)
    if stream_gga == expected["valid_by_type"].get("GGA", 0):
        assert facts["gga_quality_histogram"] == expected["gga_quality_histogram"]
    assert sum(facts["gga_quality_histogram"].values()) == stream_gga

    assert facts["first_fix"]["source"] == expected["fix_source"]
    for ours, theirs in (
        (facts["first_fix"], expected["first_fix"]),
        (facts["last_fix"], expected["last_fix"]),
    ):
        assert ours["lat"] == pytest.approx(theirs["lat"], abs=1e-9)  # theirs: 9 decimals
        assert ours["lon"] == pytest.approx(theirs["lon"], abs=1e-9)
        assert tod_text(theirs["utc"]) in ours["utc"]
        if theirs["quality"].isdigit():
            assert ours["quality"] == int(theirs["quality"])
        else:  # "RMC-A": no usable GGA, RMC status A, here without a mode: quality 1
            assert ours["quality"] == 1


def test_gp320fw_glued_gga_is_found_by_the_stream_rule(capsys):
    """The stream finds one more GGA than the line-strict histogram: the one glued after a
    GSV cut short, a no-fix (quality 0) GGA."""
    name = "gp-320fw-2019-04-07-coldboot.nmea"
    raw = (NMEA_DIR / name).read_bytes()
    glued = b"$GPGSV,3,3,12,06,08,270,,16,01,090,,02,16,270,$GPGGA,000410.00,"
    assert raw.count(glued) == 1
    facts = info_json(capsys, NMEA_DIR / name)
    line_strict = Counter(EXPECTED[name]["gga_quality_histogram"])
    assert Counter(facts["gga_quality_histogram"]) - line_strict == Counter({"0": 1})
    gga = [r for r in records_of(name) if isinstance(r, GGA)]
    [found] = [r for r in gga if r.raw.startswith(b"$GPGGA,000410.00,")]
    assert found.quality == 0 and raw.index(found.raw) == raw.index(glued) + glued.index(b"$GPGGA")
    # The rest of the corruption is counted, not hidden.
    assert facts["truncated"] > 0 and facts["unterminated"] > 0 and facts["garbage_bytes"] > 0
    assert facts["utc_backwards"] > 0 and facts["duration_s"] is None  # week-rollover dates


def test_info_as_a_user_runs_it():
    name = "ublox-zed-f9r.nmea"
    result = subprocess.run(
        [sys.executable, "-m", "treetraits", "nmea", "info", str(NMEA_DIR / name), "--json"],
        capture_output=True,
        text=True,
        check=True,
    )
    facts = json.loads(result.stdout)
    assert facts["valid_by_type"] == by_type(EXPECTED[name]["valid_by_address_stream"])
    assert facts["valid_by_type"]["RMC"] == 30  # all 30 follow binary on their line
    assert facts["duration_s"] == 29.0

    human = subprocess.run(
        [sys.executable, "-m", "treetraits", "nmea", "info", str(NMEA_DIR / name)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "GGA: 30" in human and "RMC: 30" in human and "first fix" in human


@pytest.mark.parametrize("command", [["nmea"], ["nmea", "info"]])
def test_every_nmea_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([*command, "--help"])
    assert exit_info.value.code == 0
    assert "usage: treetraits nmea" in capsys.readouterr().out


def test_missing_input_is_one_clear_line(capsys, tmp_path):
    assert main(["nmea", "info", str(tmp_path / "nope.nmea")]) == 2
    err = capsys.readouterr().err
    assert "no such file" in err and "Traceback" not in err


def _none(value):
    return None if value == "" else value


def _tod_ns(value) -> int | None:
    if value == "":
        return None
    return ((value.hour * 60 + value.minute) * 60 + value.second) * 10**9 + value.microsecond * 1000


@pytest.mark.parametrize("name", LOGS)
def test_every_gga_and_rmc_agrees_with_pynmeagps(name):
    compared = 0
    for sentence in sentences_of(name):
        if not sentence.checksum_ok or sentence.kind not in ("GGA", "RMC"):
            continue
        ours = decode(sentence)
        theirs = NMEAReader.parse(sentence.raw)
        pairs = [
            (ours.tod_ns, _tod_ns(theirs.time)),
            (ours.lat, _none(theirs.lat)),  # pynmeagps rounds to 10 decimals
            (ours.lon, _none(theirs.lon)),
        ]
        if isinstance(ours, GGA):
            station = None if ours.station_id is None else int(ours.station_id)
            pairs += [
                (ours.quality, _none(theirs.quality)),
                (ours.satellites, _none(theirs.numSV)),
                (ours.hdop, _none(theirs.HDOP)),
                (ours.altitude_m, _none(theirs.alt)),
                (ours.geoid_separation_m, _none(theirs.sep)),
                (ours.correction_age_s, _none(theirs.diffAge)),
                (station, _none(theirs.diffStation)),
            ]
        else:
            variation = ours.magnetic_variation_deg
            pairs += [
                (ours.status, _none(theirs.status)),
                (ours.speed_kn, _none(theirs.spd)),
                (ours.course_deg, _none(theirs.cog)),
                (ours.date, _none(theirs.date)),
                (None if variation is None else abs(variation), _none(theirs.mv)),
                (ours.mode, _none(getattr(theirs, "posMode", ""))),
            ]
        for mine, peer in pairs:
            if isinstance(mine, float) and peer is not None:
                assert mine == pytest.approx(peer, abs=1e-9), sentence.raw
            else:
                assert mine == peer, sentence.raw
        compared += 1
    expected = by_type(EXPECTED[name]["valid_by_address_stream"])
    assert compared == expected.get("GGA", 0) + expected.get("RMC", 0)


# ------------------------------------------------------------- values from the raw text


def test_rtk_minutes_keep_all_eight_decimals():
    name = "nmea-rtk.nmea"
    ggas = [r for r in records_of(name) if isinstance(r, GGA)]
    assert len(ggas) == 122
    for gga in ggas:
        fields = gga.raw.decode().split(",")
        assert len(fields[2].split(".")[1]) == 8
        assert Decimal(gga.lat) == pytest.approx(dmm(fields[2], fields[3]), abs=Decimal("1e-13"))
        assert Decimal(gga.lon) == pytest.approx(dmm(fields[4], fields[5]), abs=Decimal("1e-13"))
    first = ggas[0]  # $GNGGA,132819.60,4134.49795459,N,09345.03431408,W,2,...,6.6,0133*6A
    assert f"{(first.lat - 41) * 60:.8f}" == "34.49795459"
    assert f"{(-first.lon - 93) * 60:.8f}" == "45.03431408"
    assert first.correction_age_s == 6.6 and first.station_id == "0133"
    rmc = next(r for r in records_of(name) if isinstance(r, RMC))
    assert rmc.magnetic_variation_deg == 11.5985 and rmc.mode == "D"
    assert rmc.date == dt.date(2020, 3, 18)
    qualities = Counter(f.quality for f in fixes_of(name))
    assert qualities == {2: 104, 4: 18}  # DGPS, then RTK fixed: told apart


def test_empty_geoid_separation_means_no_ellipsoidal_height():
    # $GPGGA,204132.10,4205.733715,N,08802.040978,W,2,08,1.0,221.921,M,,,3,0138*15
    fixes = fixes_of("rst39.nmea")
    # The first epoch is an RMC alone ($GPRMC,204132.00,A,...,D*7C): position and
    # quality 2 (mode D) from RMC, nothing of GGA's.
    assert fixes[0].quality == 2 and fixes[0].satellites is None
    assert fixes[0].speed_mps == pytest.approx(9.415 * 1852 / 3600)
    first = fixes[1]
    assert first.altitude_msl_m == 221.921
    assert first.geoid_separation_m is None and first.altitude_ellipsoid_m is None
    assert first.correction_age_s == 3.0 and first.quality == 2
    assert first.lat == pytest.approx(float(dmm("4205.733715", "N")), abs=1e-12)


def test_empty_hdt_gives_no_heading():
    records = records_of("hemi.nmea")
    hdts = [r for r in records if r.kind == "HDT"]
    assert len(hdts) == 215
    assert sum(r.heading_deg is None for r in hdts) == 211
    assert sorted(r.heading_deg for r in hdts if r.heading_deg is not None) == [
        274.04,
        274.07,
        274.11,
        274.12,
    ]
    headings = [f.heading_deg for f in assemble(records) if f.heading_deg is not None]
    assert sorted(headings) == [274.04, 274.07, 274.11, 274.12]


def test_two_d_fix_has_no_altitude():
    # $GPGGA,112257.00,3844.24011,N,00908.43828,W,1,03,10.5,,,,,,*72 and GSA mode 2
    records = records_of("polarx2.nmea")
    gsa = next(r for r in records if isinstance(r, GSA))
    assert gsa.fix_mode == 2 and gsa.vdop is None and gsa.satellite_ids == (10, 13, 23)
    fixes = list(assemble(records))
    assert len(fixes) == 5
    assert all(f.quality == 1 and f.altitude_msl_m is None for f in fixes)
    assert fixes[0].lat == pytest.approx(38.737335167, abs=1e-9)
    assert fixes[0].lon == pytest.approx(-9.140638, abs=1e-9)
    # GST: $GPGST,112257.00,0.387,317.719,3.872,1.791,317.563,10.659,180.746*61
    assert (fixes[0].std_lat_m, fixes[0].std_lon_m, fixes[0].std_alt_m) == (
        317.563,
        10.659,
        180.746,
    )
    # RMC course 339.1 deg, 0.1 kn; magnetic variation 5.6 E
    assert fixes[0].course_deg == 339.1
    assert fixes[0].speed_mps == pytest.approx(0.1 * 1852 / 3600)


def test_dual_antenna_heading_from_ths_mode_a():
    # $GNTHS,244.28,A*11 and $GNHDT,244.28,T*13 every epoch; RTK float (5)
    records = records_of("skytraq-PX1172RH_DS.nmea")
    ths = [r for r in records if r.kind == "THS"]
    assert [r.mode for r in ths] == ["A"] * 9 and ths[0].heading_deg == 244.28
    fixes = list(assemble(records))
    assert [f.heading_deg for f in fixes] == [r.heading_deg for r in ths]
    assert all(f.quality == 5 for f in fixes)
    # A THS whose mode is not accepted means no heading, HDT beside it or not.
    assembler = EpochAssembler(ths_modes=())
    no_heading = [f for r in records if (f := assembler.push(r))] + [assembler.flush()]
    assert all(f.heading_deg is None for f in no_heading)
    assert assembler.stats.ths_rejected == 9


def test_gst_std_devs_and_southern_hemisphere():
    # $GNGGA,003956.00,4552.65403,S,17030.00668,E,1,12,0.64,14.2,M,1.8,M,,*56
    # $GNGST,003956.00,235111,,,,2.3,3.5,4.0*46
    fixes = fixes_of("ublox-zed-f9p-nmea.nmea")
    assert len(fixes) == 29
    first = fixes[0]
    assert first.lat == pytest.approx(-float(dmm("4552.65403", "N")), abs=1e-12)
    assert first.lon == pytest.approx(float(dmm("17030.00668", "E")), abs=1e-12)
    assert (first.std_lat_m, first.std_lon_m, first.std_alt_m) == (2.3, 3.5, 4.0)
    assert first.altitude_msl_m == 14.2 and first.geoid_separation_m == 1.8
    assert first.altitude_ellipsoid_m == pytest.approx(16.0)
    assert first.satellites == 12 and first.hdop == 0.64
    assert (
        first.utc_ns
        == int(dt.datetime(2019, 4, 12, 0, 39, 56, tzinfo=dt.timezone.utc).timestamp()) * 10**9
    )


def test_rmc_after_binary_is_decoded():
    fixes = fixes_of("ublox-zed-f9r.nmea")
    assert len(fixes) == 30
    assert all(f.quality == 5 for f in fixes)  # GGA says RTK float; RMC mode F agrees
    # $GNRMC,231408.00,A,4503.94632,N,00739.54368,E,0.013,,110425,,,F,V*17: no course
    assert fixes[0].course_deg is None
    assert fixes[0].speed_mps == pytest.approx(0.013 * 1852 / 3600)
    assert fixes[0].std_lat_m is not None  # GST every epoch


def test_bad_checksums_are_never_used():
    """firefly-II: every GGA has a bad checksum (and an empty quality); fixes come from
    RMC alone, without GGA's satellites or altitude."""
    sentences = sentences_of("firefly-II.nmea")
    bad = [s for s in sentences if not s.checksum_ok]
    assert len(bad) == 23 and {s.kind for s in bad} == {"GGA"}
    assert all(decode(s) is None for s in bad)
    fixes = fixes_of("firefly-II.nmea")
    assert len(fixes) == 23
    assert all(f.satellites is None and f.altitude_msl_m is None for f in fixes)
    assert all(f.quality == 1 for f in fixes)  # RMC status A, NMEA 2.x: no mode field


def test_repeated_gga_from_another_talker_is_ignored():
    """SiRFstarV sends GPGGA (8 satellites) then GLGGA (GLONASS only, 2) per epoch."""
    assembler = EpochAssembler()
    fixes = [f for r in records_of("sirfstarv-nmea.nmea") if (f := assembler.push(r))]
    fixes.append(assembler.flush())
    assert len(fixes) == 59
    assert fixes[0].satellites == 8
    assert assembler.stats.repeated == 59


def test_dates_from_zda_and_rmc_make_utc():
    fixes = fixes_of("mt3339.nmea")
    assert len(fixes) == 30
    start = dt.datetime(2015, 4, 13, 20, 26, 40, tzinfo=dt.timezone.utc)
    assert fixes[0].utc_ns == int(start.timestamp()) * 10**9
    assert [f.utc_ns - fixes[0].utc_ns for f in fixes] == [i * 10**9 for i in range(30)]
    # Week-rollover garbage is decoded as sent, not "fixed".
    records = records_of("gp-320fw-2019-04-07-coldboot.nmea")
    dates = {r.date for r in records if isinstance(r, RMC) and r.date}
    assert dt.date(1999, 8, 22) in dates and dt.date(2006, 12, 16) in dates
    assert {r.year for r in records if isinstance(r, ZDA)} == {1999}


@pytest.mark.parametrize("name", LOGS)
def test_every_sentence_keeps_its_raw_bytes(name):
    data = (NMEA_DIR / name).read_bytes()
    position = 0
    for sentence in sentences_of(name):
        position = data.index(sentence.raw, position) + len(sentence.raw)
        assert sentence.raw.startswith((b"$", b"!"))
        record = decode(sentence) if sentence.checksum_ok else None
        assert record is None or record.raw is sentence.raw


# ------------------------------------------------------------------------- recordings


@pytest.mark.parametrize("name", LOGS)
def test_recording_round_trip(name, tmp_path):
    """Sentences recorded on /gnss/nmea (log_time = t_host) read back as the log's."""
    source = LogSource(NMEA_DIR / name)
    original = list(source)
    source.close()
    path = tmp_path / "gnss.mcap"
    with recording.RecordingWriter(path) as writer:
        for number, sentence in enumerate(original):
            t_host = 1_700_000_000_000_000_000 + number * 1_000_000  # distinct, increasing
            writer.write(recording.GNSS_NMEA, sentence.raw, log_time=t_host)
            writer.write(recording.WHEELS_BRIDGE, b"\x01\x02", log_time=t_host)  # skipped
    replay = open_gnss_source(path)
    assert isinstance(replay, RecordingSource) and not replay.is_live
    replayed = list(replay)
    replay.close()
    assert [s.raw for s in replayed] == [s.raw for s in original]
    assert [s.checksum_ok for s in replayed] == [s.checksum_ok for s in original]
    assert [s.t_host for s in replayed] == [
        1_700_000_000_000_000_000 + n * 1_000_000 for n in range(len(original))
    ]
    counters = replay.counters()
    assert counters["reads"] == len(original) and counters["garbage_bytes"] == 0
    assert counters["recording_truncated"] is False
