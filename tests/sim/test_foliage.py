"""The twin's foliage models: each one's ring roughness on the VLP-16 emulator's returns
against what real canopy shows, the default twin unchanged, and the setting's checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from treetraits.pipeline.classify import roughness
from treetraits.sim.foliage import MODELS, foliage_model, tree_scan
from treetraits.sim.orchard import (
    Ground,
    TreeSettings,
    TreeSpec,
    _cylinder,
    grid_orchard,
    measure_truth,
    tree_foliage,
    tree_mesh,
)
from treetraits.sim.run import SurveySettings, build_world

# A real VLP-16 in an apple row: ~0.011 m at 1-2.5 m range, 0.030-0.037 m at 4-9 m. The
# twin's 0.02 m range noise alone gives ~0.018 m on any surface: a model as smooth as real
# canopy measures at most ~0.022 near.
REAL_NEAR = (0.010, 0.022)
REAL_FAR = (0.020, 0.040)
# The original twin's crowns: ~0.1 m and more, away from the closest range.
ROUGH_FAR = (0.10, 0.20)
NEAR_M, FAR_M = 2.0, 8.0


def ring_roughness(model: str, range_m: float, seeds=range(3)) -> float:
    """The median over trees (seeds) of a tree's ring roughness at `range_m`."""
    values = []
    for seed in seeds:
        scan = tree_scan(model, range_m, seed)
        assert len(scan.points) > 200  # a crown, not a few stray returns
        # Returns from the near side (at range_m) round to the crown's flanks (1.35 m wide).
        assert range_m - 0.1 <= np.median(scan.range_m) <= range_m + 1.0
        values.append(roughness(scan.points, scan.ring, np.zeros(2)))
    return float(np.median(values))


@pytest.mark.parametrize("model", ["dense", "broadleaf"])
def test_smooth_models_are_as_rough_as_a_real_canopy(model):
    near, far = ring_roughness(model, NEAR_M), ring_roughness(model, FAR_M)
    assert REAL_NEAR[0] <= near <= REAL_NEAR[1], near
    assert REAL_FAR[0] <= far <= REAL_FAR[1], far


def test_clumped_lies_between_a_real_canopy_and_the_original_twin():
    near, far = ring_roughness("clumped", NEAR_M), ring_roughness("clumped", FAR_M)
    assert REAL_NEAR[1] < near < 0.05, near
    assert REAL_FAR[1] < far < ROUGH_FAR[0], far


@pytest.mark.parametrize("model", ["scattered", "sparse"])
def test_scattered_and_sparse_crowns_are_rough(model):
    near, far = ring_roughness(model, NEAR_M), ring_roughness(model, FAR_M)
    assert near > 0.05, near  # beams reach decimetres into the crown
    assert ROUGH_FAR[0] <= far <= ROUGH_FAR[1], far


def test_triangles_per_tree_stay_within_twice_the_original():
    spec = TreeSpec("T1", "1", 3.0, 0.0, 0.45, 0.08, 1.35, 1.1)
    original = len(tree_mesh(spec, Ground(), np.random.default_rng(0))[1])
    for name in MODELS:
        mesh = tree_mesh(spec, Ground(), np.random.default_rng(0), foliage=name)
        assert len(mesh[1]) <= 2 * original, name


def _original_leaves(centre, a, b, rng, leaves_per_m3=4000.0, leaf_size=0.10):
    """The twin's crown before foliage models, written out again: 0.10 m triangles,
    4000 per m^3 of the ellipsoid, radius u^0.2."""
    count = int(leaves_per_m3 * 4 / 3 * math.pi * a * a * b)
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(0, 1, count) ** 0.2
    centres = centre + direction * radius[:, None] * np.array([a, a, b])
    corners = rng.normal(size=(count, 3, 3))
    corners /= np.linalg.norm(corners, axis=2, keepdims=True)
    return (centres[:, None, :] + corners * (leaf_size / 2)).reshape(-1, 3)


