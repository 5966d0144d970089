"""Per-scan cost of the camera side: decode one 720p JPEG, NDVI, project a ~30k-point scan
with the z-buffer and sample NDVI per point, against the 100 ms a VLP-16 scan takes at
10 Hz. Peer in the same run: our projection against `cv2.projectPoints` on the same points.

The scan is a real dual-return VLP-16 rotation (29,202 points, `nebula_vlp16_dual_10hz`),
the calibration the real CitrusFarm Survey3N one; the frame is a synthetic 1280x720 RGN
image with texture and noise (no real Survey3N JPEG is bundled), encoded at quality 90.
Several rounds, interleaved; medians.

Last line, exactly: `fusion_ms_median=M fraction_of_scan_period=F vs_cv2_projectpoints=R`,
where M is the median per-scan time of `fuse_scan` (frame choice + decode + NDVI +
projection + z-buffer + sampling), F = M / 100 ms and R = cv2's projection time / ours
(higher is better: > 1 means ours is faster).

    .venv/bin/python bench/fusion.py [--rounds 25]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from treetraits.drivers.calibration import load_calibration
from treetraits.drivers.records import Frame, Scan
from treetraits.drivers.velodyne.reader import LidarReader
from treetraits.drivers.velodyne.sources import open_source
from treetraits.pipeline.fusion import fuse_scan
from treetraits.pipeline.ndvi import ndvi_image
from treetraits.pipeline.projection import point_ndvi, project_points, scan_mid_time

FIXTURES = Path(__file__).resolve().parent.parent / "tests" / "fixtures"
CAPTURE = FIXTURES / "vlp16" / "nebula_vlp16_dual_10hz.pcap"
CALIBRATION = FIXTURES / "citrusfarm_calib" / "citrusfarm_calibration_v1.json"
SCAN_PERIOD_MS = 100.0  # VLP-16 at 600 rpm


def load_scan() -> Scan:
    reader = LidarReader(open_source(CAPTURE))
    scans = [s for s in reader if isinstance(s, Scan)]
    reader.close()
    return scans[1]  # the first complete rotation


def synthetic_jpeg(seed: int = 0) -> bytes:
    """A 1280x720 RGN-looking frame: smooth blobs (canopy, soil, sky) plus pixel noise."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0, 1, (18, 32, 3))
    smooth = cv2.resize(coarse, (1280, 720), interpolation=cv2.INTER_CUBIC)
    base = np.array([150.0, 80.0, 60.0]) + (smooth - 0.5) * np.array([120.0, 60.0, 80.0])
    image = np.clip(base + rng.normal(0, 6, (720, 1280, 3)), 0, 255).astype(np.uint8)
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return data.tobytes()


def timed(function, *args) -> float:
    start = time.perf_counter()
    function(*args)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=25)
    args = parser.parse_args()

    calibration = load_calibration(CALIBRATION)
    camera, extrinsic = calibration.camera, calibration.T_camera_lidar
    scan = load_scan()
    t = scan_mid_time(scan)
    frame = Frame(synthetic_jpeg(), t, t)
    points = np.column_stack([scan.points["x"], scan.points["y"], scan.points["z"]])
    points = points.astype(np.float64)
    rvec, _ = cv2.Rodrigues(extrinsic[:3, :3])
    tvec = extrinsic[:3, 3].copy()
    cv_points = points.reshape(-1, 1, 3)

    def ours_projection() -> None:
        project_points(points, camera, extrinsic)

    def cv2_projection() -> None:
        cv2.projectPoints(cv_points, rvec, tvec, camera.K, camera.dist)

    image = frame.decode()
    ndvi = ndvi_image(image, camera.channels, calibration.reflectance)
    parts = {
        "decode": lambda: frame.decode(),
        "ndvi": lambda: ndvi_image(image, camera.channels, calibration.reflectance),
        "points": lambda: point_ndvi(scan.points, ndvi, camera, extrinsic),
    }
    # Warm up caches, imports and OpenCV's thread pool.
    fuse_scan(scan, [frame], calibration), ours_projection(), cv2_projection()
    totals, ours, peer = [], [], []
    part_times: dict[str, list[float]] = {name: [] for name in parts}
    for _ in range(args.rounds):  # interleaved so machine noise hits all alike
        totals.append(timed(fuse_scan, scan, [frame], calibration))
        for name, function in parts.items():
            part_times[name].append(timed(function))
        ours.append(timed(ours_projection))
        peer.append(timed(cv2_projection))

    total_ms = statistics.median(totals) * 1e3
    ours_ms, peer_ms = statistics.median(ours) * 1e3, statistics.median(peer) * 1e3
    visible = int(project_points(points, camera, extrinsic).in_image.sum())
    print(
        f"scan: {len(points)} points ({visible} in the image), frame {camera.width}x"
        f"{camera.height} JPEG {len(frame.jpeg) // 1024} KiB, {args.rounds} rounds, medians"
    )
    for name, values in part_times.items():
        print(f"  {name:<22s} {statistics.median(values) * 1e3:8.2f} ms")
    print(f"  {'fuse_scan (all)':<22s} {total_ms:8.2f} ms")
    print(f"  {'project_points (ours)':<22s} {ours_ms:8.2f} ms")
    print(f"  {'cv2.projectPoints':<22s} {peer_ms:8.2f} ms")
    fraction = total_ms / SCAN_PERIOD_MS
    print(
        f"fusion_ms_median={total_ms:.2f} fraction_of_scan_period={fraction:.3f} "
        f"vs_cv2_projectpoints={peer_ms / ours_ms:.2f}"
    )


if __name__ == "__main__":
    main()
