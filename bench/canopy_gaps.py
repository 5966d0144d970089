"""How often one LiDAR beam passes through the top of a real canopy: the physical reason
a crown's height is bounded by what two scans agree on (`pipeline.mapper`,
`_Tree.height_measured`), measured on real returns.

The real orchard capture (tests/fixtures/real_orchard: a VLP-16 on its side among apple
rows, 1.4 m up) turns each rotation into a vertical cross-section of both rows. Per scan,
ring and side, the row's returns (0.4-3 m across, above the sensor) give its top; in the
band from the top down 0.5 m, the firings whose ray crosses the band at the row's median
distance are counted from the ring's median firing step, and those without a return in
the band passed through it. A beam over a crown's top in our top test is such a beam: one
that saw nothing may have passed through the top layer, not over it.

Last line: `through_share=S median_sweep=M p10=A p90=B sweeps=N`.

    .venv/bin/python bench/canopy_gaps.py [--band 0.5]
"""

from __future__ import annotations

import argparse

import numpy as np
from cues import ORCHARD, ORCHARD_CALIBRATION, scans_of

ROW_ACROSS_M = (0.4, 3.0)  # the near rows, 3.3 m apart: the alley's centre to past a row
MIN_FIRINGS = 3  # a band crossed by fewer firings says nothing


def through_shares(scans, T_base_lidar: np.ndarray, band_m: float) -> tuple[float, list[float]]:
    """The share of firings through the band over all sweeps, and each sweep's share."""
    height = T_base_lidar[2, 3]
    through = crossing = 0.0
    shares = []
    for scan in scans:
        p = scan.points
        xyz = np.column_stack([p["x"], p["y"], p["z"]]).astype(float)
        xyz = xyz @ T_base_lidar[:3, :3].T + T_base_lidar[:3, 3]
        azimuth = p["azimuth"].astype(float)  # radians
        for ring in np.unique(p["ring"]):
            mine = p["ring"] == ring
            if mine.sum() < 10:
                continue
            step = float(np.median(np.diff(np.sort(azimuth[mine]))))
            for side in (1.0, -1.0):
                across, z = xyz[mine, 1] * side, xyz[mine, 2]
                row = (across > ROW_ACROSS_M[0]) & (across < ROW_ACROSS_M[1]) & (z > height)
                if row.sum() < 10:
                    continue
                top = float(z[row].max())
                in_band = row & (z > top - band_m)
                distance = float(np.median(across[in_band]))
                low = np.arctan2(top - band_m - height, distance)
                firings = (np.arctan2(top - height, distance) - low) / step
                if firings < MIN_FIRINGS:
                    continue
                missed = max(0.0, firings - int(in_band.sum()))
                through += missed
                crossing += firings
                shares.append(missed / firings)
    return through / crossing, shares


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--band", type=float, default=0.5, help="the top band's depth (m)")
    args = parser.parse_args()
    from treetraits.drivers.calibration import load_calibration

    T_base_lidar = np.asarray(load_calibration(ORCHARD_CALIBRATION).T_base_lidar, dtype=float)
    scans = scans_of(ORCHARD, 1_000)  # every complete scan (20)
    share, shares = through_shares(scans, T_base_lidar, args.band)
    p10, median, p90 = np.percentile(shares, (10, 50, 90))
    print(f"{len(scans)} scans, {len(shares)} ring sweeps of a row's top {args.band} m")
    print(
        f"through_share={share:.3f} median_sweep={median:.3f} p10={p10:.3f} p90={p90:.3f} "
        f"sweeps={len(shares)}"
    )


if __name__ == "__main__":
    main()
