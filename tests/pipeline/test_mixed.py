"""Mixed returns (`pipeline.mixed`): a return between an object's edge and what stands
behind it, on made-up rings and on the real captures."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.captures import VLP16_DIR, decode_file
from tests.helpers.paths import FIXTURES
from treetraits.drivers.records import POINT_DTYPE
from treetraits.pipeline.config import ClusterConfig
from treetraits.pipeline.mixed import mixed_returns

TOLERANCE_M = ClusterConfig().tolerance_m
OFFSET_M = ClusterConfig().mixed_offset_m
STEP_RAD = np.radians(0.2)  # a VLP-16's firing step at 600 rpm


def ring_of(ranges: list[float] | np.ndarray, ring: int = 7) -> np.ndarray:
    """One ring's returns in firing order, level, at the given ranges."""
    points = np.zeros(len(ranges), dtype=POINT_DTYPE)
    azimuth = np.arange(len(ranges)) * STEP_RAD
    points["azimuth"] = azimuth
    points["x"] = np.sin(azimuth) * np.asarray(ranges)
    points["y"] = np.cos(azimuth) * np.asarray(ranges)
    points["t"] = np.arange(len(ranges)) * 55_296  # ns: one firing sequence apart
    points["ring"] = ring
    points["return_type"] = 1
    return points


def test_the_return_between_an_edge_and_the_wall_behind_it_is_mixed():
    # An object's face at 6.5 m, its edge return at 7.6 m, the wall behind at 9.3 m.
    ranges = [6.5] * 6 + [7.6] + [9.3] * 6
    assert np.flatnonzero(mixed_returns(ring_of(ranges), TOLERANCE_M, OFFSET_M)).tolist() == [6]


def test_a_clean_edge_and_a_small_step_leave_nothing_out():
    clean = [6.5] * 6 + [9.3] * 6
    assert not mixed_returns(ring_of(clean), TOLERANCE_M, OFFSET_M).any()
    # Surfaces 0.4 m apart cluster together anyway: the return between them links nothing.
    small = [6.5] * 6 + [6.7] + [6.9] * 6
    assert not mixed_returns(ring_of(small), TOLERANCE_M, OFFSET_M).any()


def test_foliage_depths_are_rarely_taken_for_mixed_returns():
    """Consecutive beams on a crown fall on leaves decimetres apart in depth: a jump's sides
    seldom go on as surfaces, so a crown keeps nearly all its returns (the real orchard
    capture: 2.8 per mille left out, below)."""
    rng = np.random.default_rng(3)
    crown = 4.0 + rng.uniform(-0.4, 0.4, 4000)
    found = mixed_returns(ring_of(crown), TOLERANCE_M, OFFSET_M)
    assert found.mean() < 0.005
    # Not by chance: the same depths sorted into two smooth surfaces with a jump do lose
    # the return between them.
    assert mixed_returns(ring_of([3.7] * 5 + [4.0] + [4.3] * 5), 0.5, OFFSET_M).sum() == 1


def test_a_missing_firing_breaks_the_ring():
    points = ring_of([6.5] * 6 + [7.6] + [9.3] * 6)
    points["azimuth"][7:] += 3 * STEP_RAD  # two firings gave no return after the edge one
    assert not mixed_returns(points, TOLERANCE_M, OFFSET_M).any()


def test_offset_zero_keeps_every_return():
    points = ring_of([6.5] * 6 + [7.6] + [9.3] * 6)
    assert not mixed_returns(points, TOLERANCE_M, 0.0).any()


def test_order_does_not_matter():
    """Returns out of firing order (a converted bag) give the same returns, on a real scan."""
    scans, _ = decode_file(VLP16_DIR / "einride_vlp16_strongest_1000pkts.bin")
    points = scans[4].points
    found = mixed_returns(points, TOLERANCE_M, OFFSET_M)
    assert found.any()
    shuffle = np.random.default_rng(1).permutation(len(points))
    assert np.array_equal(mixed_returns(points[shuffle], TOLERANCE_M, OFFSET_M), found[shuffle])


# Real captures: what the rule leaves out, per mille of the returns over the first 20
# scans. Indoors, the edges of furniture and door frames against the walls; in the
# orchard, canopy edges against the rows behind (each scan a cross-section of two rows).
@pytest.mark.parametrize(
    ("path", "at_most"),
    [
        (VLP16_DIR / "einride_vlp16_strongest_1000pkts.bin", 1.0),
        (VLP16_DIR / "veloview_vlp16_20hz_strongest.pcap", 1.0),
        (VLP16_DIR / "nebula_vlp16_dual_10hz.pcap", 1.0),
        (FIXTURES / "real_orchard" / "lfuji_apple_vlp16_sideways_2s.pcap", 5.0),
    ],
    ids=lambda value: getattr(value, "stem", value),
)
def test_real_captures_lose_a_few_returns_per_mille(path, at_most):
    scans, _ = decode_file(path)
    flagged = [mixed_returns(scan.points, TOLERANCE_M, OFFSET_M) for scan in scans[:20]]
    per_mille = 1000 * sum(f.sum() for f in flagged) / sum(len(f) for f in flagged)
    assert 0 < per_mille <= at_most
    for scan, found in zip(scans, flagged, strict=False):
        if scan.points["return_type"].any():  # dual returns: only last echoes are read
            assert np.all(scan.points["return_type"][found] == 1)
