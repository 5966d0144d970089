"""Per-scan cost of the tree pipeline (`TreeMapper.process`: detection, tracking, traits)
against the RPH baseline (`pipeline.rph.RphMapper`) on the same scans, in the same run.

The scans: the digital twin of an orchard (4 rows x 8 citrus trees, 5 m apart), the robot
driving between rows 2 and 3 at 0.5 m/s; VLP-16 packets emulated and decoded by our
batcher. Each benchmark scan is two consecutive rotations in one (the second moved into
the first's LiDAR frame with the exact poses): ~30k points, the density of a dual-return
VLP-16 scan and of the paper's 27-30k-point clouds. Both mappers are warmed up on the
first scans, then fed the following scans in order, one per round, interleaved (machine
noise hits both alike); medians over the rounds. Poses exact, in `odom`.

Printed: per-stage medians of ours (LiDAR only), ours with a 720p Survey3N frame (NDVI
fusion included), RPH as shipped and as retuned for single scans. Last line, exactly:
`pipeline_ms_median=M vs_rph=R`, M = our median ms per scan without a camera frame (the
input RPH gets), R = RPH's median / ours, with the faster of the two RPH presets
(conservative). The paper: 220 ms vs 530 ms on a Xavier AGX.

`--sweep` instead prints the measurements behind docs/pipeline.md (voxel x tolerance,
the innovation's scale, the merge, the trait methods under stray returns and pose
noise) on the 2 x 3 grid drive of tests/helpers/twin.py. It takes a few minutes.

    .venv/bin/python bench/pipeline.py [--rounds 30] [--sweep]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # `tests` for --sweep, when run as a script

from treetraits.drivers.calibration import load_calibration  # noqa: E402
from treetraits.drivers.records import Frame, Scan  # noqa: E402
from treetraits.drivers.velodyne.batcher import ScanBatcher  # noqa: E402
from treetraits.pipeline.config import (  # noqa: E402
    ClusterConfig,
    DetectionConfig,
    MapperConfig,
    TrackingConfig,
    TraitsConfig,
)
from treetraits.pipeline.localization.pose import Pose  # noqa: E402
from treetraits.pipeline.mapper import TreeMapper  # noqa: E402
from treetraits.sim.camera import Survey3Emulator  # noqa: E402
from treetraits.sim.lidar import Scene, Vlp16Emulator  # noqa: E402
from treetraits.sim.orchard import Ground, grid_orchard, ground_mesh, tree_mesh  # noqa: E402

CALIBRATION = ROOT / "tests" / "fixtures" / "citrusfarm_calib" / "citrusfarm_calibration_v1.json"
LATENCY_NS = 200_000
STAGES = ("crop", "mixed", "ground", "ndvi", "ndvi_check", "voxel", "stems", "cluster", "features")
STAGES += ("tracking", "traits")


def world_from_base(pose: Pose) -> np.ndarray:
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:3, 3] = (pose.x, pose.y, pose.z)
    return out


def orchard_scans(calibration, seconds: float, layout: str, seed: int = 0):
    """Complete scans and exact poses driving along a row gap; and the scene. `grid`:
    the paper's 2 x 3 grid, from 9.5 m before it; `orchard`: 4 rows x 8, between rows 2
    and 3, trees all around."""
    rng = np.random.default_rng(seed)
    ground = Ground()
    scene = Scene()
    scene.add(*ground_mesh(ground, (-30, 70), (-30, 45)), label=0)
    rows, per_row, (x0, y0) = {"grid": (2, 3, (-9.5, 2.5)), "orchard": (4, 8, (5.0, 7.5))}[layout]
    for i, spec in enumerate(grid_orchard(rows, per_row, 5.0, 5.0, rng)):
        scene.add(*tree_mesh(spec, ground, rng), label=i + 1)
    speed = 0.5

    def path(t):
        x = x0 + speed * np.asarray(t) / 1e9
        return x, np.full(np.shape(t), y0), np.zeros(np.shape(t)), np.zeros(np.shape(t))

    batcher, scans, poses = ScanBatcher(), [], []
    lidar = Vlp16Emulator(scene, calibration.T_base_lidar, rng=rng)
    for t_device, payload in lidar.packets(path, 0, int(seconds * 1e9)):
        scan = batcher.push(payload, t_device + LATENCY_NS)
        if scan is not None and scan.complete:
            t_mid = scan.t_host - (scan.t_end - scan.t_start) // 2
            x = float(path(np.array(t_mid - LATENCY_NS))[0])
            scans.append(scan)
            poses.append(Pose(t_mid, x, y0, 0.0, np.eye(3) * 1e-4, "odom"))
    return scans, poses, scene


def merge_pairs(scans, poses, calibration) -> list[tuple[Scan, Pose]]:
    """Two consecutive rotations as one scan in the first's LiDAR frame (exact poses)."""
    T_base_lidar = calibration.T_base_lidar
    out = []
    for i in range(0, len(scans) - 1, 2):
        first, second = scans[i], scans[i + 1]
        T = (
            np.linalg.inv(world_from_base(poses[i]) @ T_base_lidar)
            @ world_from_base(poses[i + 1])
            @ T_base_lidar
        )
        moved = second.points.copy()
        xyz = np.column_stack([moved["x"], moved["y"], moved["z"]]).astype(float)
        xyz = xyz @ T[:3, :3].T + T[:3, 3]
        moved["x"], moved["y"], moved["z"] = xyz.T
        points = np.concatenate([first.points, moved])
        merged = dataclasses.replace(first, points=points, packets=first.packets + second.packets)
        out.append((merged, poses[i]))
    return out


