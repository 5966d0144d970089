"""Shared test helpers: the real VLP-16 fixtures and their reference facts."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne.reader import LidarReader
from treetraits.drivers.velodyne.sources import open_source

FIXTURES = Path(__file__).parent / "fixtures"
VLP16_DIR = FIXTURES / "vlp16"
# Every real VLP-16 capture we hold (secondary/ holds other models).
VLP16_CAPTURES = [
    "einride_vlp16_strongest_1000pkts.bin",
    "lidarutils_vlp16_strongest_0x21_with_position.pcap",
    "lidarutils_vlp16_strongest_0x22.pcap",
    "nebula_vlp16_dual_10hz.pcap",
    "veloview_vlp16_20hz_strongest.pcap",
]


# trees.csv's first columns as docs/architecture.md fixes them (restated here, not imported
# from the code): never reordered or renamed. A new column is appended after them in
# pipeline/trees.py's table, and the tests check the header starts with these.
CONTRACT_CSV_COLUMNS = [
    "tree_id",
    "field_id",
    "row",
    "easting",
    "northing",
    "utm_zone",
    "lat",
    "lon",
    "width_m",
    "height_m",
    "ndvi",
    "observations",
    "first_seen",
    "last_seen",
    "status",  # appended after the contract's fourteen: found or missing
    "height_top_seen",  # appended: true, false (height a lower bound) or empty
]


def chunk_spans(path: Path) -> list:
    """(start offset, end offset, chunk record) of every chunk of an MCAP file, read with
    mcap's own reader (not ours): where to damage a recording in a test."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    chunks = []
    with open(path, "rb") as f:
        records = StreamReader(f, emit_chunks=True).records
        start = f.tell()
        for record in records:
            if isinstance(record, Chunk):
                chunks.append((start, f.tell(), record))
            start = f.tell()
    return chunks


def reference(name: str) -> dict:
    """The reference facts shipped beside a capture (`*.reference.json`)."""
    return json.loads((VLP16_DIR / f"{name}.reference.json").read_text())


def decode_file(path: str | Path, **options) -> tuple[list[Scan], LidarReader]:
    """All scans of a capture through the public source + batcher path."""
    reader = LidarReader(open_source(path), **options)
    scans = [item for item in reader if isinstance(item, Scan)]
    reader.close()
    return scans, reader


@pytest.fixture(params=VLP16_CAPTURES)
def capture(request) -> str:
    return request.param


@pytest.fixture
def decode_calls(monkeypatch):
    """Counts every JPEG decode in the process, OpenCV's (`cv2.imdecode`) and the frames'
    (`simplejpeg.decode_jpeg`, `Frame.decode`); the real ones still run."""
    import simplejpeg

    calls = []

    def counting(real):
        def decode(*args, **kwargs):
            calls.append(1)
            return real(*args, **kwargs)

        return decode

    monkeypatch.setattr(cv2, "imdecode", counting(cv2.imdecode))
    monkeypatch.setattr(simplejpeg, "decode_jpeg", counting(simplejpeg.decode_jpeg))
    return calls


def first_complete_scan(scene, T_base_lidar, rng, seconds: float = 0.35):
    """The first complete scan the twin's VLP-16 emulator sends from a robot standing at
    the origin (yaw 0), decoded by our own batcher."""
    from treetraits.drivers.velodyne.batcher import ScanBatcher
    from treetraits.sim.lidar import Vlp16Emulator

    def standing(t):
        zeros = np.zeros(t.shape)
        return zeros, zeros, zeros, zeros

    batcher = ScanBatcher()
    emulator = Vlp16Emulator(scene, T_base_lidar, rng=rng)
    for t_device, payload in emulator.packets(standing, 0, int(seconds * 1e9)):
        scan = batcher.push(payload, t_device)
        if scan is not None and scan.complete:
            return scan
    raise AssertionError("no complete scan")