def _original_tree(spec: TreeSpec, ground: Ground, rng) -> np.ndarray:
    base_z = float(ground.height(spec.x, spec.y))
    b = spec.crown_half_height
    centre = np.array([spec.x, spec.y, base_z + spec.trunk_height + b])
    leaves = _original_leaves(centre, spec.crown_radius, b, rng)
    trunk, _ = _cylinder(
        spec.x, spec.y, base_z - 0.05, base_z + spec.trunk_height + b * 0.6, spec.trunk_radius
    )
    return np.vstack([leaves, trunk]).astype(np.float32)


def test_the_default_twin_grows_the_original_trees_from_the_same_draws():
    """A default world's trees are the original algorithm's, leaf for leaf, and the survey's
    generator is left where the original left it (the sensors' noise comes next)."""
    settings = SurveySettings(seed=3)
    assert settings.trees.foliage == "scattered"
    rng = np.random.default_rng(3)
    world = build_world(settings, rng)

    again = np.random.default_rng(3)
    specs = grid_orchard(settings.columns, settings.rows, settings.width, settings.length, again)
    ground = Ground()
    for spec, truth in zip(specs, world.trees, strict=True):
        moved = TreeSpec(
            truth.tree_id,
            truth.row,
            spec.x + settings.length,
            spec.y - (settings.columns - 1) * settings.width / 2,
            spec.trunk_height,
            spec.trunk_radius,
            spec.crown_radius,
            spec.crown_half_height,
        )
        vertices = _original_tree(moved, ground, again)
        original = measure_truth(moved, vertices, ground)
        assert (truth.width, truth.height) == (original.width, original.height)
    assert rng.bit_generator.state == again.bit_generator.state


def test_a_scattered_tree_is_the_original_mesh():
    spec = TreeSpec("T1", "1", 4.0, -1.0, 0.5, 0.07, 1.3, 1.05)
    vertices, triangles = tree_mesh(spec, Ground(), np.random.default_rng(11))
    expected = _original_tree(spec, Ground(), np.random.default_rng(11))
    np.testing.assert_array_equal(vertices, expected)
    assert triangles.shape == ((len(vertices) - 24) // 3 + 24, 3)  # leaves + a 12-sided trunk


def test_other_models_leave_the_survey_generator_alone():
    spec = TreeSpec("T1", "1", 4.0, 0.0, 0.5, 0.07, 1.3, 1.05)
    rng = np.random.default_rng(2)
    before = rng.bit_generator.state
    tree_mesh(spec, Ground(), rng, foliage="dense", foliage_rng=np.random.default_rng(9))
    assert rng.bit_generator.state == before


def test_an_unknown_model_is_a_clear_error():
    with pytest.raises(ValueError, match=r"unknown foliage model 'hedge'.*dense.*sparse"):
        foliage_model("hedge")
    with pytest.raises(ValueError, match="choose from scattered"):
        TreeSettings(foliage="hedge")
    with pytest.raises(ValueError, match="'thick'"):
        TreeSettings(foliage_mix=("dense", "thick"))


def test_a_mix_draws_each_tree_from_its_models():
    settings = TreeSettings(foliage_mix=("dense", "sparse"))
    drawn = tree_foliage(settings, 40, np.random.default_rng(0))
    assert set(drawn) == {"dense", "sparse"}
    assert (
        tree_foliage(TreeSettings(foliage="clumped"), 3, np.random.default_rng(0))
        == ["clumped"] * 3
    )


def test_sim_foliage_option_names_one_model_or_a_mix():
    from treetraits.cli.sim import _foliage
    from treetraits.errors import ConfigError

    assert _foliage("dense") == {"foliage": "dense"}
    assert _foliage("dense, sparse") == {"foliage_mix": ("dense", "sparse")}
    with pytest.raises(ConfigError, match="unknown 'hedge'; choose from scattered"):
        _foliage("dense,hedge")


def test_the_command_lines_model_names_are_the_models():
    """`--foliage` offers `treetraits.sim.FOLIAGE_MODELS` (no import of the twin to build
    the parser): the very models sim/foliage.py grows, in its order."""
    from treetraits.sim import FOLIAGE_MODELS

    assert tuple(MODELS) == FOLIAGE_MODELS
