"""service/survey_start.py: the survey's first firing on the host clock, by the least
delay of its first packets (what a video played as the camera is stamped from)."""

from __future__ import annotations

import numpy as np

from treetraits.drivers.velodyne import models as m
from treetraits.drivers.velodyne.encode import encode_packets
from treetraits.service.survey_start import ANCHOR_SPAN_NS, SurveyStart

FIRST_FIRING = 1_778_605_200_000_000_000  # host clock, ns
LEAST_DELAY = 300_000  # loopback UDP, unloaded


def packets(count: int, first_toh_us: int) -> list[bytes]:
    shape = (count, m.BLOCKS_PER_PACKET, m.RECORDS_PER_BLOCK)
    toh = first_toh_us + np.arange(count) * m.PACKET_NS_SINGLE // 1000
    data = encode_packets(
        np.zeros((count, m.BLOCKS_PER_PACKET), dtype=int),
        np.zeros(shape, dtype=int),
        np.zeros(shape, dtype=int),
        toh,
    )
    return [data[k * m.DATA_PACKET_SIZE : (k + 1) * m.DATA_PACKET_SIZE] for k in range(count)]


def test_late_first_packets_do_not_move_the_start():
    """The first 20 packets read 3 ms late (a loaded host), the rest on time; the packets'
    ToH runs across the hour. The estimate is the first firing plus the least delay."""
    start = SurveyStart()
    first_toh = 3_600_000_000 - 10_000  # 10 ms before the hour: the ToH wraps
    for k, packet in enumerate(packets(100, first_toh)):
        sent = FIRST_FIRING + (k + 1) * m.PACKET_NS_SINGLE
        start.add(packet, sent + LEAST_DELAY + (3_000_000 if k < 20 else 0))
    # The ToH counts whole microseconds.
    assert 0 <= start.first_firing_ns - (FIRST_FIRING + LEAST_DELAY) < 1000


def test_the_estimate_is_fixed_after_the_span():
    start = SurveyStart()
    first, later = packets(2, 0)
    assert start.add(first, FIRST_FIRING + m.PACKET_NS_SINGLE + 5_000_000)
    settled = start.first_firing_ns
    # A packet after the span, however little delayed, changes nothing.
    t = FIRST_FIRING + ANCHOR_SPAN_NS + 10 * m.PACKET_NS_SINGLE
    assert not start.add(later, t)
    assert start.first_firing_ns == settled
    assert not start.add(b"not a data packet", FIRST_FIRING)
