"""Orchard scale: a survey grown to 50,000 mapped trees through the real mapper, store and
export path, and the cost of one scan near its start and at its end.

The orchard is synthetic. Rows of trees run east, `--row-m` long (default 500 m), 5 m
apart, a tree every 2.5 m along a row, each tree at its planted spot plus a seeded
jitter of up to 0.2 m; the field map holds every tree (WGS84, in a UTM grid near
Valencia, 39.47 N, 0.38 W). The robot drives a serpentine, one lane between every second
pair of rows (a lane sees its two rows, both new), `--step-m` (default 5 m) per scan,
at 10 scans a second of survey time, with an exact pose in `utm`. Each scan sees the trees
of its two rows within 7.5 m ahead or behind (about 12), so each tree is seen in 3 scans
(`output.min_observations`), each as one cluster: its crown,
a seeded ellipsoid shell of 120 returns (radius 1.0-1.4 m, top 2.6-3.4 m above flat
ground, a trunk of 20 returns under it) placed in the robot's `base` frame, rings from
each return's elevation as a VLP-16 sees it, no NDVI. Detection itself is left out
(`TreeMapper.process_detection`): its cost depends on the points in view, not on the
trees mapped, and `bench/pipeline.py` times it.

Per scan, timed: `TreeMapper.process_detection` and `RunWriter.commit` (the scan's
observations and touched trees georeferenced, matched to the field map and written to
`traits.sqlite`), as the replay and the service call them. Every 50 scans (5 s, the
service's `output.export_every_s`) `RunWriter.export` rewrites trees.csv and
trees.geojson; its time is reported apart (it is not a scan's cost), with how far apart
the service would space exports that take so long (`output.export_max_share`) and the
share of a core they would then take. Times are the process's CPU time
(`time.process_time`: what the work costs, not how long a machine shared with other jobs
made it wait). The process is pinned to one CPU with one BLAS
thread.

Last line, exactly: `scan_ms_at_100=A scan_ms_at_50000=B growth=B/A rss_mb=M`, A and B the
median ms of the 100 scans after the map first holds 100 and `--trees` (50,000) trees,
M the process's peak RSS. With `--trees N` the second key is `scan_ms_at_N`.

    .venv/bin/python bench/scale.py [--trees 50000] [--row-m 500] [--step-m 5] [--cpu N]
"""

from __future__ import annotations

import os

# One thread for NumPy's BLAS and OpenMP: set before NumPy is first imported.
for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROW_SPACING_M = 5.0
TREE_SPACING_M = 2.5
SEEN_ALONG_M = 7.5  # a tree is a cluster of the scan while this near along the lane
CROWN_RETURNS, TRUNK_RETURNS = 120, 20
SCAN_NS = 100_000_000  # 10 scans a second
WINDOW = 100  # scans timed at each point
EXPORT_EVERY = 50  # scans (5 s)
ORIGIN = (39.47, -0.38)  # lat, lon of the orchard's corner
LIDAR_HEIGHT_M = 0.5  # ring elevations measured from here (the twin's VLP-16 mount)


def tree_xy(lane: int, side: int, index: int, rng_seed: int) -> np.ndarray:
    """Planted spot of tree `index` of row `2 lane + side`, with its fixed jitter (m,
    orchard frame: x along the rows, y across)."""
    jitter = np.random.default_rng((rng_seed, lane, side, index)).uniform(-0.2, 0.2, 2)
    row = 2 * lane + side
    return np.array([index * TREE_SPACING_M, row * ROW_SPACING_M]) + jitter


