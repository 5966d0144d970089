"""Facts about a LiDAR stream, gathered in one pass (for `treetraits lidar info`).

`full_scans` follows the reference facts' definition: every scan but the first and the
last of the input, because a capture starts and stops at arbitrary points.
`complete_scans` is the batcher's own account (scans seen to begin and end at the cut);
it can be one higher when a file happens to end exactly at a cut.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne.telemetry import Telemetry


@dataclass
class LidarSummary:
    scan_points: list[int] = field(default_factory=list)  # distinct points per scan
    complete_scans: int = 0
    lost_packets: int = 0
    models: Counter = field(default_factory=Counter)
    return_modes: Counter = field(default_factory=Counter)
    rings_present: set[int] = field(default_factory=set)
    t_first: int | None = None
    t_last: int | None = None
    sweep_rad: float = 0.0
    sweep_s: float = 0.0
    pps_status: Counter = field(default_factory=Counter)
    nmea_sentences: Counter = field(default_factory=Counter)

    def add_scan(self, scan: Scan) -> None:
        points = scan.distinct
        self.scan_points.append(len(points))
        self.complete_scans += int(scan.complete)
        self.lost_packets += scan.lost_packets
        self.models[scan.model] += 1
        self.return_modes[scan.return_mode] += 1
        self.rings_present.update(np.unique(points["ring"]).tolist())
        self.t_first = scan.t_start if self.t_first is None else self.t_first
        self.t_last = scan.t_end
        if len(points) > 1:
            # The sensor turns clockwise, so azimuth grows with time; unwrap it to
            # measure the rotation rate over the scan.
            order = np.argsort(points["t"], kind="stable")
            azimuth = np.unwrap(points["azimuth"][order].astype(np.float64))
            t = points["t"][order]
            self.sweep_rad += float(azimuth[-1] - azimuth[0])
            self.sweep_s += float(t[-1] - t[0]) / 1e9

    def add_telemetry(self, telemetry: Telemetry) -> None:
        self.pps_status[telemetry.pps] += 1
        if telemetry.nmea:
            self.nmea_sentences[telemetry.nmea] += 1

    @property
    def rpm(self) -> float | None:
        if self.sweep_s <= 0:
            return None
        return self.sweep_rad / (2 * np.pi) / self.sweep_s * 60

    def as_dict(self, counters: dict[str, int | bool]) -> dict:
        """The `lidar info --json` object; `counters` come from `LidarReader.counters()`."""
        full = self.scan_points[1:-1]
        dual_points = counters["batcher_duplicate_returns"]
        return {
            "data_packets": counters["data_packets"],
            "position_packets": counters["position_packets"],
            "malformed": counters["malformed"]
            + counters["batcher_malformed"]
            + counters["telemetry_malformed"],
            "foreign": counters["foreign"],
            "unsupported_model": counters["batcher_unsupported_model"],
            "lost": counters["batcher_lost"],
            "duplicates": counters["batcher_duplicates"],
            "out_of_order": counters["batcher_out_of_order"],
            "late": counters["batcher_late"],
            "time_jumps": counters["batcher_time_jumps"],
            "kernel_drops": counters["kernel_drops"],
            "truncated": counters["truncated"],
            "scans": len(self.scan_points),
            "full_scans": len(full),
            "complete_scans": self.complete_scans,
            "points_per_full_scan_median": float(np.median(full)) if full else None,
            "points_total": int(sum(self.scan_points)),
            "duplicate_returns": dual_points,
            "rings_present": sorted(self.rings_present),
            "return_mode": _single(self.return_modes),
            "model": _single(self.models),
            "rpm": None if self.rpm is None else round(self.rpm, 1),
            "duration_s": None
            if self.t_first is None
            else round((self.t_last - self.t_first) / 1e9, 6),
            "t_first_ns": self.t_first,
            "t_last_ns": self.t_last,
            "pps_status": dict(self.pps_status),
            "nmea_sentences": dict(self.nmea_sentences.most_common(5)),
        }


def _single(counter: Counter) -> str | None:
    """The one value seen, or 'a+b' when the stream changed mid-way."""
    if not counter:
        return None
    return "+".join(sorted(counter))
