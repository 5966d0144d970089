"""Things in a real grove that are not trees: weeds and cover crop, drip lines, trellis
posts and wire, people (standing and walking), a parked vehicle, a wall. Each object is a
mesh of its own with its own label and `Material`, and a row of the truth's objects file
(`ObjectTruth`), so the evaluation can say what a false positive hit.

Objects are placed from the orchard's layout (the tree rows' lines along +x) and kept
clear of the robot's path: the twin's robot does not avoid obstacles, so nothing may
stand where it drives (weeds are mowed there, people step aside).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from treetraits.sim.lidar import Material

# Labels of clutter meshes start here (trees are 1..N, the ground 0).
CLUTTER_LABEL_BASE = 100_000

KINDS = ("weed", "drip_line", "post", "wire", "person", "walking_person", "vehicle", "wall")

# What each kind looks like to the VLP-16 (reflectivity 0-100: the twin's soil is 8, its
# foliage 45) and to the Survey3N (red, green, NIR reflectance; NDVI in the comment).
MATERIALS = {
    "weed": Material(40, (0.06, 0.14, 0.32)),  # green grass and forbs, NDVI 0.68
    "drip_line": Material(5, (0.04, 0.04, 0.05)),  # black polyethylene, NDVI 0.11
    "post": Material(30, (0.25, 0.24, 0.30)),  # weathered wood / concrete, NDVI 0.09
    "wire": Material(60, (0.35, 0.35, 0.38)),  # galvanised steel, NDVI 0.04
    "person": Material(25, (0.30, 0.25, 0.40)),  # cotton work clothes, NDVI 0.14
    "walking_person": Material(25, (0.30, 0.25, 0.40)),
    "vehicle": Material(60, (0.35, 0.35, 0.38)),  # painted steel and glass, NDVI 0.04
    "wall": Material(35, (0.30, 0.29, 0.33)),  # block wall / shed cladding, NDVI 0.05
}


@dataclass(frozen=True)
class ClutterSettings:
    """Non-tree objects (all 0 / off: the paper's bare twin)."""

    weeds: int = 0  # clumps of weeds / cover crop, in the inter-row and under the trees
    weed_height_m: tuple[float, float] = (0.1, 0.6)  # cover crop and weeds up to ~0.6 m
    weed_radius_m: tuple[float, float] = (0.15, 0.4)  # one clump's footprint radius
    # Drip irrigation line along each tree row: "none", "ground" (lying on it) or "hung"
    # (on a wire at drip_hang_m, ~0.3-0.4 m, clear of weeds and mowers).
    drip_lines: str = "none"
    drip_hang_m: float = 0.35
    drip_diameter_m: float = 0.02  # 16-20 mm polyethylene tubing
    posts: bool = False  # trellis / end posts at both ends of every tree row
    post_width_m: float = 0.1  # 10 cm square timber or concrete
    post_height_m: tuple[float, float] = (1.5, 2.2)
    wires: bool = False  # a trellis wire between a row's two posts (needs posts)
    wire_height_m: float = 1.0
    wire_diameter_m: float = 0.004  # high-tensile trellis wire: 2.5-4 mm
    standing_people: int = 0  # workers standing in a tree row's gaps / at row ends
    walking_people: int = 0  # people walking across the rows while the robot drives
    walking_speed_mps: float = 1.2  # a relaxed walk: 1.2-1.4 m/s
    vehicle: bool = False  # a pickup (~4 x 1.8 x 1.6 m) parked at the far headland
    wall: bool = False  # a wall / shed side (8 m long, 2.5 m high) beside the grove
    # Nothing but weeds (mowed, driven over) comes nearer the robot's path than this.
    clearance_m: float = 1.0

    def validate(self) -> None:
        if self.drip_lines not in ("none", "ground", "hung"):
            raise ValueError(f"drip_lines must be none, ground or hung, got {self.drip_lines!r}")
        for name in ("weeds", "standing_people", "walking_people"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.wires and not self.posts:
            raise ValueError("wires hang between posts: wires needs posts")

    @property
    def any(self) -> bool:
        return bool(
            self.weeds
            or self.drip_lines != "none"
            or self.posts
            or self.standing_people
            or self.walking_people
            or self.vehicle
            or self.wall
        )


@dataclass(frozen=True)
class ObjectTruth:
    """One non-tree object: its footprint is the segment of `length` m through (x, y)
    along `heading` (rad ccw from +x), `width` m across (length 0: a point-like object);
    `size` is its largest horizontal extent."""

    object_id: str
    kind: str
    label: int
    x: float
    y: float
    size: float
    length: float
    width: float
    heading: float
    height: float


@dataclass(frozen=True)
class WalkingPath:
    """A person walking back and forth along y at x, between y0 and y1, at `speed`, from
    phase `phase_s` (seconds into the back-and-forth) at the run's start `t0_s`; the mesh
    is built standing at (x, (y0 + y1) / 2) and moved by `offset`. The feet follow the
    ground (`ground` has a vectorised `height(x, y)`)."""

    x: float
    y0: float
    y1: float
    speed: float
    phase_s: float
    t0_s: float
    ground: object
    body_radius: float

    @property
    def centre(self) -> tuple[float, float]:
        return (self.x, (self.y0 + self.y1) / 2)

    @property
    def reach(self) -> float:
        return abs(self.y1 - self.y0) / 2 + self.body_radius

    def y_at(self, t_s) -> np.ndarray:
        span = abs(self.y1 - self.y0)
        period = 2 * span / self.speed
        u = np.mod(np.asarray(t_s, dtype=float) - self.t0_s + self.phase_s, period)
        along = np.where(u < period / 2, u * self.speed, (period - u) * self.speed)
        return min(self.y0, self.y1) + along

    def offset(self, t_s) -> np.ndarray:
        y = self.y_at(t_s)
        mid = self.centre[1]
        dz = self.ground.height(np.full_like(y, self.x), y) - self.ground.height(self.x, mid)
        return np.column_stack([np.zeros_like(y), y - mid, dz])


# ---- meshes ---------------------------------------------------------------------------


def box(cx, cy, z0, z1, length, width, heading=0.0):
    """A box standing on z0, `length` along `heading`, `width` across."""
    c, s = math.cos(heading), math.sin(heading)
    corners = []
    for dz in (z0, z1):
        for u, v in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            a, b = u * length / 2, v * width / 2
            corners.append((cx + c * a - s * b, cy + s * a + c * b, dz))
    faces = [
        (0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7),  # bottom, top
        (0, 1, 5), (0, 5, 4), (1, 2, 6), (1, 6, 5),
        (2, 3, 7), (2, 7, 6), (3, 0, 4), (3, 4, 7),
    ]  # fmt: skip
    return np.array(corners, dtype=float), np.array(faces, dtype=np.int32)


def cylinder(x, y, z0, z1, radius, sides: int = 12):
    """A closed vertical cylinder."""
    angles = np.linspace(0, 2 * math.pi, sides, endpoint=False)
    ring = np.stack([x + radius * np.cos(angles), y + radius * np.sin(angles)], axis=1)
    vertices = np.vstack(
        [
            np.column_stack([ring, np.full(sides, z0)]),
            np.column_stack([ring, np.full(sides, z1)]),
            [[x, y, z0], [x, y, z1]],
        ]
    )
    triangles = []
    for i in range(sides):
        j = (i + 1) % sides
        triangles += [(i, j, sides + i), (j, sides + j, sides + i)]
        triangles += [(2 * sides, j, i), (2 * sides + 1, sides + i, sides + j)]
    return vertices, np.array(triangles, dtype=np.int32)


def tube(points: np.ndarray, radius: float, sides: int = 6):
    """A tube of `radius` along a polyline (N, 3) running mostly horizontally."""
    points = np.asarray(points, dtype=float)
    rings = []
    for i in range(len(points)):
        a, b = points[max(i - 1, 0)], points[min(i + 1, len(points) - 1)]
        along = (b - a) / max(np.linalg.norm(b - a), 1e-9)
        side = np.cross(along, (0.0, 0.0, 1.0))
        side /= max(np.linalg.norm(side), 1e-9)
        up = np.cross(side, along)
        angles = np.linspace(0, 2 * math.pi, sides, endpoint=False)
        rings.append(
            points[i] + radius * (np.cos(angles)[:, None] * side + np.sin(angles)[:, None] * up)
        )
    vertices = np.vstack(rings)
    triangles = []
    for i in range(len(points) - 1):
        for k in range(sides):
            a, b = i * sides + k, i * sides + (k + 1) % sides
            triangles += [(a, b, a + sides), (b, b + sides, a + sides)]
    return vertices, np.array(triangles, dtype=np.int32)


def weed_clump(x, y, ground_z, radius, height, rng, leaves_per_m3=6000.0, leaf_size=0.06):
    """Grass / forb blades (small triangles) filling a dome of `radius` and `height` on
    the ground: denser than a crown's leaves, and smaller (blades of ~6 cm)."""
    count = max(8, int(leaves_per_m3 * 2 / 3 * math.pi * radius * radius * height))
    direction = rng.normal(size=(count, 3))
    direction[:, 2] = np.abs(direction[:, 2])
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    r = rng.uniform(0, 1, count) ** (1 / 3)
    centres = np.array([x, y, ground_z]) + direction * r[:, None] * (radius, radius, height)
    corners = rng.normal(size=(count, 3, 3))
    corners /= np.linalg.norm(corners, axis=2, keepdims=True)
    vertices = (centres[:, None, :] + corners * (leaf_size / 2)).reshape(-1, 3)
    return vertices, np.arange(count * 3, dtype=np.int32).reshape(-1, 3)


def person(x, y, ground_z, facing=0.0):
    """A standing adult, 1.75 m tall and 0.45 m across the shoulders, facing `facing` (rad
    ccw from +x): two legs, a torso, two arms and a head."""
    parts = [
        cylinder(0.0, -0.1, 0.0, 0.85, 0.075),  # legs
        cylinder(0.0, 0.1, 0.0, 0.85, 0.075),
        box(0.0, 0.0, 0.85, 1.5, 0.25, 0.3),  # torso: 0.25 deep, 0.3 wide
        cylinder(0.0, -0.175, 0.8, 1.45, 0.05),  # arms: 0.45 m across their outsides
        cylinder(0.0, 0.175, 0.8, 1.45, 0.05),
        cylinder(0.0, 0.0, 1.5, 1.75, 0.1),  # neck and head
    ]
    vertices, triangles = _merge(parts)
    c, s = math.cos(facing), math.sin(facing)
    rotated = vertices @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return rotated + np.array([x, y, ground_z]), triangles


def vehicle(x, y, ground_z, heading):
    """A pickup truck, 4.0 x 1.8 x 1.6 m: wheels, a body from 0.4 to 1.0 m, a cab."""
    c, s = math.cos(heading), math.sin(heading)
    parts = [box(x, y, ground_z + 0.4, ground_z + 1.0, 4.0, 1.8, heading)]
    cab_x, cab_y = x + c * 0.6, y + s * 0.6  # the cab over the front half
    parts.append(box(cab_x, cab_y, ground_z + 1.0, ground_z + 1.6, 1.6, 1.7, heading))
    for u in (-1.3, 1.3):
        for v in (-0.75, 0.75):
            wx, wy = x + c * u - s * v, y + s * u + c * v
            parts.append(box(wx, wy, ground_z, ground_z + 0.45, 0.7, 0.25, heading))
    return _merge(parts)


def _merge(parts):
    vertices, triangles, offset = [], [], 0
    for v, t in parts:
        vertices.append(v)
        triangles.append(t + offset)
        offset += len(v)
    return np.vstack(vertices), np.vstack(triangles).astype(np.int32)


# ---- placing --------------------------------------------------------------------------


@dataclass
class Placed:
    vertices: np.ndarray
    triangles: np.ndarray
    truth: ObjectTruth
    walk: WalkingPath | None = None


def place_clutter(
    settings: ClutterSettings,
    row_lines_y: list[float],
    tree_x: list[float],
    spacing: float,
    crowns: list[tuple[float, float, float]],
    poses: np.ndarray,
    ground,
    rng: np.random.Generator,
    t0_s: float = 0.0,
) -> list[Placed]:
    """Every object of `settings` for tree rows along x at `row_lines_y`, trees at
    `tree_x` (`spacing` apart), the planted trees' `crowns` (x, y, radius) and the robot's
    `poses` (t s, x, y, yaw)."""
    settings.validate()
    path = poses[:: max(1, len(poses) // 2000), 1:3]
    out: list[Placed] = []

    def clear(x, y, margin):
        return np.hypot(path[:, 0] - x, path[:, 1] - y).min() >= margin

    crown = np.asarray(crowns, dtype=float).reshape(-1, 3)

    def outside_crowns(x, y, margin):
        """(x, y) at least `margin` outside every crown (y may be an array: a line)."""
        if not len(crown):
            return True
        y = np.atleast_1d(y)
        gap = np.hypot(crown[None, :, 0] - x, crown[None, :, 1] - y[:, None]) - crown[:, 2]
        return bool(gap.min() >= margin)

    def add(kind, vertices, triangles, x, y, size, length, width, heading, height, walk=None):
        n = sum(p.truth.kind == kind for p in out)
        label = CLUTTER_LABEL_BASE + len(out)
        truth = ObjectTruth(
            f"{kind}{n + 1}", kind, label, x, y, size, length, width, heading, height
        )
        out.append(Placed(np.asarray(vertices, np.float32), triangles, truth, walk))

    x_first, x_last = min(tree_x), max(tree_x)
    row_start, row_end = x_first - spacing / 2, x_last + spacing / 2
    ys = sorted(row_lines_y)
    gap = (ys[1] - ys[0]) if len(ys) > 1 else 5.0
    z = ground.height

    # Weeds: half under the trees (near a row line), half in the inter-row.
    tries = 0
    while sum(p.truth.kind == "weed" for p in out) < settings.weeds and tries < 50 * (
        settings.weeds + 1
    ):
        tries += 1
        x = rng.uniform(row_start, row_end)
        if rng.random() < 0.5:
            y = ys[int(rng.integers(len(ys)))] + rng.normal(0, 0.6)
        else:
            y = rng.uniform(ys[0] - gap / 2, ys[-1] + gap / 2)
        radius = rng.uniform(*settings.weed_radius_m)
        height = rng.uniform(*settings.weed_height_m)
        if not clear(x, y, radius + 0.5):  # the robot's 0.43 m half-width and a little
            continue
        v, t = weed_clump(x, y, float(z(x, y)) - 0.02, radius, height, rng)
        add("weed", v, t, x, y, 2 * radius, 0.0, 2 * radius, 0.0, height)

    # Drip lines along each row, 0.3 m beside the trunks (the emitters' side).
    if settings.drip_lines != "none":
        lift = settings.drip_hang_m if settings.drip_lines == "hung" else 0.0
        radius = settings.drip_diameter_m / 2
        for y_row in ys:
            y = y_row + 0.3
            xs = np.arange(row_start, row_end + 1e-9, 0.25)
            points = np.column_stack([xs, np.full_like(xs, y), z(xs, np.full_like(xs, y))])
            points[:, 2] += lift + radius
            v, t = tube(points, radius)
            length = row_end - row_start
            add("drip_line", v, t, (row_start + row_end) / 2, y, length, length,
                settings.drip_diameter_m, 0.0, lift + 2 * radius)  # fmt: skip

    # End posts at both ends of every row, and the wire between them.
    if settings.posts:
        for y in ys:
            heights = []
            for x in (row_start, row_end):
                if not clear(x, y, settings.clearance_m):
                    continue
                height = rng.uniform(*settings.post_height_m)
                heights.append(height)
                w = settings.post_width_m
                v, t = box(x, y, float(z(x, y)) - 0.3, float(z(x, y)) + height, w, w)
                add("post", v, t, x, y, w, 0.0, w, 0.0, height)
            if settings.wires and len(heights) == 2:
                xs = np.linspace(row_start, row_end, 40)
                points = np.column_stack(
                    [xs, np.full_like(xs, y), z(xs, np.full_like(xs, y)) + settings.wire_height_m]
                )
                v, t = tube(points, settings.wire_diameter_m / 2, sides=4)
                length = row_end - row_start
                add("wire", v, t, (row_start + row_end) / 2, y, length, length,
                    settings.wire_diameter_m, 0.0, settings.wire_height_m)  # fmt: skip

    # Standing people: in a row's gap between two trees, else just past a row's end.
    spots = [((a + b) / 2, y) for y in ys for a, b in itertools.pairwise(sorted(tree_x))]
    spots += [(row_end + 1.0, y) for y in ys] + [(row_start - 1.0, y) for y in ys]
    standing = 0
    for x, y in spots:
        if standing == settings.standing_people:
            break
        if not clear(x, y, settings.clearance_m + 0.25) or not outside_crowns(x, y, 0.5):
            continue
        v, t = person(x, y, float(z(x, y)))
        add("person", v, t, x, y, 0.45, 0.0, 0.45, 0.0, 1.75)
        standing += 1

    # Walking people: back and forth across the rows, in the gap between two trees (or
    # past the rows' end), from beyond one side of the path to beyond the other; the phase
    # is the first (in a seeded order) that keeps them clearance_m + 0.5 from the robot.
    y0 = float(min(path[:, 1].min(), ys[0]) - 2.0)
    y1 = float(max(path[:, 1].max(), ys[-1]) + 2.0)
    line = np.linspace(y0, y1, 200)
    taken = [p.truth.x for p in out if p.truth.kind in ("person", "post")]
    crossings = [(a + b) / 2 for a, b in itertools.pairwise(sorted(tree_x))]
    crossings += [row_end + 1.5, row_start - 1.5]
    crossings = [
        x
        for x in crossings
        if outside_crowns(x, line, 0.4) and all(abs(x - other) > 1.0 for other in taken)
    ] or [row_end + 1.5]
    times = poses[:: max(1, len(poses) // 2000), 0]
    for k in range(settings.walking_people):
        x = crossings[k % len(crossings)]
        period = 2 * (y1 - y0) / settings.walking_speed_mps
        best, best_clearance = 0.0, -1.0
        for phase in rng.permutation(64) / 64 * period:
            walk = WalkingPath(x, y0, y1, settings.walking_speed_mps, phase, 0.0, ground, 0.25)
            gap_m = np.hypot(path[:, 0] - x, path[:, 1] - walk.y_at(times)).min()
            if gap_m > best_clearance:
                best, best_clearance = phase, gap_m
            if gap_m >= settings.clearance_m + 0.5:
                break
        walk = WalkingPath(x, y0, y1, settings.walking_speed_mps, best, t0_s, ground, 0.25)
        mid = walk.centre[1]
        v, t = person(x, mid, float(z(x, mid)), facing=math.pi / 2)
        add("walking_person", v, t, x, mid, y1 - y0, y1 - y0, 0.45, math.pi / 2, 1.75, walk)

    # A pickup parked across the far headland, 2.5 m beyond where the robot turns.
    if settings.vehicle:
        x = max(row_end, float(path[:, 0].max())) + 2.5 + 0.9
        y = float(np.mean(ys))
        v, t = vehicle(x, y, float(z(x, y)), math.pi / 2)
        add("vehicle", v, t, x, y, 4.0, 4.0, 1.8, math.pi / 2, 1.6)

    # A wall (or a shed's side) along the grove, 3 m beyond the path's outermost lane.
    if settings.wall:
        y = float(path[:, 1].min()) - 3.0
        x = x_first + 3.0
        length, height = 8.0, 2.5
        xs = np.linspace(x - length / 2, x + length / 2, 9)
        low = float(z(xs, np.full_like(xs, y)).min())
        v, t = box(x, y, low - 0.2, float(z(x, y)) + height, length, 0.2)
        add("wall", v, t, x, y, length, length, 0.2, 0.0, height)
    return out