def crown(lane: int, side: int, index: int, seed: int) -> np.ndarray:
    """The returns of one tree (N x 3, around its spot, z up from the ground): the same
    each time it is seen, as a standing tree's surface is."""
    rng = np.random.default_rng((seed, lane, side, index, 1))
    radius = rng.uniform(1.0, 1.4)
    top = rng.uniform(2.6, 3.4)
    centre_z = top - radius
    u = rng.normal(size=(CROWN_RETURNS, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    shell = u * radius * rng.uniform(0.85, 1.0, (CROWN_RETURNS, 1))
    shell[:, 2] = centre_z + shell[:, 2] * 0.9
    trunk = np.column_stack(
        [
            rng.normal(0, 0.05, TRUNK_RETURNS),
            rng.normal(0, 0.05, TRUNK_RETURNS),
            rng.uniform(0.1, centre_z - 0.5 * radius, TRUNK_RETURNS),
        ]
    )
    return np.vstack([shell, trunk])


def rings(points_base: np.ndarray) -> np.ndarray:
    """VLP-16 ring of each return: -15 to +15 degrees in 2-degree steps from the LiDAR."""
    distance = np.hypot(points_base[:, 0], points_base[:, 1])
    elevation = np.degrees(np.arctan2(points_base[:, 2] - LIDAR_HEIGHT_M, distance))
    return np.clip(np.round((elevation + 15.0) / 2.0), 0, 15).astype(np.uint8)


class Orchard:
    """The synthetic survey: poses along the serpentine and each scan's clusters."""

    def __init__(self, row_m: float, step_m: float, seed: int, origin_en: tuple[float, float]):
        self.trees_per_row = int(row_m // TREE_SPACING_M) + 1
        self.row_m = (self.trees_per_row - 1) * TREE_SPACING_M
        self.step_m = step_m
        self.seed = seed
        self.origin = np.asarray(origin_en, dtype=float)
        self.scans_per_lane = int(self.row_m // step_m) + 1
        # Per tree in sight: its spot, returns, voxel centres (around the spot) and shape.
        self._trees: dict[tuple[int, int, int], tuple] = {}

    def robot(self, scan: int) -> tuple[float, float, float]:
        """(x, y, yaw) in the orchard frame: lanes driven east then west."""
        lane, k = divmod(scan, self.scans_per_lane)
        along = k * self.step_m
        y = (2 * lane + 0.5) * ROW_SPACING_M
        if lane % 2:
            return self.row_m - along, y, math.pi
        return along, y, 0.0

    def clusters(self, scan: int):
        """The scan's clusters (`pipeline.detection.Cluster`, base frame)."""
        from treetraits.pipeline.classify import TREE
        from treetraits.pipeline.detection import Cluster

        lane = scan // self.scans_per_lane
        x, y, yaw = self.robot(scan)
        c, s = math.cos(yaw), math.sin(yaw)
        first = max(0, math.ceil((x - SEEN_ALONG_M) / TREE_SPACING_M))
        last = min(self.trees_per_row - 1, math.floor((x + SEEN_ALONG_M) / TREE_SPACING_M))
        out = []
        for side in (0, 1):
            for index in range(first, last + 1):
                spot, local, voxels, shape, cues, evidence = self._tree(lane, side, index)
                dx, dy = spot[0] - x, spot[1] - y
                # base = Rz(-yaw) (world - robot): the tree's returns and voxels as seen now.
                rotation = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
                shift = np.array([c * dx + s * dy, -s * dx + c * dy, 0.0])
                points = local @ rotation.T + shift
                centres = voxels @ rotation.T + shift
                out.append(
                    Cluster(
                        centroid=centres.mean(axis=0),
                        num_points=len(centres),
                        ndvi=math.nan,
                        voxels=centres,
                        points=points,
                        ring=rings(points),
                        ground_z=0.0,
                        shape=shape,
                        verdict=TREE,
                        cues=cues,
                        evidence=evidence,
                    )
                )
        return out

    def _tree(self, lane: int, side: int, index: int) -> tuple:
        """A tree's fixed parts, made when it first comes in sight (trees of lanes passed
        are forgotten: the robot never comes back to them)."""
        from treetraits.pipeline.classify import shape_of
        from treetraits.pipeline.config import ClassifyConfig
        from treetraits.pipeline.vegetation import Cues, weigh

        key = (lane, side, index)
        if key not in self._trees:
            self._trees = {k: v for k, v in self._trees.items() if k[0] >= lane}
            local = crown(lane, side, index, self.seed)
            voxels = np.unique(np.floor(local / 0.1), axis=0) * 0.1 + 0.05
            # What detection's classifier reads (from a LiDAR 4 m away); the verdict is set.
            shape = shape_of(local, rings(local - (0.0, 4.0, 0.0)), np.array([0.0, 4.0]), 0.0)
            # And its vegetation cues, as a real crown reads without a camera (the real
            # orchard capture's medians, bench/cues.py): a tree by its evidence, as the
            # mapper judges a track, not by the per-scan verdict alone.
            cues = Cues(
                texture_m=0.075, texture_triples=30, planar_share=0.2, planar_patches=10,
                intensity=18.0,
            )  # fmt: skip
            evidence = weigh(cues, ClassifyConfig())
            self._trees[key] = (
                tree_xy(lane, side, index, self.seed),
                local,
                voxels,
                shape,
                cues,
                evidence,
            )
        return self._trees[key]

    def pose(self, scan: int, t: int):
        from treetraits.pipeline.localization.pose import Pose

        x, y, yaw = self.robot(scan)
        return Pose(
            t, float(self.origin[0] + x), float(self.origin[1] + y), yaw, np.eye(3) * 1e-4, "utm"
        )

    def field_map(self, grid, lanes: int) -> list:
        """Every tree of the first `lanes` lanes as a field-map tree (WGS84)."""
        from treetraits.pipeline.fieldmap import FieldTree

        spots, names = [], []
        for lane in range(lanes):
            for side in (0, 1):
                for index in range(self.trees_per_row):
                    spots.append(tree_xy(lane, side, index, self.seed) + self.origin)
                    names.append((f"R{2 * lane + side + 1}T{index + 1}", str(2 * lane + side + 1)))
        spots = np.array(spots)
        lat, lon = grid.inverse(spots[:, 0], spots[:, 1])
        return [
            FieldTree(name, float(a), float(o), row)
            for (name, row), a, o in zip(names, lat, lon, strict=True)
        ]


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trees", type=int, default=50_000, help="grow to (default 50000)")
    parser.add_argument("--row-m", type=float, default=500.0, help="row length (default 500)")
    parser.add_argument("--step-m", type=float, default=5.0, help="m per scan (default 5)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--retire-m",
        type=float,
        help="tracking.retire_m (default: the config's; 0 keeps every tree in memory)",
    )
    parser.add_argument("--out", type=Path, help="keep the outputs here (default: a temp dir)")
    parser.add_argument("--cpu", type=int, help="the CPU to pin to (default: the first allowed)")
    args = parser.parse_args()
    if args.trees < 2 * 100:
        parser.error("--trees must be at least 200")

    cpu = args.cpu if args.cpu is not None else min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})

    from tqdm import tqdm

    from treetraits.drivers.calibration import Calibration
    from treetraits.pipeline.detection import Detection, GroundPlane
    from treetraits.pipeline.localization.utm import UtmGrid
    from treetraits.pipeline.mapper import TreeMapper
    from treetraits.service.config import ServiceConfig
    from treetraits.service.outputs import RunWriter, next_export_after
    from treetraits.service.survey import ScanOutcome, SurveyProcessor

    calibration = Calibration()
    config = ServiceConfig()
    if args.retire_m is not None:
        config = replace(config, tracking=replace(config.tracking, retire_m=args.retire_m))
    mapper = TreeMapper(config.mapper(), calibration)
    processor = SurveyProcessor(mapper, calibration)
    # The run's UTM grid, as the first fix would set it (no GNSS is simulated).
    grid = UtmGrid.for_position(*ORIGIN)
    processor.localizer.grid = grid
    processor.world_frame = "utm"
    orchard = Orchard(args.row_m, args.step_m, args.seed, grid.forward(*ORIGIN))
    lanes = math.ceil(args.trees / (2 * orchard.trees_per_row)) + 1
    field_map = orchard.field_map(grid, lanes)

    # Flat, level ground at z = 0 of base, as detection reports it.
    ground = GroundPlane(np.array([0.0, 0.0, 1.0]), 0.0, 0, True)
    times: dict[int, list[float]] = {100: [], args.trees: []}
    exports: dict[int, list[float]] = {100: [], args.trees: []}
    reached: dict[int, int] = {}  # goal -> scan at which the map first held it
    mapped = 0
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as temp:
        out = args.out or Path(temp)
        out.mkdir(parents=True, exist_ok=True)
        writer = RunWriter(Path(out), processor, field_map, config.output)
        progress = tqdm(total=args.trees, unit="tree", file=sys.stderr, mininterval=2.0)
        scan = 0
        while len(times[args.trees]) < WINDOW:
            t = 1_700_000_000_000_000_000 + scan * SCAN_NS
            detection = Detection(orchard.clusters(scan), ground)
            pose = orchard.pose(scan, t)
            start = time.process_time()
            result = mapper.process_detection(detection, t, pose)
            writer.commit(ScanOutcome(None, pose, None, result))
            elapsed = (time.process_time() - start) * 1e3
            mapped = max(mapped, max((c.tree_id for c in result.clusters), default=0))
            progress.update(min(mapped, args.trees) - progress.n)
            for goal in times:
                if mapped >= goal and goal not in reached:
                    reached[goal] = scan
                if goal in reached and len(times[goal]) < WINDOW:
                    times[goal].append(elapsed)
            if scan % EXPORT_EVERY == EXPORT_EVERY - 1:
                start = time.process_time()
                writer.export()
                export_ms = (time.process_time() - start) * 1e3
                for goal in times:  # the exports within a goal's window of scans
                    if goal in reached and scan < reached[goal] + WINDOW + EXPORT_EVERY:
                        exports[goal].append(export_ms)
            scan += 1
        progress.close()
        final = writer.export()
        writer.close()

    a, b = statistics.median(times[100]), statistics.median(times[args.trees])
    print(
        f"orchard: rows {orchard.row_m:.0f} m, {orchard.trees_per_row} trees a row, "
        f"{len(field_map)} trees in the field map; {scan} scans, {mapped} tree ids, "
        f"{len(final.found)} reported, {sum(t.field_id is not None for t in final.found)} "
        f"matched; CPU {cpu}"
    )
    share = config.output.export_max_share
    for goal in times:
        e = statistics.median(exports[goal]) if exports[goal] else math.nan
        median, p90 = statistics.median(times[goal]), np.percentile(times[goal], 90)
        # The service's spacing of exports that take this long (`next_export_after`).
        gap = next_export_after(0.0, e / 1e3, config.output.export_every_s, share)
        print(
            f"  at {goal:6d} trees (scan {reached[goal]}): scan {median:7.2f} ms median, "
            f"p90 {p90:7.2f} ms; export {e:8.1f} ms, live every {gap:4.1f} s: "
            f"{100 * e / 1e3 / (gap + e / 1e3):.1f} % of a core"
        )
    growth = f"growth={b / a:.2f} rss_mb={rss_mb():.0f}"
    print(f"scan_ms_at_100={a:.2f} scan_ms_at_{args.trees}={b:.2f} {growth}")


if __name__ == "__main__":
    main()
