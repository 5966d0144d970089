"""The orchard of the digital twin: citrus-like trees on a grid, as triangle meshes that
the sensor emulators ray-cast.

A tree is a trunk (a cylinder) under a porous crown: thousands of small leaf triangles
scattered through an ellipsoid, denser towards its surface, so that LiDAR beams sometimes
pass a little way in, as they do in a real canopy (the default `scattered` foliage; the
other models of `sim.foliage` fill it otherwise). Ground truth width and height are
measured on the generated geometry with the same definitions as the traits: height is the
top of the tree above the ground at its trunk, width the largest horizontal distance
between two points of the tree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from treetraits.sim.foliage import DEFAULT as DEFAULT_FOLIAGE
from treetraits.sim.foliage import crown_leaves, foliage_model

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
    # An irregular crown: the union of these ellipsoids instead of the one above, each
    # (dx, dy, dz) from the crown's centre and its (horizontal, vertical) semi-axes.
    lobes: tuple[tuple[float, float, float, float, float], ...] = ()
    kind: str = "tree"  # "missing": a field-map position with no tree planted (no mesh)


@dataclass(frozen=True)
class TreeTruth:
    tree_id: str
    row: str
    x: float
    y: float
    width: float  # NaN for a missing tree
    height: float
    kind: str = "tree"  # tree | missing


@dataclass(frozen=True)
class Ground:
    """The terrain: z = slope_x * x + slope_y * y plus undulation, furrows and raised beds
    (every extra 0 = the plane of the paper's twin, two triangles).

    The twin's tree rows run along +x (the path's direction), so `slope_x` is the slope
    along the rows and `slope_y` across them. Heights are analytic (`height`); the scene's
    mesh samples them on a grid (`ground_mesh`), and the robot rides on `height`.
    """

    slope_x: float = 0.0  # rise over run along the rows; orchards on hills: up to ~0.15
    slope_y: float = 0.0  # across the rows; usually gentler (terraced or contoured): ~0.08
    # Rolling ground: three sinusoids of 4.6-11.9 m wavelength (what years of tractor
    # passes and settling leave on an orchard floor), summed to at most +-undulation_m.
    undulation_m: float = 0.0
    # Furrows parallel to the rows (irrigation furrows, wheel ruts): a cosine across the
    # rows of +-furrow_m, furrow_spacing_m apart (furrow irrigation: 0.75-1.2 m).
    furrow_m: float = 0.0
    furrow_spacing_m: float = 1.0
    # Raised beds (berms) under the tree rows at these y (m): citrus is often planted on
    # berms ~0.2-0.4 m high and ~1.5-2.5 m wide, for drainage.
    bed_rows_y: tuple[float, ...] = ()
    bed_height_m: float = 0.25
    bed_width_m: float = 1.6  # flat top; the sides fall off over bed_shoulder_m
    bed_shoulder_m: float = 0.6
    phase_seed: int = 0  # the undulation's phases (the survey's seed)

    @property
    def is_plane(self) -> bool:
        return self.undulation_m == 0 and self.furrow_m == 0 and not self.bed_rows_y

    def height(self, x, y):
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        z = self.slope_x * x + self.slope_y * y
        if self.undulation_m:
            phases = np.random.default_rng([self.phase_seed, 7]).uniform(0, 2 * math.pi, 3)
            wave = 0.0
            for (wx, wy), phase in zip(_UNDULATION_WAVES, phases, strict=True):
                wave = wave + np.sin(wx * x + wy * y + phase)
            z = z + self.undulation_m / len(_UNDULATION_WAVES) * wave
        if self.furrow_m:
            z = z + self.furrow_m * np.cos(2 * math.pi * y / self.furrow_spacing_m)
        for centre in self.bed_rows_y:
            half = self.bed_width_m / 2
            off = np.clip((np.abs(y - centre) - half) / self.bed_shoulder_m, 0.0, 1.0)
            z = z + self.bed_height_m * 0.5 * (1 + np.cos(math.pi * off))
        return z


# Wave vectors (rad/m) of the undulation: wavelengths 11.9, 7.3 and 4.6 m in three
# directions, so no two repeat together within a field.
_UNDULATION_WAVES = tuple(
    (2 * math.pi / length * math.cos(angle), 2 * math.pi / length * math.sin(angle))
    for length, angle in ((11.9, 0.3), (7.3, 1.9), (4.6, -0.8))
)


@dataclass(frozen=True)
class TerrainSettings:
    """The ground of a real grove (all 0 / False: the flat plane of the paper's twin). The
    slope along the rows is `SurveySettings.slope`; see `Ground` for what each models."""

    slope_across: float = 0.0  # rise over run across the rows (+y); up to ~0.08
    undulation_m: float = 0.0  # rolling ground, +- m (up to ~0.10)
    furrow_m: float = 0.0  # furrows along the rows, +- m (up to ~0.10)
    furrow_spacing_m: float = 1.0  # furrow irrigation: 0.75-1.2 m apart
    raised_beds: bool = False  # berms under the tree rows (Ground.bed_*)
    bed_height_m: float = 0.25  # citrus berms: ~0.2-0.4 m


@dataclass(frozen=True)
class TreeSettings:
    """Trees that are hard (all 0 / False: the paper's uniform citrus, 2.6-2.8 m)."""

    young_fraction: float = 0.0  # replants: 1.0-1.5 m tall, crowns 0.8-1.2 m (YOUNG)
    old_fraction: float = 0.0  # old trees: ~5 m tall, crowns 4-5 m (OLD)
    irregular_fraction: float = 0.0  # crowns of 2-4 offset ellipsoids (lobed, lopsided)
    missing: int = 0  # positions in the field map with no tree (dead, removed, not planted)
    # Hedgerow: crowns 3.0-3.3 m wide, so at 2.5-3 m in-row spacing they touch and overlap,
    # as in high-density plantings pruned into a continuous wall.
    hedgerow: bool = False
    # How leaves fill the crowns (sim.foliage.MODELS): scattered is the paper's twin, dense
    # and broadleaf are as smooth along a ring as a real canopy, clumped and sparse between
    # and beyond. foliage_mix: each tree's model drawn from these instead.
    foliage: str = DEFAULT_FOLIAGE
    foliage_mix: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in (self.foliage, *self.foliage_mix):
            foliage_model(name)  # a ValueError naming the models

    @property
    def shapes_default(self) -> bool:
        """Every tree of the default size and shape (foliage aside)."""
        return replace(self, foliage=DEFAULT_FOLIAGE, foliage_mix=()) == TreeSettings()


def tree_foliage(settings: TreeSettings, count: int, rng: np.random.Generator) -> list[str]:
    """Each tree's foliage model: `foliage`, or drawn uniformly from `foliage_mix`."""
    if not settings.foliage_mix:
        return [settings.foliage] * count
    return [settings.foliage_mix[int(i)] for i in rng.integers(0, len(settings.foliage_mix), count)]


# (width m, height m, trunk height m, trunk radius m) ranges of each kind of tree.
# Young: a 2-3 year old citrus replant (trunk 5-8 cm thick, skirt low).
YOUNG = ((0.8, 1.2), (1.0, 1.5), (0.25, 0.35), (0.025, 0.04))
# Old: a 30+ year old tree left unpruned (trunk 25-35 cm thick, skirt high).
OLD = ((4.0, 5.0), (4.8, 5.2), (0.6, 0.9), (0.12, 0.18))
HEDGEROW = ((3.0, 3.3), (2.8, 3.2), (0.35, 0.55), (0.06, 0.1))


def vary_trees(
    specs: list[TreeSpec], settings: TreeSettings, rng: np.random.Generator
) -> list[TreeSpec]:
    """The grid's trees made young, old, hedgerow, irregular or missing by `settings`
    (positions and ids kept). Draws only from `rng` (its own generator: the default twin's
    trees are unchanged)."""
    for name in ("young_fraction", "old_fraction", "irregular_fraction"):
        value = getattr(settings, name)
        if not 0 <= value <= 1:
            raise ValueError(f"{name} must be in [0, 1], got {value}")
    if settings.young_fraction + settings.old_fraction > 1:
        raise ValueError("young_fraction + old_fraction must be <= 1")
    if not 0 <= settings.missing <= len(specs):
        raise ValueError(f"missing must be in [0, {len(specs)}], got {settings.missing}")
    n = len(specs)
    order = rng.permutation(n)
    n_young = round(settings.young_fraction * n)
    n_old = round(settings.old_fraction * n)
    kinds = {int(i): YOUNG for i in order[:n_young]}
    kinds |= {int(i): OLD for i in order[n_young : n_young + n_old]}
    irregular = {int(i) for i in rng.permutation(n)[: round(settings.irregular_fraction * n)]}
    missing = {int(i) for i in rng.permutation(n)[: settings.missing]}
    out = []
    for i, spec in enumerate(specs):
        ranges = kinds.get(i, HEDGEROW if settings.hedgerow else None)
        if ranges is not None:
            (w0, w1), (h0, h1), (t0, t1), (r0, r1) = ranges
            width, height = rng.uniform(w0, w1), rng.uniform(h0, h1)
            trunk = rng.uniform(t0, t1)
            spec = replace(
                spec,
                trunk_height=trunk,
                trunk_radius=rng.uniform(r0, r1),
                crown_radius=width / 2,
                crown_half_height=(height - trunk) / 2,
            )
        if i in irregular:
            spec = replace(spec, lobes=_lobes(spec, rng))
        if i in missing:
            spec = replace(spec, kind="missing")
        out.append(spec)
    return out


def _lobes(spec: TreeSpec, rng: np.random.Generator):
    """2-4 ellipsoids, each 55-80 % of the crown's semi-axes, their centres up to half the
    crown radius off its centre in random directions: a lobed, lopsided crown (pruning,
    a broken limb, shade from a neighbour) about as big as the regular one."""
    a, b = spec.crown_radius, spec.crown_half_height
    lobes = []
    for _ in range(int(rng.integers(2, 5))):
        angle = rng.uniform(0, 2 * math.pi)
        off = rng.uniform(0.2, 0.5) * a
        scale = rng.uniform(0.55, 0.8)
        lobes.append(
            (
                float(off * math.cos(angle)),
                float(off * math.sin(angle)),
                float(rng.uniform(-0.25, 0.25) * b),
                float(scale * a),
                float(scale * b),
            )
        )
    return tuple(lobes)


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
    foliage: str = DEFAULT_FOLIAGE,
    foliage_rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N, 3) float32 and triangles (M, 3) int32 of one tree, in the world frame.
    `scattered` foliage (`leaves_per_m3`, `leaf_size`) is drawn from `rng` as it always
    was; any other model (`sim.foliage`) from `foliage_rng` (default `rng`)."""
    model = foliage_model(foliage)
    base_z = float(ground.height(spec.x, spec.y))
    a, b = spec.crown_radius, spec.crown_half_height
    centre = np.array([spec.x, spec.y, base_z + spec.trunk_height + b])
    ellipsoids = [(centre + np.array([dx, dy, dz]), la, lb) for dx, dy, dz, la, lb in spec.lobes]
    ellipsoids = ellipsoids or [(centre, a, b)]
    if model.name == DEFAULT_FOLIAGE:
        parts = [_leaves(c, la, lb, rng, leaves_per_m3, leaf_size) for c, la, lb in ellipsoids]
    else:
        leaf_rng = rng if foliage_rng is None else foliage_rng
        parts = [crown_leaves(model, c, la, lb, leaf_rng) for c, la, lb in ellipsoids]
    leaf_vertices = np.vstack(parts)
    count = len(leaf_vertices) // 3
    leaf_triangles = np.arange(count * 3, dtype=np.int32).reshape(-1, 3)

    trunk_vertices, trunk_triangles = _cylinder(
        spec.x, spec.y, base_z - 0.05, base_z + spec.trunk_height + b * 0.6, spec.trunk_radius
    )
    vertices = np.vstack([leaf_vertices, trunk_vertices]).astype(np.float32)
    triangles = np.vstack([leaf_triangles, trunk_triangles + len(leaf_vertices)])
    return vertices, triangles.astype(np.int32)


def _leaves(centre, a, b, rng, leaves_per_m3, leaf_size) -> np.ndarray:
    """Corners (3 per leaf) of leaf triangles filling the ellipsoid (a, a, b) at centre,
    denser towards its surface."""
    count = int(leaves_per_m3 * 4 / 3 * math.pi * a * a * b)
    # Leaf centres: uniform directions, radius biased to the shell (u^(1/5)).
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(0, 1, count) ** 0.2
    centres = centre + direction * radius[:, None] * np.array([a, a, b])
    # Each leaf: a small triangle with a random orientation.
    corners = rng.normal(size=(count, 3, 3))
    corners /= np.linalg.norm(corners, axis=2, keepdims=True)
    return (centres[:, None, :] + corners * (leaf_size / 2)).reshape(-1, 3)


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
    import cv2

    base_z = float(ground.height(spec.x, spec.y))
    hull = cv2.convexHull(vertices[:, :2].astype(np.float32)).reshape(-1, 2).astype(float)
    gaps = hull[:, None, :] - hull[None, :, :]
    width = float(np.sqrt((gaps**2).sum(axis=2)).max())
    height = float(vertices[:, 2].max() - base_z)
    return TreeTruth(spec.tree_id, spec.row, spec.x, spec.y, width, height)


def missing_truth(spec: TreeSpec) -> TreeTruth:
    """A field-map position with no tree: nothing to measure."""
    return TreeTruth(spec.tree_id, spec.row, spec.x, spec.y, math.nan, math.nan, "missing")


def ground_mesh(ground: Ground, x_range, y_range, cell: float = 0.15):
    """The ground as triangles: two for a plane (exact), else a height field sampled every
    `cell` metres (0.15 m: finer than a furrow's half-spacing, and below the VLP-16's
    footprint spacing on the ground near the robot)."""
    (x0, x1), (y0, y1) = x_range, y_range
    if ground.is_plane:
        corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)
        z = ground.height(corners[:, 0], corners[:, 1])
        vertices = np.column_stack([corners, z]).astype(np.float32)
        return vertices, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    xs = np.linspace(x0, x1, max(2, math.ceil((x1 - x0) / cell) + 1))
    ys = np.linspace(y0, y1, max(2, math.ceil((y1 - y0) / cell) + 1))
    gx, gy = np.meshgrid(xs, ys)  # (ny, nx)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), ground.height(gx, gy).ravel()])
    nx = len(xs)
    i = (np.arange(len(ys) - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    triangles = np.concatenate(
        [np.stack([i, i + 1, i + nx + 1], 1), np.stack([i, i + nx + 1, i + nx], 1)]
    )
    return vertices.astype(np.float32), triangles.astype(np.int32)


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
