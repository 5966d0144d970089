"""drivers/gnss/times.py: the UTC `publish_time` of live NMEA sentences, against the real
receiver captures in tests/fixtures/nmea (see PROVENANCE.md there). Expected times are
read from the sentences' own text with `datetime.strptime`, not with the code under test."""

from __future__ import annotations

import datetime as dt

import pytest

from tests.helpers.paths import FIXTURES
from treetraits.drivers.gnss.sentences import checksum
from treetraits.drivers.gnss.stream import SentenceSplitter
from treetraits.drivers.gnss.times import EPOCH_SPAN_NS, NmeaClock, nearest_utc_ns, publish_times

NMEA_DIR = FIXTURES / "nmea"
UTC = dt.timezone.utc
# The host clock of these tests: years after the captures, so a date taken from the host
# instead of the sentences shows.
HOST_T0 = int(dt.datetime(2026, 11, 23, 12, 0, tzinfo=UTC).timestamp()) * 10**9


def ns(moment: dt.datetime) -> int:
    """Exact ns since the epoch (no float) of an aware datetime."""
    delta = moment - dt.datetime(1970, 1, 1, tzinfo=UTC)
    return (delta.days * 86_400 + delta.seconds) * 10**9 + delta.microseconds * 1000


def sentences(name: str, step_ns: int) -> list[tuple[bytes, int]]:
    """The fixture's framed sentences (good and bad checksums), received `step_ns` apart."""
    splitter = SentenceSplitter()
    found = list(splitter.push((NMEA_DIR / name).read_bytes(), 0)) + list(splitter.flush())
    return [(s.raw, HOST_T0 + i * step_ns) for i, s in enumerate(found)]


def fields(raw: bytes) -> list[str]:
    """Address (without `$`) and fields."""
    return raw.split(b"*")[0][1:].decode("ascii", "replace").split(",")


def time_of_day_ns(text: str) -> int:
    clock = dt.datetime.strptime(text, "%H%M%S.%f" if "." in text else "%H%M%S")
    return ns(clock.replace(tzinfo=UTC)) - ns(
        clock.replace(hour=0, minute=0, second=0, microsecond=0, tzinfo=UTC)
    )


def nmea(body: str) -> bytes:
    return b"$%s*%02X\r\n" % (body.encode(), checksum(body.encode()))


def test_ublox_f9p_every_sentence_takes_its_epochs_utc_on_the_rmc_date():
    # u-blox sends RMC first in each burst, then VTG, GGA, GSA, GSV, GLL, GST, ZDA.
    items = sentences("ublox-zed-f9p-nmea.nmea", 1_000_000)
    stamps = publish_times(items)
    expected, epoch = [], None
    for raw, _ in items:
        f = fields(raw)
        if f[0].endswith("RMC"):
            epoch = ns(
                dt.datetime.strptime(f"{f[9]} {f[1]}", "%d%m%y %H%M%S.%f").replace(tzinfo=UTC)
            )
        expected.append(epoch)
    assert None not in expected and stamps == expected
    assert len(set(stamps)) == sum(fields(r)[0].endswith("RMC") for r, _ in items) > 20
    assert dt.datetime.fromtimestamp(stamps[0] / 1e9, UTC).date() == dt.date(2019, 4, 12)


def test_hemisphere_untimed_sentences_before_any_time_keep_t_host_then_join_the_zda_epoch():
    # This Hemisphere receiver sends HDT, GGA (no fix: empty time) and VTG, and a ZDA a second.
    items = sentences("hemi.nmea", 100_000_000)
    stamps = publish_times(items)
    first_zda = next(i for i, (raw, _) in enumerate(items) if fields(raw)[0].endswith("ZDA"))
    assert first_zda > 0
    assert stamps[:first_zda] == [t for _, t in items[:first_zda]]  # no epoch known yet
    checked = 0
    epoch = day = None
    for (raw, t_host), stamp in zip(items[first_zda:], stamps[first_zda:], strict=True):
        f = fields(raw)
        if f[0].endswith("ZDA"):
            day = ns(dt.datetime(int(f[4]), int(f[3]), int(f[2]), tzinfo=UTC))
        if f[0].endswith(("ZDA", "GGA")) and f[1]:  # GGA has a time once it has a fix
            utc = day + time_of_day_ns(f[1])
            if epoch is None or epoch[0] != utc:
                epoch = (utc, t_host)
        if t_host - epoch[1] <= EPOCH_SPAN_NS:
            assert stamp == epoch[0]
            checked += 1
    assert checked > 500


