"""Damage in a recording or a capture, reported the same way by every command that reads
one (docs/cli.md, "Damaged inputs"): what was read is used and said to be partial, one
line on stderr says what was lost, and the exit status is 3 (completed with data loss)
unless `--allow-damaged` accepts the loss.

`integrity_facts` is the summary's account (`damaged_chunks`, `truncated`, `lost`,
`data_loss`), from the damage-tolerant recording reader or a capture's `truncated` flag;
`report_damage` prints the line and gives the exit status.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from treetraits.errors import EXIT_DATA_LOSS
from treetraits.files import iso_utc

if TYPE_CHECKING:
    from treetraits.drivers.recording import RecordingReader


def integrity_facts(recording: RecordingReader | None = None, truncated: bool = False) -> dict:
    """What could not be read: `damaged_chunks` (skipped, reading went on after them),
    `truncated` (the file is cut), `lost` (the recorded times the lost messages lie
    within, ISO UTC; "" where the file does not tell) and `data_loss`. Of a recording
    (its reader, once read as far as the command read it), else of a capture that is cut
    or not (`truncated`)."""
    if recording is None:
        return {"damaged_chunks": 0, "truncated": truncated, "lost": [], "data_loss": truncated}
    return {
        "damaged_chunks": recording.damaged_chunks,
        "truncated": recording.truncated,
        "lost": [
            {"from": iso_utc(d.lost_from_ns), "to": iso_utc(d.lost_to_ns)} for d in recording.damage
        ],
        "data_loss": recording.lost_data,
    }


def source_integrity(source: Any) -> dict:
    """`integrity_facts` of a file source (LiDAR or GNSS): its recording's when it reads
    one, else its own `truncated` flag (a cut pcap or raw file; a text log has none)."""
    recording = getattr(source, "recording", None)
    if recording is not None:
        return integrity_facts(recording)
    return integrity_facts(truncated=bool(getattr(source.stats, "truncated", False)))


def add_allow_damaged(parser: argparse.ArgumentParser, what: str) -> None:
    """The one `--allow-damaged` of every command that reads a recording or a capture;
    `what`: what the command gives of the part it could read ("writes the outputs")."""
    parser.add_argument(
        "--allow-damaged",
        action="store_true",
        help=f"exit 0 also when the input is damaged or cut (without it such a run still "
        f"{what} of what it read, but exits {EXIT_DATA_LOSS}: completed with data loss)",
    )


def format_loss(facts: dict, rest: str = "the outputs are from the rest") -> str:
    """One line on what of the input could not be read, and what `rest` is made of it."""
    return f"{describe_loss(facts)}; {rest} (exit {EXIT_DATA_LOSS}; --allow-damaged accepts it)"


def describe_loss(facts: dict) -> str:
    """What of the input could not be read, and when it was recorded."""
    parts = []
    if facts["damaged_chunks"]:
        parts.append(f"{facts['damaged_chunks']} damaged chunk(s) skipped")
    if facts["truncated"]:
        parts.append("the file is cut short")
        if facts.get("field_map", {}).get("source") == "none":
            # The simulator attaches the field map at the end of its recording (the live
            # recorder at the start): cut, it is lost and the trees go unmatched.
            parts.append(
                "no field map was read (one attached to the recording would be in the part "
                "cut off; give --field-map FILE)"
            )
    spans = "; ".join(
        f"between {s['from'] or 'the start'} and {s['to'] or 'the end'}" for s in facts["lost"]
    )
    lost = f"; messages lost {spans}" if spans else ""
    return f"{' and '.join(parts) or 'damaged'}{lost}"


def report_damage(
    path: object, facts: dict, allow_damaged: bool, rest: str = "the outputs are from the rest"
) -> int:
    """The DATA LOSS line on stderr when `facts` say data was lost; the exit status: 3
    then, unless `allow_damaged`, else 0. Facts without the account say no loss."""
    if not facts.get("data_loss"):
        return 0
    print(f"treetraits: warning: {path}: DATA LOSS: {format_loss(facts, rest)}", file=sys.stderr)
    return 0 if allow_damaged else EXIT_DATA_LOSS
