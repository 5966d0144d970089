"""Ring roughness of each foliage model of the twin (sim/foliage.py), to set their
parameters by measurement: one default-sized tree at a time, its crown's near side at each
range, one scan of the VLP-16 emulator; `classify.roughness` of the crown's returns, the
median over seeds. A real VLP-16 in an apple row gives ~0.011 m at 1-2.5 m, ~0.030 m at
4-6 m and ~0.037 m at 6-9 m.

    .venv/bin/python bench/foliage.py [--models dense,clumped] [--ranges 2,5,8] [--seeds 4]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from treetraits.pipeline.classify import roughness
from treetraits.sim.foliage import MODELS, tree_scan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default=",".join(MODELS))
    parser.add_argument("--ranges", default="2,5,8", help="m, comma list")
    parser.add_argument("--seeds", type=int, default=4)
    args = parser.parse_args()
    ranges = [float(r) for r in args.ranges.split(",")]
    print(f"{'model':10} {'triangles':>9} " + " ".join(f"{r:>5.1f} m" for r in ranges) + "   s")
    for name in args.models.split(","):
        start = time.perf_counter()
        cells, returns_at, triangles = [], [], 0
        for r in ranges:
            values, ranges_m = [], []
            for seed in range(args.seeds):
                scan = tree_scan(name, r, seed)
                triangles = scan.triangles
                values.append(roughness(scan.points, scan.ring, np.zeros(2)))
                ranges_m.append(float(np.median(scan.range_m)))
            cells.append(float(np.median(values)))
            returns_at.append(float(np.median(ranges_m)))
        took = time.perf_counter() - start
        print(f"{name:10} {triangles:9d} " + " ".join(f"{c:7.3f}" for c in cells) + f" {took:4.1f}")
        # Where the returns are: the near side at the range, the flanks farther.
        print(f"{'':10} {'median m':>9} " + " ".join(f"{r:7.2f}" for r in returns_at))


if __name__ == "__main__":
    main()
