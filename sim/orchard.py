"""The orchard of the digital twin: citrus-like trees on a grid, as triangle meshes that
the sensor emulators ray-cast.

A tree is a trunk (a cylinder) under a porous crown: thousands of small leaf triangles
scattered through an ellipsoid, denser towards its surface, so that LiDAR beams sometimes
pass a little way in, as they do in a real canopy. Ground truth width and height are
measured on the generated geometry with the same definitions as the traits: height is the
top of the tree above the ground at its trunk, width the largest horizontal distance
between two points of the tree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

GROUND_ID = 0  # geometry label of the ground; trees are labelled by their index + 1


@dataclass(frozen=True)
class TreeSpec:
    tree_id: str
    row: str
    x: float
    y: float
    trunk_height: float  # where the crown's skirt starts
    trunk_radius: float
    crown_radius: float  # horizontal semi-axis of the crown ellipsoid
    crown_half_height: float  # vertical semi-axis


@dataclass(frozen=True)
class TreeTruth:
    tree_id: str
    row: str
    x: float
    y: float
    width: float
    height: float


@dataclass(frozen=True)
class Ground:
    """z = slope_x * x + slope_y * y (a plane; 0 = flat)."""

    slope_x: float = 0.0
    slope_y: float = 0.0

    def height(self, x, y):
        return self.slope_x * np.asarray(x) + self.slope_y * np.asarray(y)


def grid_orchard(
    rows: int,
    trees_per_row: int,
    row_spacing: float,
    tree_spacing: float,
    rng: np.random.Generator,
    width_range: tuple[float, float] = (2.6, 2.8),
    height_range: tuple[float, float] = (2.5, 2.8),
) -> list[TreeSpec]:
    """Rows run along +x and are `row_spacing` apart in y; row 1 is at y = 0.
    Sizes are drawn uniformly from the ranges (the paper's simulated citrus: width
    2.67-2.77 m, height 2.58-2.74 m)."""
    specs = []
    for r in range(rows):
        for c in range(trees_per_row):
            width = rng.uniform(*width_range)
            height = rng.uniform(*height_range)
            trunk = rng.uniform(0.35, 0.55)
            specs.append(
                TreeSpec(
                    tree_id=f"R{r + 1}T{c + 1}",
                    row=str(r + 1),
                    x=c * tree_spacing + rng.normal(0, 0.05),
                    y=r * row_spacing + rng.normal(0, 0.05),
                    trunk_height=trunk,
                    trunk_radius=rng.uniform(0.06, 0.1),
                    crown_radius=width / 2,
                    crown_half_height=(height - trunk) / 2,
                )
            )
    return specs


def tree_mesh(
    spec: TreeSpec,
    ground: Ground,
    rng: np.random.Generator,
    leaves_per_m3: float = 4000.0,
    leaf_size: float = 0.10,
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) float32 and triangles (M, 3) int32 of one tree, in the world frame."""
    base_z = float(ground.height(spec.x, spec.y))
    a, b = spec.crown_radius, spec.crown_half_height
    centre = np.array([spec.x, spec.y, base_z + spec.trunk_height + b])
    count = int(leaves_per_m3 * 4 / 3 * math.pi * a * a * b)
    # Leaf centres: uniform directions, radius biased to the shell (u^(1/5)).
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(0, 1, count) ** 0.2
    centres = centre + direction * radius[:, None] * np.array([a, a, b])
    # Each leaf: a small triangle with a random orientation.
    corners = rng.normal(size=(count, 3, 3))
    corners /= np.linalg.norm(corners, axis=2, keepdims=True)
    leaf_vertices = (centres[:, None, :] + corners * (leaf_size / 2)).reshape(-1, 3)
    leaf_triangles = np.arange(count * 3, dtype=np.int32).reshape(-1, 3)

    trunk_vertices, trunk_triangles = _cylinder(
        spec.x, spec.y, base_z - 0.05, base_z + spec.trunk_height + b * 0.6, spec.trunk_radius
    )
    vertices = np.vstack([leaf_vertices, trunk_vertices]).astype(np.float32)
    triangles = np.vstack([leaf_triangles, trunk_triangles + len(leaf_vertices)])
    return vertices, triangles.astype(np.int32)


def _cylinder(x, y, z0, z1, radius, sides: int = 12):
    angles = np.linspace(0, 2 * math.pi, sides, endpoint=False)
    ring = np.stack([x + radius * np.cos(angles), y + radius * np.sin(angles)], axis=1)
    vertices = np.vstack(
        [np.column_stack([ring, np.full(sides, z0)]), np.column_stack([ring, np.full(sides, z1)])]
    )
    triangles = []
    for i in range(sides):
        j = (i + 1) % sides
        triangles += [(i, j, sides + i), (j, sides + j, sides + i)]
    return vertices, np.array(triangles, dtype=np.int32)


