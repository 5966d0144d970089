"""The digital twin's drives: VLP-16 packets emulated along a straight path through an
orchard of known trees, decoded by our batcher, a Survey3N frame rendered per scan, exact
poses from the path in `odom`; the paper's 2 x 3 grid drive, the mapper over it, and its
trees matched to the truth."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import numpy as np

from tests.helpers.paths import CITRUSFARM
from treetraits.drivers.calibration import Calibration, CameraModel, load_calibration
from treetraits.drivers.records import Frame, Scan
from treetraits.drivers.velodyne.batcher import ScanBatcher
from treetraits.pipeline.config import MapperConfig, TraitsConfig
from treetraits.pipeline.localization.pose import Pose
from treetraits.pipeline.mapper import ScanResult, TrackedTree, TreeMapper
from treetraits.sim.camera import Survey3Emulator
from treetraits.sim.lidar import Scene, Vlp16Emulator
from treetraits.sim.orchard import Ground, TreeTruth, grid_orchard, ground_mesh, measure_truth
from treetraits.sim.orchard import tree_mesh as make_tree

CALIBRATION = load_calibration(CITRUSFARM)
LATENCY_NS = 200_000  # host receive time = device time + this, in the emulated stream


def small_camera(calibration: Calibration, factor: int = 4) -> Calibration:
    """The CitrusFarm Survey3N at 1/4 of its resolution (same field of view and lens,
    320 x 180): a frame per scan renders in ~20 ms instead of ~0.3 s."""
    c = calibration.camera
    k = c.K.copy()
    k[:2] /= factor
    camera = CameraModel(c.width // factor, c.height // factor, k, c.dist, c.channels)
    return dataclasses.replace(calibration, camera=camera)


@dataclasses.dataclass(frozen=True)
class Drive:
    scans: list[Scan]
    poses: list[Pose]  # base_footprint in odom at each scan's middle, exact
    frames: list[Frame]  # one per scan (empty without a camera)
    truth: list[TreeTruth]
    calibration: Calibration


def drive(specs, *, start, heading, speed, seconds, frames=False, seed=0, ground=None) -> Drive:
    """Emulate a straight drive at constant speed and heading past `specs`."""
    rng = np.random.default_rng(seed)
    ground = ground or Ground()
    scene = Scene()
    scene.add(*ground_mesh(ground, (-45, 45), (-45, 45)), label=0)
    truth = []
    for i, spec in enumerate(specs):
        vertices, triangles = make_tree(spec, ground, rng)
        scene.add(vertices, triangles, label=i + 1)
        truth.append(measure_truth(spec, vertices, ground))
    c, s = math.cos(heading), math.sin(heading)

    def path(t):
        travelled = speed * t / 1e9
        x, y = start[0] + c * travelled, start[1] + s * travelled
        return x, y, np.zeros(np.shape(t)), np.full(np.shape(t), heading)

    calibration = small_camera(CALIBRATION)
    camera = Survey3Emulator(scene, calibration, rng=rng) if frames else None
    batcher, scans, poses, images = ScanBatcher(), [], [], []
    lidar = Vlp16Emulator(scene, calibration.T_base_lidar, rng=rng)
    for t_device, payload in lidar.packets(path, 0, int(seconds * 1e9)):
        scan = batcher.push(payload, t_device + LATENCY_NS)
        if scan is None or not scan.complete:
            continue
        t_mid = scan.t_host - (scan.t_end - scan.t_start) // 2
        x, y, _, yaw = (float(v) for v in path(np.array(t_mid - LATENCY_NS)))
        scans.append(scan)
        poses.append(Pose(t_mid, x, y, yaw, np.eye(3) * 1e-4, "odom"))
        if camera is not None:
            world_from_base = np.eye(4)
            world_from_base[:2, :2] = [[c, -s], [s, c]]
            world_from_base[:2, 3] = (x, y)
            images.append(Frame(camera.jpeg(world_from_base), t_mid, t_mid))
    return Drive(scans, poses, images, truth, calibration)


@functools.cache
def grid_drive() -> Drive:
    """The paper's straight case: a 2 x 3 grid of citrus trees 5 m apart (rows at y = 0
    and y = 5, trees at x = 0, 5, 10), the robot between the rows at 0.5 m/s for 20 s,
    from 9.5 m before the front trees (their tops in the top ring's view) to beside them.
    The back trees are seen only from 9.5-15 m, mostly behind the middle ones."""
    specs = grid_orchard(2, 3, 5.0, 5.0, np.random.default_rng(1))
    return drive(specs, start=(-9.5, 2.5), heading=0.0, speed=0.5, seconds=20.0, frames=True)


def map_twin_drive_watching(
    config: MapperConfig, owner: object, name: str, spy: Callable, trees: bool = False
) -> None:
    """The mapper over the twin drive (`grid_drive`) with `owner.name` replaced meanwhile
    by `spy(original)`, which records what it is called with (kernel tests replay those
    inputs); `trees`: `mapper.trees()` after every scan too."""
    data = grid_drive()
    mapper = TreeMapper(config, data.calibration)
    original = getattr(owner, name)
    setattr(owner, name, spy(original))
    try:
        for scan, pose in zip(data.scans, data.poses, strict=True):
            mapper.process(scan, None, pose)
            if trees:
                mapper.trees()
    finally:
        setattr(owner, name, original)


@functools.cache
def mapped(method: str = "paper") -> tuple[TreeMapper, tuple[ScanResult, ...]]:
    data = grid_drive()
    mapper = TreeMapper(MapperConfig(traits=TraitsConfig(method=method)), data.calibration)
    results = tuple(
        mapper.process(s, f, p) for s, f, p in zip(data.scans, data.frames, data.poses, strict=True)
    )
    return mapper, results


def match(trees: list[TrackedTree], truth: list[TreeTruth], radius: float = 1.5):
    """Each tree to the nearest true tree within `radius` (x-y): {truth id: [trees]}, and
    the trees near none."""
    found: dict[str, list[TrackedTree]] = {t.tree_id: [] for t in truth}
    stray = []
    for tree in trees:
        gaps = [math.hypot(tree.x - t.x, tree.y - t.y) for t in truth]
        best = int(np.argmin(gaps))
        (found[truth[best].tree_id] if gaps[best] < radius else stray).append(tree)
    return found, stray


def ghost_returns(scans, fraction, seed=0):
    """Stray returns: `fraction` of the returns within 15 m above the ground pushed
    0.3-3 m further along their ray (mixed pixels behind crown edges, dust)."""
    rng = np.random.default_rng(seed)
    out = []
    for scan in scans:
        p = scan.points.copy()
        distance = np.sqrt(p["x"] ** 2 + p["y"] ** 2 + p["z"] ** 2)
        pool = np.flatnonzero((p["z"] > -0.1) & (distance < 15))
        pick = rng.choice(pool, int(fraction * len(pool)), replace=False)
        scale = 1 + rng.uniform(0.3, 3.0, len(pick)) / np.maximum(distance[pick], 0.5)
        for axis in ("x", "y", "z"):
            p[axis][pick] *= scale
        out.append(dataclasses.replace(scan, points=p))
    return out
