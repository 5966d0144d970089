"""What lies under the crowns joins a crown only within reach and never links two
(`pipeline.understorey`): twin scans of a row with a drip line hung at 0.35 m and weeds
between the trees, seen from a robot at the origin."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.helpers.scans import scan_of
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.pipeline.classify import TREE
from treetraits.pipeline.config import ClusterConfig, DetectionConfig
from treetraits.pipeline.detection import detect
from treetraits.pipeline.understorey import join_understorey
from treetraits.sim.clutter import tube, weed_clump
from treetraits.sim.orchard import Ground, TreeSpec, tree_mesh

ROW_Y = 2.5
CROWN_RADIUS = 1.4  # the crowns are 2.8 m wide
WITHOUT = DetectionConfig(cluster=ClusterConfig(bridge_min_height_m=0.0))


def row_scan(x0: float):
    """Two trees 3.9 m apart (a 1.1 m gap between crowns), a drip line along the row
    0.3 m off the trunks and a weed clump in the gap."""
    rng = np.random.default_rng(4)
    specs = [
        TreeSpec("A", "1", x0, ROW_Y, 0.45, 0.08, CROWN_RADIUS, 1.35),
        TreeSpec("B", "1", x0 + 3.9, ROW_Y, 0.45, 0.08, CROWN_RADIUS, 1.35),
    ]
    drip = np.array([[x0 - 6, ROW_Y - 0.3, 0.35], [x0 + 10, ROW_Y - 0.3, 0.35]])
    meshes = [tree_mesh(spec, Ground(), rng) for spec in specs]
    meshes += [tube(drip, 0.01), weed_clump(x0 + 1.95, ROW_Y - 0.3, 0.0, 0.35, 0.45, rng)]
    return scan_of(*meshes), [spec.x for spec in specs]


def widest_tree(clusters, centres):
    trees = [c for c in clusters if c.verdict == TREE]
    for x in centres:
        assert any(abs(c.centroid[0] - x) < 1.0 for c in trees), (x, [c.centroid for c in trees])
    return max(c.shape.width_m for c in trees)


@pytest.mark.parametrize("x0", [0.0, 2.0, 3.6])
def test_a_drip_line_and_weeds_between_trees_widen_no_crown(x0):
    scan, centres = row_scan(x0)
    clusters = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig()).clusters
    # Measured 2.47-2.74 m (the near half of a 2.8 m crown).
    assert widest_tree(clusters, centres) < 2 * CROWN_RADIUS + 0.1
    gap = [
        c for c in clusters if math.hypot(c.centroid[0] - x0 - 1.95, c.centroid[1] - ROW_Y) < 0.5
    ]
    assert all(c.verdict != TREE for c in gap)


def test_without_the_rule_the_understorey_widens_a_crown():
    widths = []
    for x0 in (0.0, 2.0, 3.6):
        scan, centres = row_scan(x0)
        widths.append(
            widest_tree(detect(scan.points, None, DEFAULT_T_BASE_LIDAR, WITHOUT).clusters, centres)
        )
    # Measured 2.97-3.51 m: the drip line and the weed joined a crown.
    assert max(widths) > 2 * CROWN_RADIUS + 0.3


def test_join_understorey_within_reach_the_rest_is_its_own_object():
    # Two crowns (labels 0, 1) 2 m apart; a line of low voxels under and between them.
    voxels = np.array(
        [[0, 0, 1.0], [2.0, 0, 1.0]] + [[x, 0, 0.3] for x in np.arange(-0.2, 2.3, 0.2)],
        dtype=float,
    )
    crowns = np.full(len(voxels), -1)
    crowns[:2] = [0, 1]
    under = crowns < 0
    starts = np.ones(len(voxels), dtype=bool)
    labels = join_understorey(voxels, crowns, under, starts, tolerance=0.75, next_label=2)
    x = voxels[under, 0]
    # Within 0.75 m of a crown voxel (0.7 m above the line): |dx| <= 0.27 m.
    assert set(labels[x <= 0.21]) == {0} and set(labels[x >= 1.79]) == {1}
    assert set(labels[(x > 0.3) & (x < 1.7)]) == {2}  # the span between: one low object
    # Green skirt points alone (no return clear of the ground band) start nothing.
    none = join_understorey(voxels, crowns, under, np.zeros(len(voxels), bool), 0.75, 2)
    assert set(none[(x > 0.3) & (x < 1.7)]) == {-1}
