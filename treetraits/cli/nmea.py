"""`treetraits nmea info`: summarise NMEA 0183 from a log, a recording or a live receiver."""

from __future__ import annotations

import argparse
import json
import sys

from treetraits.damage import add_allow_damaged, report_damage, source_integrity
from treetraits.errors import ConfigError, SourceError

_INPUT_HELP = (
    "an NMEA text log, an MCAP recording (format v1; its /gnss/nmea channel), a serial "
    "device (/dev/ttyUSB0, a symlink such as /dev/gnss) or serial:///dev/ttyUSB0?baud=N"
)


def register(commands: argparse._SubParsersAction) -> None:
    from treetraits.drivers import DEFAULT_BAUD

    nmea = commands.add_parser(
        "nmea",
        help="inspect NMEA 0183 GNSS logs, recordings and live receivers",
        description="NMEA 0183 GNSS data: count, check and summarise sentences and fixes.",
    )
    sub = nmea.add_subparsers(dest="nmea_command", metavar="COMMAND", required=True)

    info = sub.add_parser(
        "info",
        help="count sentences by type, checksum errors, fix quality, first/last fix",
        description=(
            "Read NMEA and summarise it. Sentences are found wherever a '$' starts one "
            "(after binary such as UBX, or glued to a cut sentence), so the counts follow "
            "the 'stream' rule of the test fixtures. Bad checksums are counted, never used. "
            "Sentences are grouped into epochs by UTC time; a fix is an epoch with a "
            "position and quality > 0. For a serial device, reads for --seconds (or until "
            "Ctrl-C). docs/gnss.md explains every key of --json."
        ),
    )
    info.add_argument("path", metavar="PATH", help=_INPUT_HELP)
    info.add_argument("--json", action="store_true", help="print one JSON object")
    info.add_argument(
        "--baud",
        type=int,
        help=f"serial baud rate (default {DEFAULT_BAUD}, or the serial:// URI's baud)",
    )
    info.add_argument(
        "--seconds",
        type=float,
        help="serial only: stop after this many seconds (default: until Ctrl-C)",
    )
    info.add_argument(
        "--ths-modes",
        default="A",
        metavar="MODES",
        help="THS modes whose heading is used (default A; AE also takes estimated headings)",
    )
    add_allow_damaged(info, "prints the summary")
    info.set_defaults(run=run_info)


def run_info(args: argparse.Namespace) -> int:
    from treetraits.drivers.gnss.sources import open_gnss_source
    from treetraits.drivers.gnss.summary import summarise

    if args.seconds is not None and args.seconds <= 0:
        raise ConfigError(f"--seconds must be positive, got {args.seconds}")
    if args.baud is not None and args.baud <= 0:
        raise ConfigError(f"--baud must be positive, got {args.baud}")
    modes = tuple(args.ths_modes.upper())
    if not set(modes) <= set("AEMSV"):
        raise ConfigError(f"--ths-modes takes letters of AEMSV, got {args.ths_modes!r}")
    source = open_gnss_source(args.path, baud=args.baud)
    if source.is_live:
        until = f"for {args.seconds:g} s" if args.seconds else "until Ctrl-C"
        print(f"reading {source.uri} {until}", file=sys.stderr)
    try:
        facts = summarise(source, seconds=args.seconds, ths_modes=modes)
    finally:
        source.close()
    if not source.is_live and facts["sentences"] == 0:
        # A text file with no sentence in it is not an NMEA log read as empty: refused.
        raise SourceError(
            f"{args.path}: no NMEA sentence was found in it (expected an NMEA log, or a "
            "recording with /gnss/nmea)"
        )
    status = 0
    if not source.is_live:
        status = report_damage(
            args.path, source_integrity(source), args.allow_damaged, "the counts are of the rest"
        )
    facts = {"source": source.uri, "is_live": source.is_live, **facts}
    if args.json:
        print(json.dumps(facts, indent=1))
    else:
        print(format_facts(facts))
    return status


def _counts(mapping: dict) -> str:
    return ", ".join(f"{k}: {v}" for k, v in mapping.items()) or "-"


def _fix(fix: dict | None) -> str:
    if fix is None:
        return "-"
    return (
        f"{fix['lat']:.9f}, {fix['lon']:.9f}  quality {fix['quality']}  "
        f"from {fix['source']}  at {fix['utc'] or 'unknown UTC'}"
    )


def _latency(latency_ms: float | None) -> str:
    if latency_ms is None:
        return "- (no receive times on UTC: a log file, or a host clock off UTC)"
    return f"{latency_ms:g} ms, the median from an epoch's UTC to its arrival"


def format_facts(facts: dict) -> str:
    """The human summary of `nmea info`."""
    duration = "-" if facts["duration_s"] is None else f"{facts['duration_s']:g} s"
    lines = [
        f"{facts['source']} ({'live' if facts['is_live'] else 'file'})",
        f"  bytes          {facts['bytes']}",
        f"  sentences      {facts['valid']} valid, {facts['bad_checksum']} bad checksum "
        f"(kept, not used), {facts['undecodable']} undecodable",
        f"  by type        {_counts(facts['valid_by_type'])}",
        f"  talkers        {' '.join(facts['talkers']) or '-'}",
        f"  skipped        {facts['truncated']} truncated, {facts['unterminated']} "
        f"unterminated, {facts['too_long']} too long, {facts['garbage_bytes']} garbage bytes",
        f"  GGA quality    {_counts(facts['gga_quality_histogram'])}",
        f"  headings       HDT {facts['hdt_with_value']}, THS {facts['ths_with_value']} "
        "with a value",
        f"  epochs         {facts['epochs']} ({facts['fixes']} with a fix)",
        f"  time           {facts['first_utc'] or '-'} .. {facts['last_utc'] or '-'} ({duration})",
        f"  latency        {_latency(facts['latency_ms'])}",
        f"  first fix      {_fix(facts['first_fix'])}",
        f"  last fix       {_fix(facts['last_fix'])}",
    ]
    if facts["utc_backwards"]:
        lines.append(
            f"  warning        the receiver's UTC went backwards {facts['utc_backwards']} "
            "times (a reset or a GPS week rollover bug): no duration"
        )
    if facts["is_live"]:
        lines.append(
            f"  serial         {facts['disconnects']} disconnects, {facts['reconnects']} "
            f"reconnects, {facts['open_failures']} failed reopen attempts"
        )
        if facts["bytes"] == 0:
            lines.append(
                "  hint           no bytes at all: is the receiver powered, and does it output "
                "on this port?"
            )
        elif facts["sentences"] == 0:
            lines.append(
                "  hint           bytes but no NMEA: wrong baud rate (try --baud 38400 or "
                "115200), or the port outputs binary (UBX) only"
            )
    return "\n".join(lines)
