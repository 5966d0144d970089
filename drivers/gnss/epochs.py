"""Sentences to GNSS epochs: a push assembler, decoded records in, `drivers.records.Fix` out.

A receiver sends one burst of sentences per epoch (GGA, RMC, GST, ZDA carry the epoch's UTC
time of day; VTG, HDT, THS and GSA carry none). The recipe:

1. group by UTC time of day: a timed sentence with a new time closes the open epoch and
   opens the next; a sentence without a time joins the open epoch (so a receiver that sends
   an untimed sentence *before* the timed ones of its burst has it counted one epoch early:
   text alone cannot tell the two orders apart);
2. per epoch, the first sentence of each type is used (a second GGA from another talker,
   SiRF's GLGGA for instance, is counted in `repeated` and ignored);
3. position, quality, satellites, HDOP, altitude, geoid separation and correction age come
   from GGA; when the epoch has no GGA position, position and a quality derived from the
   RMC status/mode (`RMC_MODE_QUALITY`) come from RMC;
4. standard deviations from GST; heading from THS when its mode is accepted (default: A
   only; E is dead reckoning), else none if THS was sent, else from HDT; course and speed
   from RMC (status A) with VTG (mode not N) filling what RMC left empty;
5. the date from the epoch's ZDA, else its RMC, else the last date seen (rolled over at
   midnight) makes `utc_ns`; None until a first date arrives;
6. an epoch with neither GGA nor RMC (a lone ZDA, GST or HDT) is not emitted: no position.

Bad-checksum sentences never get here (`sentences.decode` returns None for them).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, field

from treetraits.drivers.gnss.sentences import GGA, GST, HDT, RMC, THS, VTG, ZDA, NmeaRecord
from treetraits.drivers.records import Fix

NS_PER_DAY = 86_400 * 1_000_000_000
_EPOCH_DATE = dt.date(1970, 1, 1)

# RMC's mode indicator (NMEA 2.3+) as a GGA quality, for epochs without a GGA position.
RMC_MODE_QUALITY = {"N": 0, "A": 1, "D": 2, "P": 3, "R": 4, "F": 5, "E": 6, "M": 7, "S": 8}

# The record types the assembler reads; any other record is ignored (not counted).
USED_TYPES = (GGA, RMC, VTG, GST, HDT, THS, ZDA)


@dataclass
class EpochStats:
    records: int = 0  # records of the used types pushed
    epochs: int = 0  # Fix records emitted
    undated: int = 0  # of them, with utc_ns None (no date seen yet)
    position_from_rmc: int = 0  # of them, positioned by RMC for want of a GGA position
    without_position_source: int = 0  # epochs with neither GGA nor RMC: not emitted
    repeated: int = 0  # a second sentence of one type in an epoch: the first is used
    ths_rejected: int = 0  # THS headings dropped for their mode

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass
class _Epoch:
    t_host: int  # receive time of the epoch's first sentence
    tod_ns: int | None
    parts: dict[str, NmeaRecord] = field(default_factory=dict)


class EpochAssembler:
    """Push decoded records in order; `push` returns a `Fix` when a record closes an epoch,
    `flush` returns the last one. `ths_modes` are the THS modes whose heading is used.
    For the last emitted fix, `last_position_source` is "GGA" or "RMC" (None: no
    position) and `last_tod_ns` its UTC time of day (kept even while no date is known).
    """

    def __init__(self, ths_modes: Iterable[str] = ("A",)):
        self.ths_modes = frozenset(ths_modes)
        self.stats = EpochStats()
        self.last_position_source: str | None = None
        self.last_tod_ns: int | None = None
        self._epoch: _Epoch | None = None
        self._date: dt.date | None = None  # the last date seen, and the time of day it held at
        self._date_tod = 0

    def push(self, record: NmeaRecord) -> Fix | None:
        if not isinstance(record, USED_TYPES):
            return None
        self.stats.records += 1
        tod = getattr(record, "tod_ns", None)
        fix = None
        epoch = self._epoch
        if epoch is None or (tod is not None and epoch.tod_ns is not None and tod != epoch.tod_ns):
            fix = self.flush()
            epoch = self._epoch = _Epoch(record.t_host, tod)
        elif epoch.tod_ns is None:
            epoch.tod_ns = tod  # untimed sentences came first: the epoch takes this time
        if record.kind in epoch.parts:
            self.stats.repeated += 1
        else:
            epoch.parts[record.kind] = record
        return fix

    def flush(self) -> Fix | None:
        """Close the open epoch (end of stream): its Fix, or None."""
        epoch, self._epoch = self._epoch, None
        return None if epoch is None else self._fix(epoch)

    def _utc_ns(self, epoch: _Epoch) -> int | None:
        if epoch.tod_ns is None:
            return None
        zda, rmc = epoch.parts.get("ZDA"), epoch.parts.get("RMC")
        date = zda.date if isinstance(zda, ZDA) else None
        if date is None and isinstance(rmc, RMC):
            date = rmc.date
        if date is None and self._date is not None:
            date = self._date
            if epoch.tod_ns < self._date_tod - NS_PER_DAY // 2:
                date += dt.timedelta(days=1)  # past midnight since the last dated epoch
        if date is None:
            return None
        self._date, self._date_tod = date, epoch.tod_ns
        return (date - _EPOCH_DATE).days * NS_PER_DAY + epoch.tod_ns

    def _fix(self, epoch: _Epoch) -> Fix | None:
        parts = epoch.parts
        gga: GGA | None = parts.get("GGA")  # type: ignore[assignment]
        rmc: RMC | None = parts.get("RMC")  # type: ignore[assignment]
        utc_ns = self._utc_ns(epoch)  # also keeps the date going for later epochs
        if gga is None and rmc is None:
            self.stats.without_position_source += 1
            return None
        rmc_valid = rmc is not None and rmc.status == "A"
        rmc_quality = 0
        if rmc is not None and rmc_valid:
            rmc_quality = RMC_MODE_QUALITY.get(rmc.mode, 0) if rmc.mode else 1
        if gga is not None and gga.lat is not None and gga.lon is not None:
            lat, lon, source = gga.lat, gga.lon, "GGA"
        elif rmc is not None and rmc.lat is not None and rmc.lon is not None:
            lat, lon, source = rmc.lat, rmc.lon, "RMC"
            self.stats.position_from_rmc += 1
        else:
            lat = lon = source = None
        if gga is not None and gga.quality is not None and source != "RMC":
            quality = gga.quality
        else:
            quality = rmc_quality
        self.last_position_source = source
        self.last_tod_ns = epoch.tod_ns

        gst: GST | None = parts.get("GST")  # type: ignore[assignment]
        vtg: VTG | None = parts.get("VTG")  # type: ignore[assignment]
        course = speed = None
        if rmc is not None and rmc_valid:
            course, speed = rmc.course_deg, rmc.speed_mps
        if vtg is not None and vtg.mode != "N":
            course = vtg.course_true_deg if course is None else course
            speed = vtg.speed_mps if speed is None else speed

        self.stats.epochs += 1
        self.stats.undated += utc_ns is None
        return Fix(
            t_host=epoch.t_host,
            utc_ns=utc_ns,
            lat=lat,
            lon=lon,
            altitude_msl_m=None if gga is None else gga.altitude_m,
            geoid_separation_m=None if gga is None else gga.geoid_separation_m,
            quality=quality,
            satellites=None if gga is None else gga.satellites,
            hdop=None if gga is None else gga.hdop,
            std_lat_m=None if gst is None else gst.std_lat_m,
            std_lon_m=None if gst is None else gst.std_lon_m,
            std_alt_m=None if gst is None else gst.std_alt_m,
            heading_deg=self._heading(parts),
            course_deg=course,
            speed_mps=speed,
            correction_age_s=None if gga is None else gga.correction_age_s,
        )

    def _heading(self, parts: dict[str, NmeaRecord]) -> float | None:
        ths, hdt = parts.get("THS"), parts.get("HDT")
        if isinstance(ths, THS):
            # THS says whether its heading is valid; an HDT beside it (same source,
            # no validity flag) is not trusted over a THS that says no.
            if ths.heading_deg is not None and ths.mode not in self.ths_modes:
                self.stats.ths_rejected += 1
                return None
            return ths.heading_deg
        return hdt.heading_deg if isinstance(hdt, HDT) else None


def assemble(records: Iterable[NmeaRecord | None], **options) -> Iterator[Fix]:
    """Every Fix of a finite sequence of records (None entries are skipped)."""
    assembler = EpochAssembler(**options)
    for record in records:
        if record is not None:
            fix = assembler.push(record)
            if fix is not None:
                yield fix
    last = assembler.flush()
    if last is not None:
        yield last