def timed(function, *args, **kwargs):
    start = time.perf_counter()
    result = function(*args, **kwargs)
    return (time.perf_counter() - start) * 1e3, result


def bench(rounds: int, layout: str) -> None:
    from treetraits.pipeline.rph import RphMapper, rph_config

    calibration = load_calibration(CALIBRATION)
    warmup = 5
    seconds = (2 * (rounds + warmup) + 3) / 10
    scans, poses, scene = orchard_scans(calibration, seconds, layout)
    pairs = merge_pairs(scans, poses, calibration)[: rounds + warmup]
    # One 720p frame, rendered at the middle pose and re-stamped for each scan: its cost
    # (decode, NDVI, projection) does not depend on what it shows.
    middle = pairs[len(pairs) // 2][1]
    jpeg = Survey3Emulator(scene, calibration).jpeg(world_from_base(middle))

    def frame_for(pose: Pose) -> Frame:
        return Frame(jpeg, pose.t, pose.t)

    ours = TreeMapper(MapperConfig(), calibration, timing=True)
    ours_cam = TreeMapper(MapperConfig(), calibration, timing=True)
    robust = TreeMapper(MapperConfig(traits=TraitsConfig(method="robust")), calibration)
    rph = {name: RphMapper(rph_config(name), calibration) for name in ("shipped", "vlp16")}
    for scan, pose in pairs[:warmup]:
        ours.process(scan, None, pose)
        ours_cam.process(scan, frame_for(pose), pose)
        robust.process(scan, None, pose)
        for mapper in rph.values():
            mapper.process(scan, None, pose)

    times: dict[str, list[float]] = {"ours": [], "ours+frame": [], "robust": []}
    times.update({f"rph-{name}": [] for name in rph})
    stages: dict[str, list[float]] = {name: [] for name in STAGES}
    cam_stages: dict[str, list[float]] = {name: [] for name in STAGES}
    sizes, clusters = [], {"ours": [], "rph-shipped": [], "rph-vlp16": []}
    for scan, pose in pairs[warmup:]:
        sizes.append(len(scan.points))
        ms, result = timed(ours.process, scan, None, pose)
        times["ours"].append(ms)
        clusters["ours"].append(len(result.clusters))
        for name in STAGES:
            stages[name].append(result.stage_ms.get(name, 0.0))
        ms, result = timed(ours_cam.process, scan, frame_for(pose), pose)
        times["ours+frame"].append(ms)
        for name in STAGES:
            cam_stages[name].append(result.stage_ms.get(name, 0.0))
        times["robust"].append(timed(robust.process, scan, None, pose)[0])
        for name, mapper in rph.items():
            ms, result = timed(mapper.process, scan, None, pose)
            times[f"rph-{name}"].append(ms)
            clusters[f"rph-{name}"].append(len(result.clusters))

    median = {name: statistics.median(values) for name, values in times.items()}
    print(
        f"{rounds} rounds after {warmup} warm-up scans; scans of {min(sizes)}-{max(sizes)} "
        f"points (median {int(statistics.median(sizes))}); medians in ms"
    )
    print(f"  {'stage':<12s} {'ours':>8s} {'+frame':>8s}")
    for name in STAGES:
        a, b = statistics.median(stages[name]), statistics.median(cam_stages[name])
        print(f"  {name:<12s} {a:8.2f} {b:8.2f}")
    print(f"  {'sum':<12s} {sum(map(statistics.median, stages.values())):8.2f}")
    for name, value in median.items():
        extra = ""
        if name in clusters:
            extra = f"  ({statistics.median(clusters[name]):.0f} clusters/scan)"
        print(f"  {name + ' process()':<24s} {value:8.2f}{extra}")
    kd, db = clustering_alone(pairs[warmup:], calibration)
    print(f"  clustering alone (same clusters): kdtree {kd:.2f} ms, open3d dbscan {db:.2f} ms")
    rph_ms = min(median["rph-shipped"], median["rph-vlp16"])
    print(
        f"trees: ours {len(ours.trees())}, robust {len(robust.trees())}, "
        f"rph-shipped {len(rph['shipped'].trees())}, rph-vlp16 {len(rph['vlp16'].trees())}"
    )
    print(f"pipeline_ms_median={median['ours']:.2f} vs_rph={rph_ms / median['ours']:.2f}")


def clustering_alone(pairs, calibration) -> tuple[float, float]:
    """Median time of the Euclidean clustering step alone on each scan's voxels, with
    the two implementations (they must agree)."""
    from treetraits.pipeline.detection import (
        crop_mask,
        euclidean_clusters,
        fit_ground,
        to_base,
        voxel_grid,
    )

    config = MapperConfig()
    T = calibration.T_base_lidar
    times: dict[str, list[float]] = {"kdtree": [], "dbscan": []}
    for scan, _ in pairs:
        xyz = to_base(scan.points, T)
        xyz = xyz[crop_mask(xyz, config.detection.crop, T[:2, 3])]
        xyz = xyz[
            fit_ground(xyz, config.detection.ground).height(xyz)
            >= config.detection.ground.clearance_m
        ]
        _, voxels = voxel_grid(xyz, config.detection.cluster.voxel_m)
        labels = {}
        for method in times:
            ms, labels[method] = timed(
                euclidean_clusters, voxels, config.detection.cluster.tolerance_m, method
            )
            times[method].append(ms)
        assert np.array_equal(labels["kdtree"], labels["dbscan"])
    return statistics.median(times["kdtree"]), statistics.median(times["dbscan"])


# --- the measurements behind docs/pipeline.md -----------------------------------------------


def sweep() -> None:
    from tests.helpers.twin import ghost_returns, grid_drive, match

    data = grid_drive()

    def run(config, scans=None, poses=None, frames=True):
        mapper = TreeMapper(config, data.calibration, timing=True)
        scans = scans or data.scans
        poses = poses or data.poses
        outcomes: dict[str, int] = {}
        ms = []
        for i, (scan, pose) in enumerate(zip(scans, poses, strict=True)):
            frame = data.frames[i] if frames else None
            result = mapper.process(scan, frame, pose)
            ms.append(sum(result.stage_ms.values()))
            for c in result.clusters:
                outcomes[c.outcome] = outcomes.get(c.outcome, 0) + 1
        return mapper, outcomes, statistics.median(ms)

    def score(mapper):
        found, stray = match(mapper.trees(), data.truth)
        width, height, position = [], [], []
        for t in data.truth:
            if not found[t.tree_id]:
                continue
            tree = max(found[t.tree_id], key=lambda tree: tree.observations)
            width.append(100 * (tree.width_m - t.width) / t.width)
            height.append(100 * (tree.height_m - t.height) / t.height)
            position.append(math.hypot(tree.x - t.x, tree.y - t.y))
        return {
            "found": sum(1 for v in found.values() if v),
            "dups": sum(max(0, len(v) - 1) for v in found.values()),
            "stray": len(stray),
            "w_mape": float(np.mean(np.abs(width))),
            "h_mape": float(np.mean(np.abs(height))),
            "w": np.round(width, 1).tolist(),
            "h": np.round(height, 1).tolist(),
            "pos_max": max(position),
        }

    print("# voxel x tolerance (paper traits, camera frames, exact poses)")
    print("voxel tol  ms   created updated found dups stray  W-MAPE H-MAPE")
    for voxel in (0.1, 0.15, 0.2, 0.25):
        for tolerance in (0.3, 0.4, 0.5, 0.6):
            config = MapperConfig(
                DetectionConfig(cluster=ClusterConfig(voxel_m=voxel, tolerance_m=tolerance))
            )
            mapper, outcomes, ms = run(config)
            s = score(mapper)
            print(
                f"{voxel:5.2f} {tolerance:4.1f} {ms:5.1f} {outcomes.get('created', 0):7d} "
                f"{outcomes.get('updated', 0):7d} {s['found']:5d} {s['dups']:4d} {s['stray']:5d} "
                f"{s['w_mape']:7.2f} {s['h_mape']:6.2f}"
            )
    print("# clustering method (same clusters?) at the defaults")
    for method in ("kdtree", "dbscan"):
        config = MapperConfig(DetectionConfig(cluster=ClusterConfig(method=method)))
        mapper, outcomes, ms = run(config)
        print(f"{method:7s} {ms:5.1f} ms/scan  {outcomes}  {score(mapper)['w_mape']:.2f}")
    print("# innovation scale (x1 = fractions, x100 = percent) and the merge")
    print("scale merge created updated trees found dups")
    for percent in (1.0, 10.0, 30.0, 100.0):
        for merge in (1.5, 0.0):
            config = MapperConfig(tracking=TrackingConfig(percent=percent, merge_distance_m=merge))
            mapper, outcomes, _ = run(config)
            s = score(mapper)
            print(
                f"{percent:5.0f} {merge:5.1f} {outcomes.get('created', 0):7d} "
                f"{outcomes.get('updated', 0):7d} {len(mapper.trees()):5d} {s['found']:5d} "
                f"{s['dups']:4d}"
            )
    print("# traits: paper vs robust (front T1 / middle T2 / back T3 per row; % error)")
    rng = np.random.default_rng(4)
    rtk = [
        dataclasses.replace(
            p,
            x=p.x + rng.normal(0, 0.02),
            y=p.y + rng.normal(0, 0.02),
            yaw=p.yaw + rng.normal(0, math.radians(0.2)),
        )
        for p in data.poses
    ]
    x0 = data.poses[0].x
    drift = [  # wheel odometry: 1 % scale error, heading drifting 0.3 deg per metre
        dataclasses.replace(
            p,
            x=x0 + (p.x - x0) * 1.01,
            y=p.y + 0.5 * math.radians(0.3) * (p.x - x0) ** 2,
            yaw=p.yaw + math.radians(0.3) * (p.x - x0),
        )
        for p in data.poses
    ]
    cases = {
        "clean": (None, None),
        "ghost 0.5%": (ghost_returns(data.scans, 0.005), None),
        "ghost 2%": (ghost_returns(data.scans, 0.02), None),
        "rtk noise": (None, rtk),
        "odom drift": (None, drift),
    }
    print("truth ids:", [t.tree_id for t in data.truth])
    for case, (scans, poses) in cases.items():
        for method in ("paper", "robust"):
            config = MapperConfig(traits=TraitsConfig(method=method))
            mapper, _, _ = run(config, scans, poses, frames=False)
            s = score(mapper)
            print(
                f"{case:11s} {method:6s} W-MAPE {s['w_mape']:5.2f} {s['w']}  "
                f"H-MAPE {s['h_mape']:5.2f} {s['h']}  pos<= {s['pos_max']:.2f} m"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--layout", choices=("grid", "orchard"), default="grid")
    parser.add_argument("--sweep", action="store_true", help="the docs' measurements instead")
    args = parser.parse_args()
    if args.sweep:
        sweep()
        return
    try:
        import treetraits.pipeline.rph  # noqa: F401
    except ImportError as exc:
        print(f"RPH baseline not available (pipeline.rph: {exc}); no comparison possible")
        raise SystemExit(1) from exc
    bench(args.rounds, args.layout)


if __name__ == "__main__":
    main()
