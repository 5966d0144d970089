"""Facts about an NMEA stream, gathered in one pass (for `treetraits nmea info`).

Counts follow the "stream" rule of the NMEA fixtures' PROVENANCE.md: a sentence is found
wherever it starts (after binary, or glued to a cut sentence), and `valid_by_type` keys the
checksum-valid sentences by type (the address minus its two-letter talker; a proprietary
`P...` address is its own type). The `docs/gnss.md` table explains every key.
"""

from __future__ import annotations

import datetime as dt
import time
from collections import Counter
from dataclasses import dataclass, field

from treetraits.drivers.gnss.epochs import NS_PER_DAY, EpochAssembler
from treetraits.drivers.gnss.sentences import GGA, HDT, THS, Sentence, decode, sentence_type
from treetraits.drivers.gnss.sources import GnssSource
from treetraits.drivers.records import Fix
from treetraits.errors import ParseError


def _fix_facts(fix: Fix, source: str | None, tod_ns: int | None) -> dict:
    return {
        "lat": fix.lat,
        "lon": fix.lon,
        "quality": fix.quality,
        "utc": None if tod_ns is None else _time_text(fix.utc_ns, tod_ns),
        "source": source,
        "t_host": fix.t_host,
    }


def _time_text(utc_ns: int | None, tod_ns: int) -> str:
    """ISO 8601 UTC (`2019-04-12T00:39:56.000Z`), or the time of day alone (`00:39:56.000`)
    while the receiver has sent no date."""
    seconds, nanos = divmod(tod_ns, 1_000_000_000)
    hours, minutes = seconds // 3600, seconds // 60 % 60
    text = f"{hours:02d}:{minutes:02d}:{seconds % 60:02d}.{nanos // 1_000_000:03d}"
    if utc_ns is None:
        return text
    day = dt.date(1970, 1, 1) + dt.timedelta(days=utc_ns // NS_PER_DAY)
    return f"{day.isoformat()}T{text}Z"


def _seconds_between(first: tuple[int | None, int], last: tuple[int | None, int]) -> float:
    """From one epoch time to a later one: by full UTC when both are dated, else by time of
    day, a drop of more than 12 h being a midnight crossing."""
    (first_utc, first_tod), (last_utc, last_tod) = first, last
    if first_utc is not None and last_utc is not None:
        return (last_utc - first_utc) / 1e9
    step = last_tod - first_tod
    if step < -NS_PER_DAY // 2:
        step += NS_PER_DAY
    return step / 1e9


@dataclass
class NmeaSummary:
    """Feed every framed sentence with `add`; read the facts with `as_dict`."""

    ths_modes: tuple[str, ...] = ("A",)
    valid_by_address: Counter = field(default_factory=Counter)
    bad_checksum_by_address: Counter = field(default_factory=Counter)
    undecodable_by_address: Counter = field(default_factory=Counter)
    gga_quality: Counter = field(default_factory=Counter)
    hdt_with_value: int = 0
    ths_with_value: int = 0
    fixes: int = 0  # epochs with a position and quality > 0
    # First and last fix by position source: GGA's are reported; RMC's only when the
    # stream has no GGA fix at all (the fixtures' definition).
    edge_fixes: dict[str, list[dict]] = field(default_factory=dict)
    utc_backwards: int = 0  # epochs whose UTC is earlier than the previous epoch's
    # Arrival after the epoch's UTC (ns) of each dated epoch: the receiver's latency when
    # the host clock was on UTC (a recording made with NTP), else a clock offset.
    delays: list[int] = field(default_factory=list, repr=False)
    # (utc_ns or None, time of day) of the first and last epoch with a time
    _first_time: tuple[int | None, int] | None = field(default=None, init=False, repr=False)
    _last_time: tuple[int | None, int] | None = field(default=None, init=False, repr=False)
    assembler: EpochAssembler = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.assembler = EpochAssembler(ths_modes=self.ths_modes)

    def add(self, sentence: Sentence) -> Fix | None:
        """Count one sentence; returns the Fix it completed, if any."""
        if not sentence.checksum_ok:
            self.bad_checksum_by_address[sentence.address] += 1
            return None
        self.valid_by_address[sentence.address] += 1
        try:
            record = decode(sentence)
        except ParseError:
            self.undecodable_by_address[sentence.address] += 1
            return None
        if isinstance(record, GGA):
            self.gga_quality["empty" if record.quality is None else str(record.quality)] += 1
        elif isinstance(record, HDT):
            self.hdt_with_value += record.heading_deg is not None
        elif isinstance(record, THS):
            self.ths_with_value += record.heading_deg is not None
        fix = self.assembler.push(record) if record is not None else None
        if fix is not None:
            self._add_fix(fix)
        return fix

    def finish(self) -> Fix | None:
        """End of stream: the last epoch's Fix, if any."""
        fix = self.assembler.flush()
        if fix is not None:
            self._add_fix(fix)
        return fix

    def _add_fix(self, fix: Fix) -> None:
        if fix.utc_ns is not None:
            self.delays.append(fix.t_host - fix.utc_ns)
        tod = self.assembler.last_tod_ns
        if tod is not None:
            now = (fix.utc_ns, tod)
            if self._last_time is not None and _seconds_between(self._last_time, now) < 0:
                self.utc_backwards += 1
            self._first_time = now if self._first_time is None else self._first_time
            self._last_time = now
        if fix.quality > 0 and fix.lat is not None and fix.lon is not None:
            self.fixes += 1
            source = self.assembler.last_position_source or ""
            facts = _fix_facts(fix, source, tod)
            edges = self.edge_fixes.setdefault(source, [facts, facts])
            edges[1] = facts

    def as_dict(self, counters: dict[str, int | bool]) -> dict:
        """The `nmea info --json` object; `counters` from the source's `counters()`."""
        by_type: Counter = Counter()
        for address, count in self.valid_by_address.items():
            by_type[sentence_type(address)] += count
        talkers = sorted({a[:2] for a in self.valid_by_address if not a.startswith("P")})
        epochs = self.assembler.stats
        duration = None
        if self._first_time is not None and self._last_time is not None and not self.utc_backwards:
            duration = _seconds_between(self._first_time, self._last_time)
        first_fix = last_fix = None
        for source in ("GGA", "RMC"):
            if source in self.edge_fixes:
                first_fix, last_fix = self.edge_fixes[source]
                break
        facts = {
            "sentences": counters.get("sentences", 0),
            "valid": sum(self.valid_by_address.values()),
            "valid_by_type": dict(sorted(by_type.items())),
            "valid_by_address": dict(sorted(self.valid_by_address.items())),
            "talkers": talkers,
            "bad_checksum": sum(self.bad_checksum_by_address.values()),
            "bad_checksum_by_address": dict(sorted(self.bad_checksum_by_address.items())),
            "undecodable": sum(self.undecodable_by_address.values()),
            "undecodable_by_address": dict(sorted(self.undecodable_by_address.items())),
            "gga_quality_histogram": dict(sorted(self.gga_quality.items())),
            "hdt_with_value": self.hdt_with_value,
            "ths_with_value": self.ths_with_value,
            "epochs": epochs.epochs,
            "fixes": self.fixes,
            "first_fix": first_fix,
            "last_fix": last_fix,
            "first_utc": None if self._first_time is None else _time_text(*self._first_time),
            "last_utc": None if self._last_time is None else _time_text(*self._last_time),
            "duration_s": duration,
            "utc_backwards": self.utc_backwards,
            "latency_ms": _latency_ms(self.delays),
        }
        facts.update({f"epochs_{k}": v for k, v in epochs.as_dict().items() if k != "epochs"})
        for key, value in counters.items():
            facts.setdefault(key, value)
        return facts


def _latency_ms(delays: list[int]) -> float | None:
    """The median arrival after UTC, when it can be a latency (0-1 s: the host clock was
    on UTC); None for a log read now or a host clock off UTC."""
    if not delays:
        return None
    median = sorted(delays)[len(delays) // 2] / 1e6
    return round(median, 1) if 0 <= median <= 1000 else None


def summarise(source: GnssSource, *, seconds: float | None = None, **options) -> dict:
    """Read `source` to its end and summarise it. A live source is read for `seconds`
    (None: until Ctrl-C, which then ends the reading, not the summary)."""
    summary = NmeaSummary(**options)
    try:
        if source.is_live:
            read = source.read  # type: ignore[attr-defined]
            deadline = None if seconds is None else time.monotonic() + seconds
            while deadline is None or (remaining := deadline - time.monotonic()) > 0:
                sentence = read(timeout=0.5 if deadline is None else remaining)
                if sentence is not None:
                    summary.add(sentence)
                elif source.closed:  # type: ignore[attr-defined]
                    break  # closed, or unplugged without reconnect
        else:
            for sentence in source:
                summary.add(sentence)
    except KeyboardInterrupt:
        if not source.is_live:
            raise
    summary.finish()
    return summary.as_dict(source.counters())
