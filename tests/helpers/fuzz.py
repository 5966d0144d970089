"""Damage for property tests (hypothesis): bytes flipped, inserted, deleted and cut."""

from __future__ import annotations

from hypothesis import strategies as st


def mutate(data: bytes, edits: list[tuple[int, int, int]], cut: int | None) -> bytes:
    """`edits`: (position, kind, byte): 0 replaces, 1 inserts, 2 deletes a byte."""
    buffer = bytearray(data)
    for position, kind, value in edits:
        if not buffer:
            break
        i = position % len(buffer)
        if kind == 0:
            buffer[i] = value
        elif kind == 1:
            buffer.insert(i, value)
        else:
            del buffer[i]
    if cut is not None and buffer:
        del buffer[cut % len(buffer) :]
    return bytes(buffer)


edits = st.lists(
    st.tuples(st.integers(0, 10**6), st.integers(0, 2), st.integers(0, 255)), max_size=8
)
cuts = st.none() | st.integers(0, 10**6)
