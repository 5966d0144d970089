"""Raw sensor messages in, tree updates out: the wiring shared by `treetraits replay` and
the onboard service.

Messages arrive as they were received (and as a recording stores them): a topic of the
recording format, the bytes, `log_time` (host receive time) and `publish_time`. LiDAR
packets become scans, NMEA becomes fixes, Jackal MCU and retrofit encoder board bytes
become wheel samples, JPEGs wait in a short buffer. A scan is processed once the pose
history covers it (GNSS epochs arrive a little after the moment they describe), with the
camera frame nearest its middle.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers import recording as rec
from drivers.calibration import Calibration
from drivers.gnss.epochs import EpochAssembler
from drivers.gnss.sentences import decode
from drivers.gnss.stream import SentenceSplitter
from drivers.records import Fix, Frame, Pose, Scan, WheelSample
from drivers.velodyne.batcher import ScanBatcher
from firmware_bridge.jackal.session import JackalProtocol
from firmware_bridge.retrofit.reader import BridgeDecoder
from pipeline.localization import LocalizationConfig, Localizer
from pipeline.localization.utm import wrap_angle
from pipeline.projection import scan_mid_time

# A scan waits until the pose history reaches this far past its middle.
POSE_WAIT_NS = 300_000_000
# Before the first GNSS fix, scans wait this long for one; then the run maps in `odom`
# for good (trees are georeferenced at the end if a fix ever comes).
DATUM_WAIT_NS = 10_000_000_000  # 100 scans held at most (~85 MB of points)
FRAME_BUFFER = 30  # frames kept (3 s at 10 Hz)


@dataclass(frozen=True)
class ScanOutcome:
    scan: Scan
    pose: Pose | None
    frame: Frame | None
    result: Any  # what the mapper returned for this scan


@dataclass
class SurveyStats:
    scans: int = 0
    scans_without_pose: int = 0
    scans_skipped: int = 0  # could not be placed in the run's frame: not mapped (see _ready)
    frames: int = 0
    fixes: int = 0
    wheel_samples: int = 0
    unknown_topics: int = 0
    counters: dict[str, int] = field(default_factory=dict)


class SurveyProcessor:
    def __init__(self, mapper, calibration: Calibration, lidar_model: str = "auto"):
        self.mapper = mapper
        self.calibration = calibration
        self.localizer = Localizer(
            LocalizationConfig(T_base_gnss=calibration.T_base_gnss), calibration.wheels
        )
        self.stats = SurveyStats()
        self._batcher = ScanBatcher(model=lidar_model)
        self._splitter = SentenceSplitter()
        self._epochs = EpochAssembler()
        self._mcu = JackalProtocol()
        self._bridge = BridgeDecoder()
        self._frames: deque[Frame] = deque(maxlen=FRAME_BUFFER)
        self._pending: deque[Scan] = deque()
        self._latest = 0  # newest log_time seen
        # The mapper's world frame, chosen once: "utm" when a fix comes in time, else "odom".
        self.world_frame: str | None = None
        self._mapped_with_pose: bool | None = None  # set by the first scan mapped

    def feed(self, topic: str, data: bytes, log_time: int, publish_time: int) -> list[ScanOutcome]:
        """One received message; returns the scans it let through the pipeline."""
        self._latest = max(self._latest, log_time)
        if topic == rec.LIDAR_PACKETS:
            scan = self._batcher.push(data, log_time)
            if scan is not None:
                self._pending.append(scan)
        elif topic == rec.CAMERA_JPEG:
            self._frames.append(Frame(bytes(data), log_time, publish_time, self.stats.frames))
            self.stats.frames += 1
        elif topic == rec.GNSS_NMEA:
            for sentence in self._splitter.push(data, log_time):
                record = decode(sentence)
                if record is not None and (fix := self._epochs.push(record)) is not None:
                    self._add_fix(fix)
        elif topic == rec.WHEELS_JACKAL:
            for record in self._mcu.receive(data, log_time, log_time / 1e9):
                if isinstance(record, WheelSample):
                    self.stats.wheel_samples += 1
                    self.localizer.add_wheels(record)
            self._mcu.take_outgoing()  # a recording cannot answer the MCU
        elif topic == rec.WHEELS_BRIDGE:
            for record in self._bridge.push(data, log_time):
                if isinstance(record, WheelSample):  # ticks: the localizer converts them
                    self.stats.wheel_samples += 1
                    self.localizer.add_wheels(record)
        elif topic == rec.LIDAR_TELEMETRY:
            pass  # the VLP-16's own GPS input: not used for the pose
        else:
            self.stats.unknown_topics += 1
        return self._ready(self._latest - POSE_WAIT_NS)

    def finish(self) -> list[ScanOutcome]:
        """End of input: the last partial scan and GNSS epoch, then every waiting scan."""
        if (fix := self._epochs.flush()) is not None:
            self._add_fix(fix)
        if (scan := self._batcher.flush()) is not None:
            self._pending.append(scan)
        return self._ready(None)

    def _add_fix(self, fix: Fix) -> None:
        self.stats.fixes += 1
        self.localizer.add_fix(fix)

    def _choose_frame(self, end_of_input: bool) -> bool:
        if self.world_frame is None:
            if self.localizer.first_utm_time is not None:
                self.world_frame = "utm"
            elif end_of_input or (
                self._pending and self._latest - scan_mid_time(self._pending[0]) > DATUM_WAIT_NS
            ):
                self.world_frame = "odom"
        return self.world_frame is not None

    def _pose(self, t: int) -> Pose | None:
        if self.world_frame == "odom":
            return self.localizer.pose_at(t, "odom")
        pose = self.localizer.pose_at(t)
        if pose is not None:
            return pose
        # Seen before the first fix: carry the odometry pose into utm at the datum.
        odom = self.localizer.pose_at(t, "odom")
        transform = self.localizer.utm_from_odom(self.localizer.first_utm_time)
        if odom is None or transform is None:
            return None
        x, y, _ = transform @ np.array([odom.x, odom.y, 1.0])
        yaw = odom.yaw + math.atan2(transform[1, 0], transform[0, 0])
        return Pose(t, float(x), float(y), wrap_angle(yaw), odom.covariance, "utm")

    def _mappable(self, pose: Pose | None) -> bool:
        """The mapper holds its trees in one frame, fixed by the first scan it maps: a scan
        that cannot be placed in it is left out (e.g. in a live run, scans newer than the last
        pose at shutdown, or seen while the wheels and the receiver are both gone)."""
        posed = pose is not None
        if not posed and self.world_frame == "utm":
            return False
        if self._mapped_with_pose is None:
            self._mapped_with_pose = posed
        return posed == self._mapped_with_pose

    def _ready(self, horizon: int | None) -> list[ScanOutcome]:
        out = []
        if not self._choose_frame(end_of_input=horizon is None):
            return out
        while self._pending and (horizon is None or scan_mid_time(self._pending[0]) <= horizon):
            scan = self._pending.popleft()
            middle = scan_mid_time(scan)
            pose = self._pose(middle)
            if pose is None:
                self.stats.scans_without_pose += 1
            if not self._mappable(pose):
                self.stats.scans_skipped += 1
                continue
            frame = min(self._frames, key=lambda f: abs(f.t_capture - middle), default=None)
            result = self.mapper.process(scan, frame, pose)
            self.stats.scans += 1
            out.append(ScanOutcome(scan, pose, frame, result))
        return out
