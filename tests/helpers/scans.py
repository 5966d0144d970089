"""Scans of the twin's scenes: ray-cast by its VLP-16 emulator from a robot standing at the
origin, decoded by our own batcher."""

from __future__ import annotations

import numpy as np

from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.sim.lidar import Scene
from treetraits.sim.orchard import Ground, ground_mesh


def first_complete_scan(scene, T_base_lidar, rng, seconds: float = 0.35):
    """The first complete scan the twin's VLP-16 emulator sends from a robot standing at
    the origin (yaw 0), decoded by our own batcher."""
    from treetraits.drivers.velodyne.batcher import ScanBatcher
    from treetraits.sim.lidar import Vlp16Emulator

    def standing(t):
        zeros = np.zeros(t.shape)
        return zeros, zeros, zeros, zeros

    batcher = ScanBatcher()
    emulator = Vlp16Emulator(scene, T_base_lidar, rng=rng)
    for t_device, payload in emulator.packets(standing, 0, int(seconds * 1e9)):
        scan = batcher.push(payload, t_device)
        if scan is not None and scan.complete:
            return scan
    raise AssertionError("no complete scan")


def scan_of(*meshes, seed=5):
    """One scan of flat ground and the given meshes from a robot standing at the origin."""
    rng = np.random.default_rng(seed)
    scene = Scene()
    scene.add(*ground_mesh(Ground(), (-30, 30), (-30, 30)), label=0)
    for i, (vertices, triangles) in enumerate(meshes):
        scene.add(np.asarray(vertices, np.float32), np.asarray(triangles, np.int32), label=i + 1)

    return first_complete_scan(scene, DEFAULT_T_BASE_LIDAR, rng)
