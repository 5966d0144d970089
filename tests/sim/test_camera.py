"""The Survey3N emulator and the LiDAR emulator see the same orchard through two
independent paths (camera rays through the calibrated lens; LiDAR packets through our
decoder, then our projection): fused, tree points must read foliage NDVI and ground points
soil NDVI. A wrong extrinsic, lens model or frame convention would smear them."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.paths import FIXTURES
from treetraits.drivers.calibration import load_calibration
from treetraits.drivers.records import Frame
from treetraits.drivers.velodyne.batcher import ScanBatcher
from treetraits.pipeline.fusion import fuse_scan
from treetraits.pipeline.ndvi import ndvi_image
from treetraits.sim.camera import FOLIAGE, SOIL, Survey3Emulator
from treetraits.sim.lidar import Scene, Vlp16Emulator
from treetraits.sim.orchard import Ground, grid_orchard, ground_mesh, tree_mesh

CALIBRATION = load_calibration(FIXTURES / "citrusfarm_calib" / "citrusfarm_calibration_v1.json")


def ndvi_of(bands):
    red, _, nir = bands
    return (nir - red) / (nir + red)


@pytest.fixture(scope="module")
def orchard_view():
    rng = np.random.default_rng(11)
    ground = Ground()
    scene = Scene()
    scene.add(*ground_mesh(ground, (-30, 40), (-30, 30)), label=0)
    for i, spec in enumerate(grid_orchard(2, 4, 5.0, 4.5, rng)):
        scene.add(*tree_mesh(spec, ground, rng), label=i + 1)
    x, y, yaw = -2.0, 2.5, -0.35  # between the rows, turned towards row 1

    def standing(t):
        return np.full(t.shape, x), np.full(t.shape, y), np.zeros(t.shape), np.full(t.shape, yaw)

    batcher = ScanBatcher()
    scans = []
    lidar = Vlp16Emulator(scene, CALIBRATION.T_base_lidar, rng=rng)
    for t_device, payload in lidar.packets(standing, 0, int(0.35e9)):
        if (scan := batcher.push(payload, t_device)) is not None:
            scans.append(scan)
    world_from_base = np.eye(4)
    world_from_base[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    world_from_base[:2, 3] = (x, y)
    jpeg = Survey3Emulator(scene, CALIBRATION, rng=rng).jpeg(world_from_base)
    scan = scans[1]
    frame = Frame(jpeg, scan.t_host, scan.t_host - (scan.t_end - scan.t_start) // 2)
    return scan, frame


def test_rendered_frame_reads_back_the_intended_ndvi(orchard_view):
    _, frame = orchard_view
    image = frame.decode()
    assert image.shape == (720, 1280, 3)
    ndvi = ndvi_image(image, CALIBRATION.camera.channels, CALIBRATION.reflectance)
    values = ndvi[np.isfinite(ndvi)]
    # Foliage and soil both fill a good part of the view, at their own NDVI (JPEG + noise).
    assert np.mean(np.abs(values - ndvi_of(FOLIAGE)) < 0.05) > 0.2
    assert np.mean(np.abs(values - ndvi_of(SOIL)) < 0.05) > 0.2


def test_fused_points_land_on_what_they_hit(orchard_view):
    scan, frame = orchard_view
    fused = fuse_scan(scan, [frame], CALIBRATION)
    assert fused.reason == "ok"
    ndvi = fused.ndvi
    lidar_height = CALIBRATION.T_base_lidar[2, 3]
    above_ground = scan.points["z"] + lidar_height
    tree = (above_ground > 0.6) & np.isfinite(ndvi)  # crown points (trunks are thin)
    soil = (above_ground < 0.05) & np.isfinite(ndvi)
    assert tree.sum() > 1000 and soil.sum() > 1000
    # Within 0.1 of the intended NDVI; the few that miss sit on crown outlines, where the
    # camera and the LiDAR, 0.2 m apart, see slightly different edges.
    assert np.mean(np.abs(ndvi[tree] - ndvi_of(FOLIAGE)) < 0.1) > 0.95
    assert np.mean(np.abs(ndvi[soil] - ndvi_of(SOIL)) < 0.1) > 0.95
