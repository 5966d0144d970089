"""pipeline/localization/least_delay.py and serial_clock.py: device stamps onto the host
clock by the least delay, through backlogs and clock jumps."""

from __future__ import annotations

import itertools

from treetraits.pipeline.localization.least_delay import LeastDelayOffset
from treetraits.pipeline.localization.serial_clock import (
    MAX_SERIAL_WAIT_NS,
    SERIAL_WINDOW_NS,
    SerialClock,
)

MS = 1_000_000
HOST_MINUS_DEVICE = 1_700_000_000_000_000_000  # the MCU counts from somewhere else
LEAST_DELAY = 2 * MS  # transport and read, unloaded


def read_times(stamps: list[int], backlog: tuple[int, int]) -> list[int]:
    """When an unloaded host reads each message, except those stamped in `backlog`
    (start, end): held in the pty and read together at its end, 1 us apart."""
    out = []
    for k, stamp in enumerate(stamps):
        t = stamp + HOST_MINUS_DEVICE + LEAST_DELAY
        if backlog[0] <= stamp < backlog[1]:
            t = backlog[1] + HOST_MINUS_DEVICE + LEAST_DELAY + k * 1000
        out.append(t)
    return out


def test_backlogged_messages_are_placed_at_their_stamp_plus_the_least_delay():
    stamps = [k * 20 * MS for k in range(200)]  # 50 Hz for 4 s
    # 600 ms of bytes held, then read within the same millisecond.
    t_host = read_times(stamps, (1_000 * MS, 1_600 * MS))
    assert max(b - a for a, b in itertools.pairwise(t_host)) > 600 * MS  # the gap
    clock = SerialClock.new()
    placed = [clock.place(t, s) for t, s in zip(t_host, stamps, strict=True)]
    assert placed == [s + HOST_MINUS_DEVICE + LEAST_DELAY for s in stamps]
    assert all(p <= t for p, t in zip(placed, t_host, strict=True))  # never later than it was read


def test_a_stamp_that_is_missing_keeps_its_read_time():
    clock = SerialClock.new()
    assert clock.place(5 * MS, None) == 5 * MS
    assert clock.place(6 * MS, 0) == 6 * MS
    assert clock.offset.offset is None


def test_a_device_clock_stepped_back_restarts_the_estimate():
    """An MCU reset counts from its boot again: its stamps go back by far more than any
    wait, and the estimate restarts on the first of them instead of placing the next
    messages seconds early for a whole window."""
    offset = LeastDelayOffset(SERIAL_WINDOW_NS, MAX_SERIAL_WAIT_NS)
    t = 0
    for k in range(100):
        t = HOST_MINUS_DEVICE + k * 20 * MS + LEAST_DELAY
        assert offset.add(t, k * 20 * MS) == HOST_MINUS_DEVICE + LEAST_DELAY
    step_back = 30_000 * MS  # the MCU's clock 30 s behind where it was
    after = t + 20 * MS
    stamp = after - LEAST_DELAY - HOST_MINUS_DEVICE - step_back
    assert offset.add(after, stamp) == HOST_MINUS_DEVICE + step_back + LEAST_DELAY
    assert offset.restarts == 1


def test_a_wait_within_the_bound_is_a_delay_not_a_jump():
    offset = LeastDelayOffset(SERIAL_WINDOW_NS, MAX_SERIAL_WAIT_NS)
    offset.add(LEAST_DELAY, 0)
    late = MAX_SERIAL_WAIT_NS - 1  # read this much later than the least delay says
    assert offset.add(20 * MS + LEAST_DELAY + late, 20 * MS) == LEAST_DELAY
    assert offset.restarts == 0


def test_a_device_clock_stepped_forward_is_followed_at_once():
    offset = LeastDelayOffset(SERIAL_WINDOW_NS, MAX_SERIAL_WAIT_NS)
    for k in range(10):
        offset.add(k * 20 * MS + LEAST_DELAY, k * 20 * MS)
    # A time sync moves the device's clock 5 s ahead: the delay drops, the least follows.
    t = 10 * 20 * MS + LEAST_DELAY
    assert offset.add(t, 10 * 20 * MS + 5_000 * MS) == LEAST_DELAY - 5_000 * MS


def test_the_least_delay_leaves_the_window_and_the_estimate_follows_a_drift():
    """A device clock running 100 ppm slow: the offset grows 2 us per 20 ms message; the
    estimate lags it by at most the window's drift."""
    offset = LeastDelayOffset(SERIAL_WINDOW_NS)
    for k in range(2000):  # 40 s
        t = k * 20 * MS
        stamp = int(t * (1 - 100e-6))
        estimate = offset.add(t + LEAST_DELAY, stamp)
        true = t - stamp + LEAST_DELAY
        assert 0 <= true - estimate <= SERIAL_WINDOW_NS * 100e-6 + 1
