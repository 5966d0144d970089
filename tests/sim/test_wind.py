"""Wind sway in the twin: swaying meshes are ray-cast where they are at each ray's time,
trees lean downwind, still air changes nothing, and `treetraits sim --wind` checks input."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from treetraits.cli import main
from treetraits.sim.lidar import Scene
from treetraits.sim.orchard import Ground, TreeSpec, TreeTruth, WindSettings, tree_mesh, tree_sways
from treetraits.sim.run import SurveySettings, build_orchard


def box(x0, x1, y0, y1, z0, z1):
    corners = np.array(
        [[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], dtype=np.float32
    )
    faces = [
        (0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
        (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3),
    ]  # fmt: skip
    return corners, np.array(faces, dtype=np.int32)


@dataclasses.dataclass
class Leaning:
    """A sway that leans `per_second` m per metre of height per second (shear = rate * t)."""

    base: tuple[float, float, float] = (0.0, 0.0, 0.0)
    per_second: tuple[float, float] = (0.1, 0.0)
    max_offset: float = 1.0

    def shear(self, t_s):
        t = np.atleast_1d(t_s)
        return np.outer(t, self.per_second)


def test_a_swaying_mesh_is_hit_where_it_is_at_the_rays_time():
    scene = Scene()
    scene.add(*box(-1, 1, -1, 1, 0, 3), label=1, sway=Leaning())
    origins = np.array([[-5.0, 0.0, 2.0]] * 3)
    directions = np.array([[1.0, 0.0, 0.0]] * 3)
    # At t = 0, 1, 2 s the shear is 0, 0.1, 0.2: at z = 2 the near face (x = -1) has moved
    # by 0, 0.2, 0.4 m towards +x.
    distance, label = scene.cast(origins, directions, t_ns=np.array([0, 1e9, 2e9]))
    assert distance == pytest.approx([4.0, 4.2, 4.4], abs=1e-4)
    assert label.tolist() == [1, 1, 1]
    # A ray at z = 0.5 sees a quarter of the motion; one that passes beside sees nothing.
    distance, label = scene.cast(
        np.array([[-5.0, 0.0, 0.5], [-5.0, 3.0, 2.0]]), directions[:2], t_ns=2e9
    )
    assert distance[0] == pytest.approx(4.1, abs=1e-4) and label[0] == 1
    assert math.isinf(distance[1]) and label[1] == -1
    with pytest.raises(ValueError, match="t_ns"):
        scene.cast(origins, directions)


def test_the_nearest_of_still_and_swaying_meshes_is_reported():
    scene = Scene()
    scene.add(*box(2, 3, -1, 1, 0, 3), label=2)  # still, behind the swaying one at first
    scene.add(*box(-1, 1, -1, 1, 0, 3), label=1, sway=Leaning(per_second=(1.5, 0.0)))
    origin, direction = np.array([[-5.0, 0.0, 2.0]]), np.array([[1.0, 0.0, 0.0]])
    distance, label = scene.cast(origin, direction, t_ns=0)
    assert distance[0] == pytest.approx(4.0, abs=1e-4) and label[0] == 1
    # At t = 3 s the box has leant 9 m on at z = 2 (shear 4.5), past the still box.
    distance, label = scene.cast(origin, direction, t_ns=3e9)
    assert distance[0] == pytest.approx(7.0, abs=1e-4) and label[0] == 2


def test_trees_lean_downwind_by_the_wind_drag():
    rng = np.random.default_rng(4)
    ground = Ground()
    spec = TreeSpec("T1", "1", 0.0, 0.0, 0.45, 0.08, 1.35, 1.1)
    vertices, triangles = tree_mesh(spec, ground, rng)
    truth = TreeTruth("T1", "1", 0.0, 0.0, 2.7, float(vertices[:, 2].max()))
    # 5 m/s towards +y, no oscillation: the top moves 0.008 * 25 = 0.2 m.
    wind = WindSettings(speed_mps=5.0, direction_deg=90.0, sway=0.0, cross_sway=0.0)
    (sway,) = tree_sways(wind, [truth], ground, np.random.default_rng(0))
    np.testing.assert_allclose(sway.shear([0.0, 7.3]), [[0, 0.2 / truth.height]] * 2, atol=1e-9)
    # Rays straight down over the crown: the hits' mean y moves downwind by the lean at
    # their heights (the crown spans about 0.45 ... 2.65 m: between 0.3 and 1 of 0.2 m).
    xs, ys = np.meshgrid(np.linspace(-1.6, 1.6, 65), np.linspace(-1.6, 1.6, 65))
    origins = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, 5.0)])
    down = np.tile([0.0, 0.0, -1.0], (len(origins), 1))
    still, moving = Scene(), Scene()
    still.add(vertices, triangles, label=1)
    moving.add(vertices, triangles, label=1, sway=sway)
    shifts = []
    for scene in (still, moving):
        distance, label = scene.cast(origins, down, t_ns=0)
        hit = label == 1
        shifts.append(origins[hit, 1].mean())
        if scene is moving:
            top_y = origins[hit, 1][np.argmin(distance[hit])]
    assert 0.3 * 0.2 < shifts[1] - shifts[0] < 0.2
    assert abs(top_y) < 1.6  # the top is still on the tree


def test_still_air_is_the_default_and_wind_keeps_the_same_trees():
    assert SurveySettings().wind.speed_mps == 0.0
    assert tree_sways(WindSettings(), [TreeTruth("T", "1", 0, 0, 2.7, 2.6)], Ground(), None) == [
        None
    ]
    calm = SurveySettings(goal=8.0, seed=3)
    windy = dataclasses.replace(calm, wind=WindSettings(speed_mps=4.4))
    _, calm_truth, _ = build_orchard(calm, np.random.default_rng(3))
    scene, windy_truth, _ = build_orchard(windy, np.random.default_rng(3))
    assert calm_truth == windy_truth  # the sway's draws do not change the trees
    assert scene.moving
    with pytest.raises(ValueError, match="wind speed"):
        tree_sways(WindSettings(speed_mps=-1.0), calm_truth, Ground(), np.random.default_rng(0))


def test_sim_command_rejects_a_bad_wind(tmp_path, capsys):
    assert main(["sim", "--wind", "-2", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "--wind is a speed in m/s" in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists()