def measure_truth(spec: TreeSpec, vertices: np.ndarray, ground: Ground) -> TreeTruth:
    """Width and height of the generated tree, by the traits' definitions."""
    base_z = float(ground.height(spec.x, spec.y))
    hull = cv2.convexHull(vertices[:, :2].astype(np.float32)).reshape(-1, 2).astype(float)
    gaps = hull[:, None, :] - hull[None, :, :]
    width = float(np.sqrt((gaps**2).sum(axis=2)).max())
    height = float(vertices[:, 2].max() - base_z)
    return TreeTruth(spec.tree_id, spec.row, spec.x, spec.y, width, height)


def ground_mesh(ground: Ground, x_range, y_range) -> tuple[np.ndarray, np.ndarray]:
    (x0, x1), (y0, y1) = x_range, y_range
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)
    z = ground.height(corners[:, 0], corners[:, 1])
    vertices = np.column_stack([corners, z]).astype(np.float32)
    return vertices, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)


# ---- wind ------------------------------------------------------------------------------


@dataclass(frozen=True)
class WindSettings:
    """Crowns swaying in the wind while the robot drives (off at 0 m/s, the paper's
    simulated cases; its field day had 16 km/h = 4.4 m/s with gusts to 40 km/h).

    Each tree leans downwind and sways about that lean at its own frequency and phase,
    bending about its base: a point h above the base moves by (h / tree height) times the
    crown top's displacement (a shear, so the ray-cast stays exact: see `sim.lidar.Scene`).
    """

    speed_mps: float = 0.0
    direction_deg: float = 90.0  # where the wind blows towards, ccw from +x (the path)
    # Crown-top displacement (m) per (m/s)^2: drag grows with the square of the speed.
    # 0.008 gives ~15 cm at 4.4 m/s, what a dense citrus crown's top does in a breeze.
    lean_per_speed2: float = 0.008
    sway: float = 0.6  # oscillation about the mean lean, as a fraction of the lean
    cross_sway: float = 0.3  # oscillation across the wind, as a fraction of the lean
    frequency_hz: tuple[float, float] = (0.3, 0.8)  # each tree's own, drawn uniformly


@dataclass(frozen=True)
class TreeSway:
    """One tree's motion: `shear(t)` is the horizontal displacement per metre above
    `base` (x, y, z of the trunk foot) at times t (s)."""

    base: tuple[float, float, float]
    height: float
    lean: tuple[float, float]  # mean crown-top displacement (m), x and y
    sway: tuple[float, float]  # oscillation amplitude along and across the wind (m)
    across: tuple[float, float]  # unit vector across the wind
    frequency_hz: tuple[float, float]
    phase: tuple[float, float]

    @property
    def max_offset(self) -> float:
        """The farthest the crown top moves from rest (m)."""
        lean = math.hypot(*self.lean)
        return math.hypot(lean + self.sway[0], self.sway[1])

    def shear(self, t_s) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        along = self.sway[0] * np.sin(2 * math.pi * self.frequency_hz[0] * t + self.phase[0])
        cross = self.sway[1] * np.sin(2 * math.pi * self.frequency_hz[1] * t + self.phase[1])
        unit = np.array(self.lean) / max(math.hypot(*self.lean), 1e-12)
        top = (
            np.array(self.lean)[None, :]
            + along[:, None] * unit[None, :]
            + cross[:, None] * np.array(self.across)[None, :]
        )
        return top / self.height


def tree_sways(
    settings: WindSettings, truths: list[TreeTruth], ground: Ground, rng: np.random.Generator
) -> list[TreeSway | None]:
    """Each tree's sway (None for every tree in still air)."""
    if settings.speed_mps < 0:
        raise ValueError(f"wind speed must be >= 0 m/s, got {settings.speed_mps}")
    if settings.speed_mps == 0:
        return [None] * len(truths)
    heading = math.radians(settings.direction_deg)
    downwind = np.array([math.cos(heading), math.sin(heading)])
    across = (-downwind[1], downwind[0])
    top = settings.lean_per_speed2 * settings.speed_mps**2
    sways: list[TreeSway | None] = []
    for t in truths:
        frequency = rng.uniform(*settings.frequency_hz, size=2)
        phase = rng.uniform(0, 2 * math.pi, size=2)
        sways.append(
            TreeSway(
                base=(t.x, t.y, float(ground.height(t.x, t.y))),
                height=t.height,
                lean=tuple(float(v) for v in downwind * top),
                sway=(top * settings.sway, top * settings.cross_sway),
                across=(float(across[0]), float(across[1])),
                frequency_hz=(float(frequency[0]), float(frequency[1])),
                phase=(float(phase[0]), float(phase[1])),
            )
        )
    return sways
