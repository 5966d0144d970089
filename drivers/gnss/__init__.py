"""The GNSS driver: NMEA 0183 from a serial port, a text log or a recording.

Bytes go through `SentenceSplitter` (framing and resynchronisation, counters for all that is
skipped) into `Sentence`s with their raw bytes and `t_host`; `parse_sentence`/`decode` turn
those into typed records (GGA, RMC, VTG, GST, HDT, THS, GSA, ZDA); `EpochAssembler` groups
records by UTC time into `drivers.records.Fix`. `open_gnss_source(uri)` gives the sentences
of a live receiver, a log or a recording alike. Conventions: docs/gnss.md.
"""

from treetraits.drivers.gnss.epochs import EpochAssembler, EpochStats, assemble
from treetraits.drivers.gnss.sentences import (
    GGA,
    GSA,
    GST,
    HDT,
    LAYOUTS,
    RMC,
    THS,
    VTG,
    ZDA,
    NmeaRecord,
    OtherSentence,
    Sentence,
    checksum,
    decode,
    parse_sentence,
    sentence_type,
)
from treetraits.drivers.gnss.sources import (
    GnssSource,
    LogSource,
    RecordingSource,
    SerialSource,
    SourceStats,
    open_gnss_source,
)
from treetraits.drivers.gnss.stream import SentenceSplitter, SplitterStats
from treetraits.drivers.gnss.summary import NmeaSummary, summarise

__all__ = [
    "GGA",
    "GSA",
    "GST",
    "HDT",
    "LAYOUTS",
    "RMC",
    "THS",
    "VTG",
    "ZDA",
    "EpochAssembler",
    "EpochStats",
    "GnssSource",
    "LogSource",
    "NmeaRecord",
    "NmeaSummary",
    "OtherSentence",
    "RecordingSource",
    "Sentence",
    "SentenceSplitter",
    "SerialSource",
    "SourceStats",
    "SplitterStats",
    "assemble",
    "checksum",
    "decode",
    "open_gnss_source",
    "parse_sentence",
    "sentence_type",
    "summarise",
]
