"""The vegetation cues side by side: real apple canopy, real indoor walls and furniture,
and each foliage model of the twin. How docs/pipeline.md's cue table was measured, and
whether the twin's models span what the real capture shows.

Sources, each cluster as the pipeline's detection makes it (`pipeline.vegetation`):
- real orchard: tests/fixtures/real_orchard (a VLP-16 on its side among apple rows), the
  clusters spanning more than 1 m in height with 50 returns or more (the rows' sections);
- real indoor: the three captures of tests/fixtures/vlp16 (walls, furniture, people), the
  clusters of a crown's shape (those the shape rules pass);
- twin <model>: one 2.7 m tree of each foliage model (sim/foliage.py) with its crown's
  near side 2, 5 and 8 m away, seeds 0..N-1, its largest cluster.

Per source, the 10th / 50th / 90th percentile of: `texture_m` (5 cm along a ring), the
ring roughness of consecutive firings (`classify.roughness`, in the LiDAR's own frame),
`planar_share`, the median `intensity`, the depth spread (range p90 - p10 within 0.3 m
of arc along a ring: how far returns reach into the crown) and the evidence.

    .venv/bin/python bench/cues.py [--seeds 3] [--scans 20] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO / "tests" / "fixtures"
ORCHARD = FIXTURES / "real_orchard" / "lfuji_apple_vlp16_sideways_2s.pcap"
ORCHARD_CALIBRATION = FIXTURES / "real_orchard" / "lfuji_sideways_calibration.json"
INDOOR = [
    FIXTURES / "vlp16" / name
    for name in (
        "veloview_vlp16_20hz_strongest.pcap",
        "einride_vlp16_strongest_1000pkts.bin",
        "nebula_vlp16_dual_10hz.pcap",
    )
]
TWIN_RANGES_M = (2.0, 5.0, 8.0)
QUANTILES = (10, 50, 90)
CROWN_SHAPED = ("tree", "smooth", "not_green")


def scans_of(path: Path, limit: int):
    from treetraits.drivers.records import Scan
    from treetraits.drivers.velodyne.reader import LidarReader
    from treetraits.drivers.velodyne.sources import open_source

    reader = LidarReader(open_source(path))
    try:
        scans = [item for item in reader if isinstance(item, Scan) and item.complete]
    finally:
        reader.close()
    return scans[:limit]


def clusters_of(scan, T_base_lidar):
    from treetraits.pipeline.config import DetectionConfig
    from treetraits.pipeline.detection import detect

    points = scan.distinct if scan.points["duplicate"].any() else scan.points
    return detect(points, None, T_base_lidar, DetectionConfig()).clusters


def depth_spread(points_lidar: np.ndarray, ring: np.ndarray, window_m: float = 0.3) -> float:
    """Median over rings and 0.3 m arcs of the range's p90 - p10 (arcs of 4 returns or
    more): how far into the object its returns reach."""
    reach = np.linalg.norm(points_lidar, axis=1)
    bearing = np.arctan2(points_lidar[:, 1], points_lidar[:, 0])
    spreads = []
    for r in np.unique(ring):
        mine = ring == r
        if mine.sum() < 4:
            continue
        arc = np.floor(bearing[mine] * np.median(reach[mine]) / window_m).astype(np.int64)
        for cell in np.unique(arc):
            inside = reach[mine][arc == cell]
            if len(inside) >= 4:
                spreads.append(float(np.percentile(inside, 90) - np.percentile(inside, 10)))
    return float(np.median(spreads)) if spreads else math.nan


def row_of(cluster, T_base_lidar) -> dict[str, float]:
    from treetraits.pipeline.classify import roughness

    rotation, origin = T_base_lidar[:3, :3], T_base_lidar[:3, 3]
    in_lidar = (np.asarray(cluster.points) - origin) @ rotation
    return {
        "texture_m": cluster.cues.texture_m,
        "ring_roughness_m": roughness(in_lidar, cluster.ring, np.zeros(2)),
        "planar_share": cluster.cues.planar_share,
        "intensity": cluster.cues.intensity,
        "depth_spread_m": depth_spread(in_lidar, cluster.ring),
        "evidence": cluster.evidence.total,
    }


def real_orchard(scans: int) -> list[dict]:
    from treetraits.drivers.calibration import load_calibration

    T = load_calibration(ORCHARD_CALIBRATION).T_base_lidar
    rows = []
    for scan in scans_of(ORCHARD, scans):
        for c in clusters_of(scan, T):
            if np.ptp(c.points[:, 2]) > 1.0 and len(c.points) >= 50:
                rows.append(row_of(c, T))
    return rows


def real_indoor(scans: int) -> list[dict]:
    from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR

    rows = []
    for path in INDOOR:
        for scan in scans_of(path, scans):
            for c in clusters_of(scan, DEFAULT_T_BASE_LIDAR):
                if c.verdict in CROWN_SHAPED:
                    rows.append(row_of(c, DEFAULT_T_BASE_LIDAR))
    return rows


def twin(model: str, seeds: int) -> list[dict]:
    from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
    from treetraits.sim.foliage import tree_scan

    rows = []
    for range_m in TWIN_RANGES_M:
        for seed in range(seeds):
            scan = tree_scan(model, range_m, seed).scan
            clusters = clusters_of(scan, DEFAULT_T_BASE_LIDAR)
            if clusters:
                crown = max(clusters, key=lambda c: len(c.points))
                rows.append(row_of(crown, DEFAULT_T_BASE_LIDAR))
    return rows


def summary(rows: list[dict]) -> dict[str, list[float | None]]:
    out = {}
    for key in rows[0] if rows else ():
        values = np.array([r[key] for r in rows], dtype=float)
        values = values[np.isfinite(values)]
        out[key] = [
            round(float(np.percentile(values, q)), 4) if len(values) else None for q in QUANTILES
        ]
    return out


def main() -> int:
    from treetraits.sim.foliage import MODELS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3, help="twin trees per model and range")
    parser.add_argument("--scans", type=int, default=20, help="scans of each real capture")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args()
    sources = {"real orchard": real_orchard(args.scans), "real indoor": real_indoor(args.scans)}
    for model in MODELS:
        sources[f"twin {model}"] = twin(model, args.seeds)
    table = {name: {"clusters": len(rows), **summary(rows)} for name, rows in sources.items()}
    if args.json:
        print(json.dumps(table, indent=1))
        return 0
    keys = [k for k in next(iter(table.values())) if k != "clusters"]
    print(f"{'source':16} {'n':>4}  " + "  ".join(f"{k + ' p10/50/90':>26}" for k in keys))
    for name, facts in table.items():
        cells = [
            "/".join("-" if v is None else f"{v:.3g}" for v in facts.get(k, [None] * 3))
            for k in keys
        ]
        print(f"{name:16} {facts['clusters']:>4}  " + "  ".join(f"{c:>26}" for c in cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
