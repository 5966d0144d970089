"""Recordings (MCAP files) as a test damages them."""

from __future__ import annotations

from pathlib import Path


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
