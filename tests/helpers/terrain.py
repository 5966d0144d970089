"""Ground shaped as groves are (sloped, undulating, furrowed) with trees on it, and a
VLP-16 scan of it from a robot standing level or pitched and rolled by the slope."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tests.helpers.scans import first_complete_scan
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.sim.lidar import Scene
from treetraits.sim.orchard import TreeSpec, tree_mesh


@dataclass(frozen=True)
class RollingGround:
    """15 % up along x, 8 % across, +-10 cm furrows every 3 m across the rows and a
    gentle +-5 cm swell along them: the issue's worst case."""

    along: float = 0.15
    across: float = 0.08

    def height(self, x, y):
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        furrows = 0.10 * np.sin(2 * math.pi * y / 3.0)
        swell = 0.05 * np.sin(2 * math.pi * x / 7.0 + 1.0)
        return self.along * x + self.across * y + furrows + swell


def height_field(ground, extent=30.0, step=0.25):
    axis = np.arange(-extent, extent + step / 2, step)
    xx, yy = np.meshgrid(axis, axis, indexing="ij")
    vertices = np.column_stack([xx.ravel(), yy.ravel(), ground.height(xx, yy).ravel()])
    n = len(axis)
    index = np.arange(n * n).reshape(n, n)
    a, b = index[:-1, :-1].ravel(), index[1:, :-1].ravel()
    c, d = index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    triangles = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return vertices.astype(np.float32), triangles.astype(np.int32)


TREES = (
    TreeSpec("T1", "1", 5.0, 3.0, 0.45, 0.08, 1.35, 1.1),
    TreeSpec("T2", "1", 10.0, 3.0, 0.45, 0.08, 1.35, 1.1),
    TreeSpec("T3", "2", 5.0, -3.0, 0.40, 0.08, 1.30, 1.0),
    TreeSpec("T4", "2", -6.0, -3.0, 0.40, 0.08, 1.40, 1.2),
)


def high_mount(height_m: float) -> np.ndarray:
    """The default mount raised to `height_m` above the footprint (a tractor's)."""
    mount = DEFAULT_T_BASE_LIDAR.copy()
    mount[2, 3] = height_m
    return mount


def rotation(roll: float, pitch: float) -> np.ndarray:
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    return ry @ rx


def one_scan(
    ground, base_from_world_tilt: np.ndarray | None = None, mount_height_m: float | None = None
):
    """One VLP-16 scan of the scene from a robot at the origin (yaw 0). With a tilt, the
    robot stands pitched and rolled: the LiDAR is rotated with it about the footprint.
    `mount_height_m`: the LiDAR this high above the footprint (default: the Jackal's)."""
    rng = np.random.default_rng(11)
    scene = Scene()
    scene.add(*height_field(ground), label=0)
    for i, spec in enumerate(TREES):
        scene.add(*tree_mesh(spec, ground, rng), label=i + 1)
    mount = high_mount(mount_height_m) if mount_height_m else DEFAULT_T_BASE_LIDAR.copy()
    if base_from_world_tilt is not None:
        mount[:3, :3] = base_from_world_tilt @ mount[:3, :3]
        mount[:3, 3] = base_from_world_tilt @ mount[:3, 3]

    return first_complete_scan(scene, mount, rng)
