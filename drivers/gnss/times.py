"""The UTC of live NMEA sentences, as a recording's `publish_time` (docs/architecture.md,
recording format v1: "for GNSS the epoch's UTC", full ns since the Unix epoch).

A sentence is stamped as it is received, so nothing later in its burst can be waited for:

1. a sentence with a UTC time of day of its own (GGA, RMC, GST, ZDA, and GLL, GNS, GBS,
   GRS, which `sentences` does not decode) takes that time, on the date it carries (RMC,
   ZDA), else on the date of the stream's last dated sentence, else on the host's date;
   without a date of its own the day is the one that puts the time nearest the reference
   (the last dated UTC carried forward by the host clock, else `t_host`), which handles a
   burst that straddles midnight and a host clock off by hours;
2. a sentence without a time (GSA, HDT, THS, VTG, GSV, ...) or with a bad checksum takes
   the time of the epoch it belongs to: the last timed sentence's, the same grouping as
   `epochs.EpochAssembler` (an untimed sentence joins the open epoch), as long as that
   epoch began less than EPOCH_SPAN_NS before; else its receive time `t_host`.

The simulator stamps every sentence of an epoch with the epoch's UTC (sim/run.py); a live
recording now does the same.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterable
from dataclasses import dataclass

from treetraits.drivers.gnss.sentences import parse_sentence, split_frame, time_of_day
from treetraits.errors import ParseError

NS_PER_DAY = 86_400 * 1_000_000_000
_EPOCH_DATE = dt.date(1970, 1, 1)

# An untimed sentence more than this after the start of the last timed one's epoch is
# not of that epoch (a receiver sends one burst per epoch, at 1 Hz at the slowest).
EPOCH_SPAN_NS = 1_000_000_000

# Sentences `sentences.parse_sentence` leaves undecoded that carry the UTC time of day,
# and the index of that field after the address.
OTHER_TIME_FIELDS = {"GLL": 4, "GNS": 0, "GBS": 0, "GRS": 0}


def utc_ns(tod_ns: int, date: dt.date) -> int:
    """A UTC time of day on a date, as ns since the Unix epoch."""
    return (date - _EPOCH_DATE).days * NS_PER_DAY + tod_ns


def nearest_utc_ns(tod_ns: int, near_ns: int) -> int:
    """The UTC time with this time of day nearest `near_ns` (the day before, of, or after
    `near_ns`'s date): a time of day just before midnight read just after it belongs to
    the day before."""
    day = near_ns // NS_PER_DAY
    candidates = ((day + k) * NS_PER_DAY + tod_ns for k in (-1, 0, 1))
    return min(candidates, key=lambda t: abs(t - near_ns))


@dataclass(frozen=True, slots=True)
class SentenceTime:
    """What one sentence says about time: its UTC time of day and date, when it has them."""

    tod_ns: int | None
    date: dt.date | None = None


def sentence_time(raw: bytes) -> SentenceTime:
    """The time of day and date a framed sentence carries (both None when it carries
    none, or when its checksum or its time field is bad: a corrupted time is no time)."""
    try:
        if not split_frame(raw)[1]:
            return SentenceTime(None)  # bad checksum
        record = parse_sentence(raw)
    except ParseError:
        return SentenceTime(None)  # not one sentence, or a field that does not read
    tod = getattr(record, "tod_ns", None)
    if tod is not None:
        date = getattr(record, "date", None)
        return SentenceTime(tod, date if isinstance(date, dt.date) else None)
    index = OTHER_TIME_FIELDS.get(getattr(record, "kind", ""))
    fields = getattr(record, "fields", ())
    if index is None or index >= len(fields) or not fields[index]:
        return SentenceTime(None)
    try:
        return SentenceTime(time_of_day(fields[index]))
    except ValueError:
        return SentenceTime(None)


class NmeaClock:
    """Stamps live sentences, in receive order, with their epoch's UTC (module doc)."""

    def __init__(self) -> None:
        self._dated: tuple[int, int] | None = None  # (UTC, t_host) of the last dated one
        self._epoch: tuple[int, int] | None = None  # (UTC, t_host) of the open epoch

    def stamp(self, raw: bytes, t_host: int) -> int:
        """`publish_time` of one framed sentence received at `t_host` (ns)."""
        when = sentence_time(raw)
        if when.tod_ns is None:
            if self._epoch is not None and 0 <= t_host - self._epoch[1] <= EPOCH_SPAN_NS:
                return self._epoch[0]
            return t_host
        if when.date is not None:
            utc = utc_ns(when.tod_ns, when.date)
            self._dated = (utc, t_host)
        else:
            near = t_host if self._dated is None else self._dated[0] + t_host - self._dated[1]
            utc = nearest_utc_ns(when.tod_ns, near)
        if self._epoch is None or self._epoch[0] != utc:
            self._epoch = (utc, t_host)  # a new epoch opens at its first timed sentence
        return utc


def publish_times(sentences: Iterable[tuple[bytes, int]]) -> list[int]:
    """`publish_time` of each (raw sentence, t_host), in receive order."""
    clock = NmeaClock()
    return [clock.stamp(raw, t_host) for raw, t_host in sentences]
