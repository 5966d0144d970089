"""What a tree is: each rule on the object it is for, each object ray-cast by the twin's
VLP-16 emulator and decoded by our own decoder; and the real indoor captures, which hold
walls, furniture and people and no vegetation, map no tree."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from tests.helpers.captures import VLP16_DIR
from tests.helpers.scans import scan_of
from treetraits.cli import main
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.pipeline.classify import (
    FLOATING,
    LOW,
    NOT_GREEN,
    SLENDER,
    SMOOTH,
    THIN,
    TREE,
    WIDE,
    Shape,
    Votes,
    judge,
    roughness,
    roughness_of_groups,
    shape_of,
)
from treetraits.pipeline.config import ClassifyConfig, ClusterConfig, DetectionConfig
from treetraits.pipeline.detection import detect
from treetraits.pipeline.vegetation import Cues, weigh
from treetraits.sim.clutter import box, cylinder, person, tube, vehicle, weed_clump
from treetraits.sim.orchard import Ground, TreeSpec, tree_mesh

CONFIG = ClassifyConfig()


def verdicts_near(scan, x, y, reach=3.0):
    clusters = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig()).clusters
    return [c.verdict for c in clusters if math.hypot(c.centroid[0] - x, c.centroid[1] - y) < reach]


RNG = np.random.default_rng(2)
OBJECTS = {
    # object: (mesh, where it stands, the verdicts it may get)
    "person": (person(5.0, 1.0, 0.0), (5.0, 1.0), {SLENDER, SMOOTH, THIN}),
    "post": (cylinder(4.0, -2.0, 0.0, 2.0, 0.05), (4.0, -2.0), {THIN, SLENDER, SMOOTH}),
    "vehicle": (vehicle(7.0, 3.0, 0.0, 0.3), (7.0, 3.0), {SMOOTH, WIDE, FLOATING}),
    # Its foot, where the face above is out of reach, is a low object of its own.
    "wall": (box(6.0, -5.0, 0.0, 2.5, 8.0, 0.2), (6.0, -5.0), {SMOOTH, WIDE, LOW}),
    "weeds": (weed_clump(3.0, 3.0, 0.0, 0.4, 0.5, RNG), (3.0, 3.0), {LOW}),
    "drip line": (
        tube(np.array([[2.0, -3.0, 0.35], [10.0, -3.0, 0.35]]), 0.01),
        (6.0, -3.0),
        {LOW, THIN, SMOOTH, SLENDER},
    ),
}


@pytest.mark.parametrize("name", list(OBJECTS))
def test_what_is_not_a_tree_is_never_judged_one(name):
    mesh, (x, y), allowed = OBJECTS[name]
    verdicts = verdicts_near(scan_of(mesh), x, y)
    # Each is seen and judged; only a drip line 2 cm across may leave no cluster at all.
    assert verdicts or name == "drip line", name
    assert TREE not in verdicts, (name, verdicts)
    assert set(verdicts) <= allowed, (name, verdicts)


@pytest.mark.parametrize(
    ("name", "spec"),
    [
        # young: 1.2 m tall with a 1 m crown; mature citrus; old: 5 m tall, 4.6 m wide
        ("young", TreeSpec("Y", "1", 4.0, 2.0, 0.3, 0.04, 0.5, 0.45)),
        ("mature", TreeSpec("M", "1", 5.0, -2.5, 0.45, 0.08, 1.35, 1.1)),
        ("old", TreeSpec("O", "1", 7.0, 4.0, 0.6, 0.15, 2.3, 2.2)),
    ],
)
def test_trees_of_every_age_are_trees(name, spec):
    mesh = tree_mesh(spec, Ground(), np.random.default_rng(3))
    verdicts = verdicts_near(scan_of(mesh), spec.x, spec.y)
    assert verdicts and all(v == TREE for v in verdicts), (name, verdicts)


def shape(**values) -> Shape:
    base = dict(height_m=2.7, base_m=0.2, width_m=2.6, roughness=0.1, ndvi=math.nan, ndvi_share=0.0)
    return Shape(**{**base, **values})


# Cues as a crown, a wall and a dark object show them (docs/pipeline.md's cue table).
CROWN = Cues(texture_m=0.08, texture_triples=200, planar_share=0.1, planar_patches=20, intensity=20)
WALL = Cues(texture_m=0.008, texture_triples=200, planar_share=0.9, planar_patches=20, intensity=45)


@pytest.mark.parametrize(
    ("values", "cues", "verdict"),
    [
        ({}, CROWN, TREE),
        ({"height_m": 0.5}, CROWN, LOW),  # cover crop
        ({"base_m": 2.6}, CROWN, FLOATING),  # a ceiling, a crown fragment
        # A crown seen from a LiDAR mounted high, its base on the lowest beam: what is
        # under it was out of view, so nothing says it floats.
        ({"base_m": 1.5, "base_cut": True}, CROWN, TREE),
        ({"width_m": 0.3, "height_m": 1.8}, CROWN, THIN),  # a post, a person side on
        ({"width_m": 0.65, "height_m": 1.75}, CROWN, SLENDER),  # a person facing the robot
        ({"width_m": 12.0}, WALL, WIDE),  # a building
        ({}, WALL, SMOOTH),  # a wall, a vehicle
        # Rough, but the camera sees no leaves on it: the colour outweighs the surface.
        ({}, replace(CROWN, ndvi=0.1, ndvi_returns=400), NOT_GREEN),
        ({}, replace(CROWN, ndvi=0.1, ndvi_returns=10), TREE),  # too little of it seen to say
        # A pruned hedge smoother than the texture's pivot, plainly green: a tree.
        ({}, replace(CROWN, texture_m=0.025, planar_share=0.8, ndvi=0.75, ndvi_returns=300), TREE),
        # Nothing measured, or a dark object's noisy echoes (no credit for looking rough):
        # undecided in one scan, the shape's verdict stands; the track decides.
        ({}, Cues(), TREE),
        ({}, replace(CROWN, intensity=5), TREE),
    ],
)
def test_each_rule(values, cues, verdict):
    assert judge(shape(**values), CONFIG, weigh(cues, CONFIG)) == verdict


def test_the_shape_rules_alone_without_evidence():
    assert judge(shape(), CONFIG) == TREE
    assert judge(shape(height_m=0.5), CONFIG) == LOW


def test_a_base_on_the_lowest_ring_is_cut_by_the_view():
    """The lowest return on ring 0 (the sensor's lowest beam) cuts the base; on another
    ring it does not; nor on a cloud without rings (every return on ring 0)."""
    points = np.array([[4.0, 0.0, 1.2], [4.0, 0.1, 2.0], [4.1, 0.0, 2.6]])
    lidar = np.zeros(2)
    assert shape_of(points, np.array([0, 1, 2]), lidar, 0.0, rough=0.1).base_cut
    assert not shape_of(points, np.array([1, 0, 2]), lidar, 0.0, rough=0.1).base_cut
    unnumbered = shape_of(points, np.zeros(3, dtype=int), lidar, 0.0, rough=0.1, rings_known=False)
    assert not unnumbered.base_cut


def test_roughness_of_a_smooth_wall_and_of_foliage():
    """Returns of one ring along a wall 5 m away (2 cm apart, 1.5 cm range noise) and
    along foliage (leaves at depths +-0.2 m)."""
    rng = np.random.default_rng(0)
    azimuth = np.radians(np.arange(-20, 20, 0.2))
    ring = np.zeros(len(azimuth), dtype=np.uint8)

    def points(depth):
        r = 5.0 + depth
        return np.column_stack([r * np.cos(azimuth), r * np.sin(azimuth), np.full_like(r, 1.0)])

    wall = roughness(points(rng.normal(0, 0.015, len(azimuth))), ring, np.zeros(2))
    foliage = roughness(points(rng.uniform(-0.2, 0.2, len(azimuth))), ring, np.zeros(2))
    assert wall < 0.02 < CONFIG.min_roughness_m < 0.08 < foliage


def test_roughness_of_groups_is_each_ones_to_the_bit():
    """Groups of every size (none, 1-2 returns, too few triples, one ring, many rings,
    odd and even counts, duplicate bearings) against `roughness` one at a time."""
    rng = np.random.default_rng(4)
    groups = []
    for size in [0, 1, 2, 3, 5, 6, 7, 40, 41, 300, 1200, 0, 2]:
        azimuth = rng.uniform(-1, 1, size)
        azimuth[: size // 10] = azimuth[0] if size else 0.0  # repeated bearings
        r = rng.uniform(3, 9, size)
        xyz = np.column_stack([r * np.cos(azimuth), r * np.sin(azimuth), rng.uniform(0, 3, size)])
        groups.append((xyz, rng.integers(0, 1 if size < 50 else 16, size).astype(np.uint8)))
    lidar_xy = np.array([0.1, -0.05])
    sizes = np.array([len(xyz) for xyz, _ in groups])
    found = roughness_of_groups(
        np.vstack([xyz for xyz, _ in groups]),
        np.concatenate([ring for _, ring in groups]),
        lidar_xy,
        sizes,
    )
    each = np.array([roughness(xyz, ring, lidar_xy) for xyz, ring in groups])
    assert np.isfinite(each).sum() >= 4 and np.isnan(each).sum() >= 4
    assert np.array_equal(found, each, equal_nan=True)
    known = np.isfinite(each)
    assert np.array_equal(found[known].view(np.int64), each[known].view(np.int64))


def test_a_track_is_what_its_verdicts_and_its_evidence_over_all_its_scans_say():
    def votes(cues: Cues = CROWN, **counts) -> Votes:
        out = Votes()
        for verdict, n in counts.items():
            for _ in range(n):
                out.add(verdict, cues, weigh(cues, CONFIG))
        return out

    assert votes(tree=6, low=3).kind(0.5, 0.25) == TREE
    # A crown seen in pieces: its floating tops and low skirts do not count against it.
    assert votes(tree=40, floating=30, low=20).kind(0.5, 0.25) == TREE
    # A weed clump judged a tree in a few scans is still a weed.
    assert votes(tree=3, low=100).kind(0.5, 0.25) == LOW
    # A wall that looks rough in some scans: its evidence over all of them is a wall's.
    wall = votes(WALL, smooth=30, low=5)
    wall.absorb(votes(replace(WALL, texture_m=0.05), tree=10))
    assert wall.kind(0.5, 0.25) == SMOOTH
    # A smooth, pruned crown the camera saw green in 3 scans of 40: the NDVI's mean over
    # the scans that saw it counts in full, not diluted by those that did not.
    hedge = votes(replace(CROWN, texture_m=0.025), smooth=37)
    hedge.absorb(votes(replace(CROWN, texture_m=0.025, ndvi=0.75, ndvi_returns=300), tree=3))
    assert hedge.kind(0.5, 0.25) == TREE
    # A crown beside the path, a sliver of it in the camera's view in each scan (10
    # returns of 500): the green of all those slivers counts in full along the track.
    sliver = replace(CROWN, texture_m=0.025, planar_share=0.8, ndvi=0.75, ndvi_returns=10)
    assert votes(sliver, smooth=40).kind(0.5, 0.25) == TREE
    assert votes(sliver, smooth=5).kind(0.5, 0.25) == SMOOTH  # 50 returns: half the weight
    # The same crown never seen by the camera: its surface alone speaks against it.
    assert (
        votes(replace(CROWN, texture_m=0.02, planar_share=0.5), smooth=40).kind(0.5, 0.25) == SMOOTH
    )
    # A person the camera saw in a few scans, rough-looking clothes: not green.
    person = votes(replace(CROWN, ndvi=0.12, ndvi_returns=150), not_green=4)
    person.absorb(votes(tree=6))
    assert person.kind(0.5, 0.25) == NOT_GREEN
    mixed = votes(tree=2, low=3)
    mixed.absorb(votes(low=5, thin=8))
    assert mixed.kind(0.5, 0.25) == LOW  # ties: the rule tried first
    assert Votes().kind(0.5, 0.25) == TREE
    # A dark object: the surface cues earn it nothing in any scan, and nothing shows it
    # is vegetation: not a tree.
    assert votes(replace(CROWN, intensity=5), tree=20).kind(0.5, 0.25) == SMOOTH


@pytest.mark.parametrize(
    "capture",
    [
        "veloview_vlp16_20hz_strongest.pcap",
        "einride_vlp16_strongest_1000pkts.bin",
        "nebula_vlp16_dual_10hz.pcap",
    ],
)
def test_real_indoor_captures_map_no_tree_and_list_what_they_rejected(capture, tmp_path, capsys):
    assert main(["replay", str(VLP16_DIR / capture), "--out", str(tmp_path), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["trees"] == 0
    rejected = json.loads((tmp_path / "rejected.geojson").read_text())["features"]
    assert len(rejected) == sum(summary["rejected"].values()) >= 3
    assert {f["properties"]["reason"] for f in rejected} <= {
        "low",
        "tall",
        "floating",
        "thin",
        "slender",
        "wide",
        "smooth",
        "not_green",
    }
    assert all(f["properties"]["status"] == "rejected" for f in rejected)


def test_touching_crowns_of_a_hedgerow_are_cut_at_their_trunks():
    """Three 3.5 m crowns 2.75 m apart along a row 2.5 m beside the robot: one cluster
    along the row without the cut; one tree per trunk with it."""
    rng = np.random.default_rng(8)
    specs = [TreeSpec(f"H{i}", "1", 2.0 + 2.75 * i, 2.5, 0.45, 0.08, 1.75, 1.3) for i in range(3)]
    scan = scan_of(*(tree_mesh(spec, Ground(), rng) for spec in specs))
    clusters = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig()).clusters
    row = [c for c in clusters if abs(c.centroid[1] - 2.5) < 2.0 and c.verdict == TREE]
    assert len(row) == 3
    for spec in specs:
        nearest = min(row, key=lambda c: math.hypot(c.centroid[0] - spec.x, c.centroid[1] - 2.5))
        assert abs(nearest.centroid[0] - spec.x) < 0.8, spec.tree_id
    # Without the cut: crowns run together into a cluster wider than any one of them.
    uncut = DetectionConfig(cluster=ClusterConfig(min_tree_spacing_m=100.0))
    whole = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, uncut).clusters
    whole = [c for c in whole if abs(c.centroid[1] - 2.5) < 2.0]
    assert len(whole) < 3 and max(c.shape.width_m for c in whole) > 4.5
