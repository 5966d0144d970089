"""The twin's foliage models: how leaves fill a crown, and so how rough its LiDAR returns
are along a ring.

`scattered` is the original twin's crown (`orchard._leaves`, drawn from the survey's own
generator so that a default twin is unchanged). The others are drawn from a generator of
their own and span what real canopy shows: measured by `classify.roughness` on the VLP-16
emulator's returns (bench/foliage.py), a real apple row gives ~0.011 m at 1-2.5 m range and
~0.03-0.04 m at 4-9 m; `scattered` gives ~0.1 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from treetraits.drivers.records import Scan


@dataclass(frozen=True)
class Foliage:
    """One way of filling a crown ellipsoid with leaf triangles."""

    name: str
    description: str  # one line: the canopy it stands for
    leaf_size: float  # m: a leaf triangle's side (scattered: its circumscribed diameter)
    leaves_per_m3: float  # in the leafy volume (the shell, or the whole crown)
    # Thickness (m) of the leafy layer under the crown's surface; None: the whole crown,
    # denser towards the surface (the original u^0.2 radius).
    shell_m: float | None = None
    clump_m: float = 0.0  # leaves grouped around shoot tips this far (sigma, m); 0: singly
    leaves_per_clump: int = 1
    # 0: leaves at random orientations; towards 1: facing outwards (leaves turn to the
    # light, so a beam meets them face on and consecutive beams stay on one leaf).
    facing: float = 0.0


MODELS: dict[str, Foliage] = {
    m.name: m
    for m in (
        Foliage(
            "scattered",
            "the original twin: 0.10 m leaves scattered through the whole crown, denser "
            "outwards; beams reach decimetres in (ring roughness ~0.1 m)",
            leaf_size=0.10,
            leaves_per_m3=4000.0,
        ),
        Foliage(
            "dense",
            "a pruned, hedge-like crown: 0.13 m leaves packed in a 0.2 m outer shell, "
            "facing out; beams stop in the outer layer",
            leaf_size=0.13,
            leaves_per_m3=10000.0,
            shell_m=0.2,
            facing=0.7,
        ),
        Foliage(
            "broadleaf",
            "large leaves (0.17 m) in a 0.25 m shell facing the light: consecutive beams "
            "often hit the same leaf",
            leaf_size=0.17,
            leaves_per_m3=6000.0,
            shell_m=0.25,
            facing=0.7,
        ),
        Foliage(
            "clumped",
            "leaves in clumps (~0.2 m) around shoot tips spread in a 0.4 m shell, gaps "
            "between the clumps",
            leaf_size=0.10,
            leaves_per_m3=6000.0,
            shell_m=0.4,
            clump_m=0.06,
            leaves_per_clump=30,
            facing=0.3,
        ),
        Foliage(
            "sparse",
            "a young or thin crown: few 0.08 m leaves through the whole crown, beams go deep",
            leaf_size=0.08,
            leaves_per_m3=1500.0,
        ),
    )
}
# The command line offers them from `treetraits.sim.FOLIAGE_MODELS`, which imports
# nothing: the same names in the same order (tests/sim/test_foliage.py).
DEFAULT = "scattered"


def foliage_model(name: str) -> Foliage:
    """The model called `name`; a ValueError naming the choices for any other."""
    try:
        return MODELS[name]
    except KeyError:
        raise ValueError(
            f"unknown foliage model {name!r}; choose from {', '.join(MODELS)}"
        ) from None


def crown_leaves(
    model: Foliage, centre: np.ndarray, a: float, b: float, rng: np.random.Generator
) -> np.ndarray:
    """Corners (3 per leaf) of `model`'s leaf triangles in the ellipsoid (a, a, b) at
    `centre`. Not for `scattered` (orchard._leaves draws it, in its original order)."""
    scale = np.array([a, a, b])
    volume = 4 / 3 * math.pi * a * a * b
    # The shell's inner surface, as a fraction of the crown's mean semi-axis.
    inner = 0.0 if model.shell_m is None else max(0.0, 1 - model.shell_m / ((2 * a + b) / 3))
    count = int(model.leaves_per_m3 * volume * (1 - inner**3))
    clumps = max(1, count // model.leaves_per_clump)
    # Positions (leaf or clump centres): uniform directions, uniform in the shell's volume
    # (the whole crown: the original u^0.2 bias to the surface).
    direction = _unit(rng.normal(size=(clumps, 3)))
    if model.shell_m is None:
        radius = rng.uniform(0, 1, clumps) ** 0.2
    else:
        radius = rng.uniform(inner**3, 1, clumps) ** (1 / 3)
    sites = direction * radius[:, None]  # in the unit sphere
    if model.leaves_per_clump > 1:
        owner = rng.integers(0, clumps, count)
        offsets = rng.normal(0, model.clump_m, (count, 3))
        points = centre + sites[owner] * scale + offsets
        outward = _unit(sites[owner] / scale)
    else:
        points = centre + sites * scale
        outward = _unit(sites / scale)
    # Each leaf: an equilateral triangle of side ~leaf_size (+-20 %) about its normal,
    # the normal leaning outwards by `facing`, turned at random about it.
    normal = _unit(model.facing * outward + (1 - model.facing) * _unit(rng.normal(size=(count, 3))))
    u = _unit(np.cross(normal, rng.normal(size=(count, 3))))
    v = np.cross(normal, u)
    side = model.leaf_size * rng.uniform(0.8, 1.2, count)
    circum = side / math.sqrt(3)  # the corners' distance from the leaf's centre
    angles = np.array([0.0, 2 * math.pi / 3, 4 * math.pi / 3])
    corners = (
        np.cos(angles)[None, :, None] * u[:, None, :]
        + np.sin(angles)[None, :, None] * v[:, None, :]
    ) * circum[:, None, None]
    return (points[:, None, :] + corners).reshape(-1, 3)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


@dataclass(frozen=True)
class TreeScan:
    """A tree's returns in one VLP-16 scan, in the LiDAR's frame (the LiDAR at x = y = 0)."""

    points: np.ndarray  # (N, 3) float64
    ring: np.ndarray  # (N,) laser ring of each return
    range_m: np.ndarray  # (N,) horizontal distance from the LiDAR
    triangles: int  # of the tree's mesh
    scan: Scan  # the whole scan, as the pipeline takes it (`detection.detect`)


def tree_scan(
    model: str,
    range_m: float,
    seed: int = 0,
    crown_radius: float = 1.35,
    crown_half_height: float = 1.1,
    trunk_height: float = 0.45,
) -> TreeScan:
    """One default-sized tree of `model` (the twin's 2.7 m citrus) whose crown's near side is
    `range_m` ahead of a robot standing at the origin, ray-cast by the twin's VLP-16
    emulator (one complete scan, decoded by our batcher); only the crown's returns (above
    the trunk's top, no ground in the scene)."""
    from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
    from treetraits.drivers.velodyne.batcher import ScanBatcher
    from treetraits.sim.lidar import Scene, Vlp16Emulator
    from treetraits.sim.orchard import Ground, TreeSpec, tree_mesh

    spec = TreeSpec(
        "T1", "1", range_m + crown_radius, 0.0, trunk_height, 0.08, crown_radius, crown_half_height
    )
    rng = np.random.default_rng(seed)
    vertices, triangles = tree_mesh(spec, Ground(), rng, foliage=model, foliage_rng=rng)
    scene = Scene()
    scene.add(vertices, triangles, label=1)
    batcher = ScanBatcher()
    emulator = Vlp16Emulator(scene, DEFAULT_T_BASE_LIDAR, rng=np.random.default_rng([seed, 1]))

    def standing(t):
        zeros = np.zeros(t.shape)
        return zeros, zeros, zeros, zeros

    for t_device, payload in emulator.packets(standing, 0, int(0.35e9)):
        scan = batcher.push(payload, t_device)
        if scan is not None and scan.complete:
            break
    else:
        raise RuntimeError("the emulator sent no complete scan")
    p = scan.distinct
    xyz = np.column_stack([p["x"], p["y"], p["z"]]).astype(float)
    crown = xyz[:, 2] >= trunk_height - DEFAULT_T_BASE_LIDAR[2, 3]
    return TreeScan(
        xyz[crown],
        p["ring"][crown].astype(int),
        np.hypot(xyz[crown, 0], xyz[crown, 1]),
        len(triangles),
        scan,
    )
