"""Vegetation evidence: each cue on made-up surfaces whose answer is known, on real
returns (a real apple orchard captured by a VLP-16 mounted on its side, the real indoor
captures) and on the twin's objects."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.helpers.captures import VLP16_DIR, decode_file
from tests.helpers.paths import FIXTURES
from tests.helpers.scans import scan_of
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.drivers.records import POINT_DTYPE
from treetraits.pipeline.classify import TREE
from treetraits.pipeline.config import ClassifyConfig, DetectionConfig
from treetraits.pipeline.detection import detect
from treetraits.pipeline.vegetation import (
    Cues,
    measure_groups,
    planar_share_of_groups,
    texture_of_groups,
    weigh,
)
from treetraits.sim.clutter import box, person, vehicle
from treetraits.sim.orchard import Ground, TreeSpec, tree_mesh

CONFIG = ClassifyConfig()
ORCHARD = FIXTURES / "real_orchard" / "lfuji_apple_vlp16_sideways_2s.pcap"
# The orchard's VLP-16 on its side (tests/fixtures/real_orchard/PROVENANCE.md).
SIDEWAYS = np.array([[0, 0, 1, 0], [0, -1, 0, 0], [1, 0, 0, 1.4], [0, 0, 0, 1]], dtype=float)
INDOOR = [
    "veloview_vlp16_20hz_strongest.pcap",
    "einride_vlp16_strongest_1000pkts.bin",
    "nebula_vlp16_dual_10hz.pcap",
]


def ring_of(depth: np.ndarray, reach: float, step_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """One ring's returns across a surface `reach` m away, fired every `step_deg`, each
    `depth` m off it; and their azimuths."""
    azimuth = np.radians(np.arange(len(depth)) * step_deg - len(depth) * step_deg / 2)
    r = reach + depth
    xyz = np.column_stack([r * np.cos(azimuth), r * np.sin(azimuth), np.zeros_like(r)])
    return xyz, azimuth


@pytest.mark.parametrize(("reach", "step_deg"), [(1.5, 0.1), (5.0, 0.2), (9.0, 0.4)])
def test_texture_tells_leaves_from_a_wall_at_every_range_and_angular_step(reach, step_deg):
    """Texture reads returns 5 cm apart, however many firings that is: a wall with 1 cm
    of range noise stays under 0.02 m, leaves of 4 cm at depths +-0.15 m (each return's
    depth drawn per leaf: firings on one leaf share it) stay over 0.05 m."""
    rng = np.random.default_rng(1)
    count = int(1.2 / (reach * math.radians(step_deg)))  # 1.2 m of surface
    wall = rng.normal(0, 0.01, count)
    leaf = np.floor(np.arange(count) * reach * math.radians(step_deg) / 0.04).astype(int)
    leaves = rng.uniform(-0.15, 0.15, leaf.max() + 1)[leaf] + rng.normal(0, 0.01, count)
    found = []
    for depth in (wall, leaves):
        xyz, azimuth = ring_of(depth, reach, step_deg)
        texture, triples = texture_of_groups(
            xyz, np.zeros(count, np.uint8), azimuth, np.zeros(3), np.array([count]), 0.05
        )
        assert triples[0] >= 5
        found.append(texture[0])
    assert found[0] < 0.02 < CONFIG.texture_pivot_m < 0.05 < found[1], found


def test_texture_follows_the_sensor_azimuth_not_the_frame():
    """The same ring turned on its side (a LiDAR mounted sideways) keeps its texture: the
    order along a ring is the sensor's azimuth, not a bearing in the robot's frame."""
    rng = np.random.default_rng(2)
    xyz, azimuth = ring_of(rng.uniform(-0.1, 0.1, 300), 3.0, 0.2)
    sizes, ring = np.array([300]), np.zeros(300, np.uint8)
    level, _ = texture_of_groups(xyz, ring, azimuth, np.zeros(3), sizes, 0.05)
    turned = xyz @ SIDEWAYS[:3, :3].T + SIDEWAYS[:3, 3]
    side, _ = texture_of_groups(turned, ring, azimuth, SIDEWAYS[:3, 3], sizes, 0.05)
    assert side[0] == pytest.approx(level[0], rel=1e-9)


def test_planar_share_of_a_wall_and_of_a_volume_of_leaves():
    rng = np.random.default_rng(3)
    n = 4000
    rings = rng.integers(0, 16, n).astype(np.uint8)
    plane = np.column_stack([np.full(n, 4.0), rng.uniform(-1, 1, n), rng.uniform(0, 2, n)])
    plane[:, 0] += rng.normal(0, 0.008, n)
    volume = np.column_stack(
        [rng.uniform(3.6, 4.4, n), rng.uniform(-1, 1, n), rng.uniform(0, 2, n)]
    )
    share, patches = planar_share_of_groups(
        np.vstack([plane, volume]), np.concatenate([rings, rings]), np.array([n, n]), 0.3, 0.02
    )
    assert patches.min() >= 10
    assert share[0] > 0.9 and share[1] < 0.1, share


def test_a_dual_return_sensors_last_echoes_alone_make_the_texture():
    """Two echoes of each firing at one azimuth, 0.3 m apart, on a smooth wall: read as
    one sequence they would look like leaves."""
    rng = np.random.default_rng(4)
    xyz, azimuth = ring_of(rng.normal(0, 0.005, 400), 4.0, 0.2)
    behind = xyz * (1 + 0.3 / 4.0)
    firing = np.zeros(800, dtype=POINT_DTYPE)
    firing["azimuth"] = np.concatenate([azimuth, azimuth])
    firing["intensity"] = 40
    firing["return_type"] = np.repeat([0, 1], 400)  # strongest on the wall, last behind
    both = np.vstack([xyz, behind])
    order = np.argsort(firing["azimuth"], kind="stable")
    (cues,) = measure_groups(
        both[order], np.zeros(800, np.uint8), firing[order], np.zeros(3), np.array([800]), CONFIG
    )
    assert cues.texture_m < 0.02


def test_dark_echoes_earn_no_credit_for_looking_rough():
    rough_dark = Cues(texture_m=0.08, texture_triples=100, planar_share=0.0, planar_patches=20)
    bright = weigh(Cues(**{**rough_dark.__dict__, "intensity": 30.0}), CONFIG)
    dark = weigh(Cues(**{**rough_dark.__dict__, "intensity": CONFIG.dark_intensity}), CONFIG)
    assert bright.vegetation and bright.texture == CONFIG.texture_weight
    assert not dark.vegetation and dark.texture == 0 and dark.planar == 0


def test_a_cue_of_few_samples_weighs_in_proportion():
    few = weigh(Cues(texture_m=0.01, texture_triples=6, intensity=30.0), CONFIG)
    many = weigh(Cues(texture_m=0.01, texture_triples=300, intensity=30.0), CONFIG)
    assert many.texture == -CONFIG.texture_weight
    assert -CONFIG.texture_weight < few.texture < 0


def canopy_clusters(scan, transform):
    """Every cluster of a scan whose returns span more than 1 m in height, of 50 returns
    or more (fewer give the texture too few triples to weigh in full: a far crown's
    sparse top of 20 dark returns shows nothing either way)."""
    clusters = detect(scan.points, None, transform, DetectionConfig()).clusters
    return [c for c in clusters if np.ptp(c.points[:, 2]) > 1.0 and len(c.points) >= 50]


def test_real_apple_canopy_is_vegetation_in_every_scan():
    """The real orchard capture (a VLP-16 on its side among apple rows): in each of its
    full scans the row cross-sections spanning more than 1 m in height are judged
    vegetation, with the texture over its pivot and few flat patches."""
    scans, _ = decode_file(ORCHARD)
    assert len(scans) >= 19
    textures = []
    for scan in scans[1:-1]:
        canopy = canopy_clusters(scan, SIDEWAYS)
        assert len(canopy) >= 3
        judged = [c.evidence.vegetation for c in canopy]
        assert sum(judged) >= 0.95 * len(judged), [
            (len(c.points), c.cues, c.evidence) for c in canopy if not c.evidence.vegetation
        ]
        textures += [c.cues.texture_m for c in canopy]
    assert np.nanmedian(textures) > 1.5 * CONFIG.texture_pivot_m


@pytest.mark.parametrize("capture", INDOOR)
def test_real_indoor_walls_and_furniture_measure_smooth(capture):
    """Walls, furniture and people of the real indoor captures: most of what is shaped
    like a crown shows no vegetation in a scan, and their texture sits under the pivot;
    the track decides the rest (`replay` maps no tree: test_classify)."""
    scans, _ = decode_file(VLP16_DIR / capture)
    shaped = [
        c
        for scan in scans[:12]
        for c in detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig()).clusters
        if c.verdict == TREE or (not c.evidence.vegetation and c.shape.height_m >= 0.8)
    ]
    assert shaped
    vegetation = [c for c in shaped if c.evidence.vegetation]
    assert len(vegetation) <= 0.15 * len(shaped)
    assert np.nanmedian([c.cues.texture_m for c in shaped]) < CONFIG.texture_pivot_m / 2


def test_the_twins_crowns_are_vegetation_and_its_wall_vehicle_and_person_are_not():
    rng = np.random.default_rng(5)
    crown = tree_mesh(TreeSpec("M", "1", 5.0, -2.5, 0.45, 0.08, 1.35, 1.1), Ground(), rng)
    objects = {
        "crown": (crown, (5.0, -2.5)),
        "wall": (box(6.0, 4.0, 0.0, 2.5, 3.0, 0.2), (6.0, 4.0)),
        "vehicle": (vehicle(-6.0, 3.0, 0.0, 0.3), (-6.0, 3.0)),
        "person": (person(-4.0, -3.0, 0.0), (-4.0, -3.0)),
    }
    scan = scan_of(*(mesh for mesh, _ in objects.values()))
    clusters = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig()).clusters
    for name, (_, (x, y)) in objects.items():
        near = [c for c in clusters if math.hypot(c.centroid[0] - x, c.centroid[1] - y) < 2.0]
        assert near, name
        biggest = max(near, key=lambda c: len(c.points))
        assert biggest.evidence.vegetation == (name == "crown"), (name, biggest.cues)