@pytest.mark.parametrize("path", sorted(NMEA_DIR.glob("*.nmea")), ids=lambda p: p.stem)
def test_every_capture_stamps_each_timed_sentence_at_its_own_time_of_day(path):
    # Bad checksums, binary, cut sentences and sentences of every type: never an error,
    # and a sentence with a readable time of its own is stamped at that time of day.
    items = sentences(path.name, 50_000_000)
    stamps = publish_times(items)
    timed = 0
    for (raw, _), stamp in zip(items, stamps, strict=True):
        f = fields(raw)
        index = {"GGA": 1, "RMC": 1, "GST": 1, "ZDA": 1, "GNS": 1, "GBS": 1, "GRS": 1, "GLL": 5}
        at = index.get(f[0][2:]) if len(f[0]) == 5 and not f[0].startswith("P") else None
        body, _, check = raw.rstrip(b"\r\n").partition(b"*")
        good = len(check) >= 2 and int(check[:2], 16) == checksum(body[1:])
        if at is None or at >= len(f) or not f[at] or not good:
            continue
        try:
            tod = time_of_day_ns(f[at])
        except ValueError:
            continue
        assert stamp % (86_400 * 10**9) == tod
        timed += 1
    assert timed > 0


def test_midnight_without_a_date_goes_to_the_day_nearest_the_host_clock():
    just_after = ns(dt.datetime(2026, 11, 24, 0, 0, 0, 200_000, tzinfo=UTC))
    clock = NmeaClock()
    stamp = clock.stamp(
        nmea("GPGGA,235959.90,4552.65403,S,17030.00668,E,1,12,0.64,14.2,M,1.8,M,,"), just_after
    )
    assert stamp == ns(dt.datetime(2026, 11, 23, 23, 59, 59, 900_000, tzinfo=UTC))
    assert nearest_utc_ns(0, ns(dt.datetime(2026, 11, 23, 23, 59, 59, tzinfo=UTC))) == ns(
        dt.datetime(2026, 11, 24, tzinfo=UTC)
    )


def test_the_receivers_date_is_carried_across_midnight_whatever_the_host_clock_says():
    host = ns(dt.datetime(2031, 1, 1, 8, tzinfo=UTC))  # a host clock years off
    clock = NmeaClock()
    rmc = nmea("GNRMC,235959.90,A,4552.65403,S,17030.00668,E,0.025,,120419,,,A,V")
    assert clock.stamp(rmc, host) == ns(dt.datetime(2019, 4, 12, 23, 59, 59, 900_000, tzinfo=UTC))
    gga = nmea("GNGGA,000000.00,4552.65403,S,17030.00668,E,1,12,0.64,14.2,M,1.8,M,,")
    assert clock.stamp(gga, host + 100_000_000) == ns(dt.datetime(2019, 4, 13, tzinfo=UTC))
    vtg = nmea("GNVTG,,T,,M,0.025,N,0.045,K,A")
    assert clock.stamp(vtg, host + 150_000_000) == ns(dt.datetime(2019, 4, 13, tzinfo=UTC))


def test_an_untimed_sentence_long_after_the_last_epoch_or_a_corrupted_time_keeps_t_host():
    t = HOST_T0
    clock = NmeaClock()
    epoch = clock.stamp(nmea("GPZDA,120000.00,23,11,2026,00,00"), t)
    assert epoch == ns(dt.datetime(2026, 11, 23, 12, tzinfo=UTC))
    assert clock.stamp(nmea("GPHDT,274.07,T"), t + EPOCH_SPAN_NS) == epoch
    late = t + EPOCH_SPAN_NS + 1
    assert clock.stamp(nmea("GPHDT,274.07,T"), late) == late
    # A bad checksum: its time is not trusted; it is stamped as an untimed sentence.
    corrupt = nmea("GPGGA,130000.00,,,,,0,,,,M,,M,,").replace(b"130000", b"130001")
    assert NmeaClock().stamp(corrupt, late) == late
