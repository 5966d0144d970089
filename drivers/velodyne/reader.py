"""A LiDAR source and a scan batcher together: packets in, scans and telemetry out.

The `lidar` commands (info, export, listen) and `fuse` read LiDAR data through it. Replay
and the service do not: `SurveyProcessor` (service/survey.py) feeds packets from every
sensor's messages to its own `ScanBatcher`. Each piece stays usable alone.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne.batcher import ScanBatcher
from treetraits.drivers.velodyne.sources import LidarPacket, PacketSource
from treetraits.drivers.velodyne.telemetry import Telemetry, decode_telemetry
from treetraits.errors import ParseError


@dataclass
class ReaderStats:
    telemetry_malformed: int = 0


class LidarReader:
    """Iterates a packet source, yielding each completed `Scan` and each decoded
    `Telemetry`, in arrival order. Bad packets are counted (source, batcher and
    `self.stats`), never raised. At the end of a finite source the partial last scan
    is flushed."""

    def __init__(self, source: PacketSource, model: str = "auto", cut_angle_deg: float = 0.0):
        self.source = source
        self.batcher = ScanBatcher(model=model, cut_angle_deg=cut_angle_deg)
        self.stats = ReaderStats()

    def handle(self, packet: LidarPacket) -> Scan | Telemetry | None:
        """Feed one packet: the scan it completed, its decoded telemetry, or None."""
        if packet.is_data:
            return self.batcher.push(packet.payload, packet.t_host)
        try:
            return decode_telemetry(packet.payload, packet.t_host)
        except ParseError:
            self.stats.telemetry_malformed += 1
            return None

    def __iter__(self) -> Iterator[Scan | Telemetry]:
        for packet in self.source:
            item = self.handle(packet)
            if item is not None:
                yield item
        last = self.batcher.flush()
        if last is not None:
            yield last

    def counters(self) -> dict[str, int | bool]:
        """Every counter of the source, the batcher and the reader, in one flat dict."""
        merged: dict[str, int | bool] = {}
        merged.update(self.source.stats.as_dict())
        merged.update({f"batcher_{k}": v for k, v in self.batcher.stats.as_dict().items()})
        merged["telemetry_malformed"] = self.stats.telemetry_malformed
        return merged

    def close(self) -> None:
        self.source.close()
