"""The real VLP-16 fixtures and their reference facts."""

from __future__ import annotations

import json
from pathlib import Path

from tests.helpers.paths import FIXTURES
from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne.reader import LidarReader
from treetraits.drivers.velodyne.sources import open_source

VLP16_DIR = FIXTURES / "vlp16"
# Every real VLP-16 capture we hold (secondary/ holds other models).
VLP16_CAPTURES = [
    "einride_vlp16_strongest_1000pkts.bin",
    "lidarutils_vlp16_strongest_0x21_with_position.pcap",
    "lidarutils_vlp16_strongest_0x22.pcap",
    "nebula_vlp16_dual_10hz.pcap",
    "veloview_vlp16_20hz_strongest.pcap",
]


def reference(name: str) -> dict:
    """The reference facts shipped beside a capture (`*.reference.json`)."""
    return json.loads((VLP16_DIR / f"{name}.reference.json").read_text())


def decode_file(path: str | Path, **options) -> tuple[list[Scan], LidarReader]:
    """All scans of a capture through the public source + batcher path."""
    reader = LidarReader(open_source(path), **options)
    scans = [item for item in reader if isinstance(item, Scan)]
    reader.close()
    return scans, reader
