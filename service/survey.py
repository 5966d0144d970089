"""Raw sensor messages in, tree updates out: the wiring shared by `treetraits replay` and
the onboard service.

Messages arrive as they were received (and as a recording stores them): a topic of the
recording format, the bytes, `log_time` (host receive time) and `publish_time`. LiDAR
packets become scans, NMEA becomes fixes, Jackal MCU and retrofit encoder board bytes
become wheel samples, JPEGs wait in a short buffer; the VLP-16's position packets, when
its GPS input is locked, put scans and GNSS epochs on the host clock by their UTC
(`lidar_clock`). Serial data is timed by the device's own clock, not by when the host read
it (`serial_clock`): wheel samples and IMU by the MCU's header stamp (the encoder board's
clock), GNSS epochs by their UTC, each put on the host clock by its least delay; a GNSS
fix waits until the wheels have passed the time it completed at, so the localizer gets
its inputs in time order even when the wheels' bytes came in a backlog. A scan is
processed, with the camera frame nearest its middle, as soon as what it gets can no
longer change:

- its pose: the localizer is causal (an input moves the poses from its arrival on, never
  before), so the pose at the scan's middle is final once the pose history holds two
  entries at or past the middle (`Localizer.settled_until`): with the wheels at 50 Hz,
  about 40 ms after the middle, before the scan's last packet is in;
- its frame: frames arrive in capture order, so once one captured at or after the middle
  is in, no nearer one can come; a camera silent for FRAME_SILENCE_NS is not waited for.

Whatever is missing, a scan waits no longer than POSE_WAIT_NS past its middle (by the
newest message seen): then it goes with what there is (no pose: left out or mapped
without, see `_mappable`). Every rule reads message times only, so a replay is
deterministic, and the scan gets the pose and frame it would get if it waited longer.

Live, a host too slow to map every scan sheds whole scans (`behind`, set by the
service): a scan that is ready while the newest message taken is older than the service's
limit goes unmapped and is counted (`scans_shed`). Everything else (packets, poses,
frames) is still taken in, so the loop catches up and nothing is dropped at random from a
full queue. A replay never sheds.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from treetraits import __version__
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import Calibration
from treetraits.drivers.gnss.epochs import NS_PER_DAY, EpochAssembler
from treetraits.drivers.gnss.sentences import decode
from treetraits.drivers.gnss.stream import SentenceSplitter
from treetraits.drivers.recording.motion import OdometryIntegrator, decode_imu
from treetraits.drivers.recording.points import decode_points
from treetraits.drivers.records import Fix, Frame, Scan, WheelSample
from treetraits.drivers.velodyne.batcher import ScanBatcher
from treetraits.drivers.velodyne.telemetry import decode_telemetry
from treetraits.errors import ParseError
from treetraits.firmware_bridge.jackal.records import JackalImu
from treetraits.firmware_bridge.jackal.session import JackalProtocol
from treetraits.firmware_bridge.retrofit.reader import BridgeDecoder
from treetraits.pipeline.deskew import deskew_scan
from treetraits.pipeline.localization import LocalizationConfig, Localizer
from treetraits.pipeline.localization.attitude import AttitudeFilter, rotation_zyx
from treetraits.pipeline.localization.lidar_clock import LidarUtcClock
from treetraits.pipeline.localization.localizer import WHEELS_GONE_NS
from treetraits.pipeline.localization.pose import Pose
from treetraits.pipeline.localization.serial_clock import SerialClock
from treetraits.pipeline.localization.utm import wrap_angle
from treetraits.pipeline.projection import scan_mid_time
from treetraits.service.detection_worker import DetectionWorker, detection_process

if TYPE_CHECKING:
    from treetraits.service.config import ServiceConfig

# The longest a scan waits past its middle (by the newest message) for a settled pose
# and its frame: the wheels or the receiver gone, a camera running late. Past the serial
# backlogs of a loaded host (the wheels' bytes 0.6-0.73 s late on a 2-core machine): a
# pose that is only late is waited for.
POSE_WAIT_NS = 1_000_000_000
# A camera that sent nothing for this long is not waited for (absent, unplugged).
FRAME_SILENCE_NS = 1_000_000_000
# Before the first GNSS fix, scans wait this long for one; then the run maps in `odom`
# for good (trees are georeferenced at the end if a fix ever comes).
DATUM_WAIT_NS = 10_000_000_000  # 100 scans held at most (~85 MB of points)
FRAME_BUFFER = 30  # frames kept (3 s at 10 Hz)
# An IMU silent for this long is not waited for (a Jackal recording without IMU, a link
# that dropped it); roll and pitch are then those of the last samples, or 0.
IMU_SILENCE_NS = 1_000_000_000


# A replay never sheds scans, so it does not count them.
LIVE_ONLY_FACTS = ("scans_shed",)
# Not among the service's run facts: adding them changes what a live store holds, a
# decision of its own rather than a side effect of building the facts in one place.
REPLAY_ONLY_FACTS = ("reanchored_at", "gnss_latency_ms", "lidar_clock")


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
    scans_without_heading: int = 0  # in utm before the heading is known: not mapped
    reanchored_at: int | None = None  # when the map moved from odom to utm (late fix)
    scans_skipped: int = 0  # could not be placed in the run's frame: not mapped (see _ready)
    scans_shed: int = 0  # ready while the live loop was behind its sensors: not mapped
    frames: int = 0
    fixes: int = 0
    wheel_samples: int = 0
    imu_samples: int = 0
    scans_deskewed: int = 0
    unknown_topics: int = 0
    telemetry_malformed: int = 0
    motion_malformed: int = 0  # format 1.1 odometry or IMU messages of the wrong size
    points_malformed: int = 0  # format 1.1 points messages that do not decode
    nmea_malformed: int = 0  # NMEA sentences whose fields do not read: skipped
    counters: dict[str, int] = field(default_factory=dict)


class SurveyProcessor:
    def __init__(
        self,
        mapper,
        calibration: Calibration,
        localization: LocalizationConfig | None = None,
        lidar_model: str = "auto",
        workers: int = 1,
        detect_in: str = "thread",
    ):
        self.mapper = mapper
        # `workers` 2: each scan detected on a second thread, or in a second process
        # (`detect_in`), while this one maps the scan before (`service.detection_worker`);
        # a mapper without `detect_scan` (RPH) maps each scan whole, as with 1.
        self._worker: DetectionWorker[tuple[Scan, Pose | None, Frame | None]] | None = None
        if workers > 1 and hasattr(mapper, "detect_scan"):
            if detect_in == "process":
                self._worker = detection_process(mapper)
            else:
                self._worker = DetectionWorker(mapper.detect_scan)
        self.calibration = calibration
        self.localizer = Localizer(localization, calibration.wheels, calibration.T_base_gnss)
        # Roll and pitch from the Jackal MCU's IMU (its frame taken as base_link).
        self.attitude = AttitudeFilter(self.localizer.config)
        self._imu_seen: int | None = None  # log_time of the newest IMU sample
        self.stats = SurveyStats()
        self._batcher = ScanBatcher(model=lidar_model)
        # A PPS-locked VLP-16 puts its scans and the GNSS epochs on the host clock by UTC.
        self.lidar_clock = LidarUtcClock()
        self._splitter = SentenceSplitter()
        self._epochs = EpochAssembler()
        self._mcu = JackalProtocol()
        self._bridge = BridgeDecoder()
        # Device clocks on the host clock (`serial_clock`): the MCU's header stamps (wheels
        # and IMU share them), the encoder board's clock, the GNSS epochs' UTC.
        self._mcu_clock = SerialClock.new()
        self._bridge_clock = SerialClock.new()
        self._gnss_clock = SerialClock.new()
        # GNSS fixes waiting for the wheels to pass the time each completed at (placed).
        self._held_fixes: deque[tuple[int, Fix]] = deque()
        self._wheels_read: int | None = None  # log_time of the newest wheel sample
        self._odometry = OdometryIntegrator(calibration.wheels.track)
        self._frames: deque[Frame] = deque(maxlen=FRAME_BUFFER)
        self._pending: deque[Scan] = deque()
        self._latest = 0  # newest log_time seen
        self._frame_seen = None  # log_time of the newest frame, for FRAME_SILENCE_NS
        # The mapper's world frame, chosen once: "utm" when a fix comes in time, else "odom".
        self.world_frame: str | None = None
        # (time, 3x3 utm_from_odom) when a run that began in odom moved to utm.
        self.anchor: tuple[int, np.ndarray] | None = None
        self._mapped_with_pose: bool | None = None  # set by the first scan mapped
        # Live only: given the newest log_time taken, whether the loop is too far behind
        # its sensors to map a scan now (the service's `max_backlog_s`).
        self.behind: Callable[[int], bool] | None = None

    def feed(self, topic: str, data: bytes, log_time: int, publish_time: int) -> list[ScanOutcome]:
        """One received message; returns the scans it let through the pipeline."""
        self._latest = max(self._latest, log_time)
        if topic == rec.LIDAR_PACKETS:
            scan = self._batcher.push(data, log_time)
            if scan is not None:
                self._add_scan(scan)
        elif topic == rec.LIDAR_POINTS:  # format 1.1: a decoded cloud, one scan
            try:
                self._add_scan(decode_points(data))
            except ParseError:
                self.stats.points_malformed += 1
        elif topic == rec.CAMERA_JPEG:
            self._frames.append(Frame(bytes(data), log_time, publish_time, self.stats.frames))
            self._frame_seen = log_time
            self.stats.frames += 1
        elif topic == rec.GNSS_NMEA:
            for sentence in self._splitter.push(data, log_time):
                try:
                    record = decode(sentence)
                except ParseError:  # a good checksum over fields that do not read
                    self.stats.nmea_malformed += 1
                    continue
                if record is not None and (fix := self._epochs.push(record)) is not None:
                    self._hold_fix(fix, getattr(record, "tod_ns", None))
        elif topic == rec.WHEELS_JACKAL:
            for record in self._mcu.receive(data, log_time, log_time / 1e9):
                if isinstance(record, WheelSample):
                    self._add_wheels(record, self._mcu_clock, log_time)
                elif isinstance(record, JackalImu):
                    # The MCU's clock, like the wheels': placed by the same offset.
                    t = self._mcu_clock.place(record.t_host, record.stamp_ns)
                    self._add_imu(t, record.angular_velocity, record.linear_acceleration)
            self._mcu.take_outgoing()  # a recording cannot answer the MCU
        elif topic == rec.WHEELS_BRIDGE:
            for record in self._bridge.push(data, log_time):
                if isinstance(record, WheelSample):  # ticks: the localizer converts them
                    self._add_wheels(record, self._bridge_clock, log_time)
        elif topic == rec.WHEELS_ODOMETRY:  # format 1.1: a robot's odometry as numbers
            try:
                self._add_wheels(self._odometry.push(data, log_time), None, log_time)
            except ParseError:
                self.stats.motion_malformed += 1
        elif topic == rec.IMU_DATA:  # format 1.1: an IMU as numbers, on t_host like the MCU's
            try:
                sample = decode_imu(data, log_time)
            except ParseError:
                self.stats.motion_malformed += 1
            else:
                self._add_imu(sample.t_host, sample.angular_velocity, sample.linear_acceleration)
        elif topic == rec.LIDAR_TELEMETRY:
            try:
                self.lidar_clock.add_telemetry(decode_telemetry(data, log_time))
            except ParseError:
                self.stats.telemetry_malformed += 1
            self.localizer.host_minus_utc = self.lidar_clock.host_minus_utc(log_time)
        else:
            self.stats.unknown_topics += 1
        self._release_fixes(end_of_input=False)
        return self._ready(end_of_input=False)

    def finish(self) -> list[ScanOutcome]:
        """End of input: the last partial scan and GNSS epoch, then every waiting scan."""
        if (fix := self._epochs.flush()) is not None:
            self._hold_fix(fix, None)
        self._release_fixes(end_of_input=True)
        if (scan := self._batcher.flush()) is not None:
            self._add_scan(scan)
        out = self._ready(end_of_input=True)
        if self._worker is not None:
            self._worker.close()
            self._worker = None
        return out

    def facts(self, *, live: bool) -> dict[str, Any]:
        """What the processing came to, for the run's facts (the store's `run` table, and
        replay's summary): the world frame and UTM zone, the scans left unmapped and why,
        the fixes and frames taken. `live`: the service's run (`scans_shed`), else a
        replay's (`reanchored_at`, `gnss_latency_ms`, `lidar_clock`)."""
        facts = {
            "world_frame": self.world_frame,
            "reanchored_at": self.stats.reanchored_at,
            "utm_zone": self.localizer.grid.name if self.localizer.grid else None,
            "scans_without_pose": self.stats.scans_without_pose,
            "scans_without_heading": self.stats.scans_without_heading,
            # Ready while the loop was more than service.max_backlog_s behind: not mapped.
            "scans_shed": self.stats.scans_shed,
            "fixes": self.stats.fixes,
            "gnss_latency_ms": self.localizer.stats.latency_ms,
            "lidar_clock": {
                "scans_on_utc": self.lidar_clock.stats.scans_on_utc,
                "host_minus_utc_ms": self.lidar_clock.stats.host_minus_utc_ms,
            },
            "frames": self.stats.frames,
        }
        for key in REPLAY_ONLY_FACTS if live else LIVE_ONLY_FACTS:
            del facts[key]
        return facts

    def _add_scan(self, scan: Scan) -> None:
        scan = self.lidar_clock.place(scan)
        self.localizer.host_minus_utc = self.lidar_clock.host_minus_utc(scan.t_host)
        self._pending.append(scan)

    def _add_imu(self, t_host: int, gyro, accel) -> None:
        self.stats.imu_samples += 1
        self._imu_seen = t_host
        self.attitude.add_imu(t_host, gyro, accel)
        if (rate := self.attitude.yaw_rate) is not None:
            self.localizer.add_yaw_rate(t_host, rate)

    def _add_wheels(self, sample: WheelSample, clock: SerialClock | None, log_time: int) -> None:
        """A wheel sample, moved to its device time on the host clock when `clock` is given
        and the sample has one; held fixes it passes go to the localizer first."""
        if clock is not None and sample.t_device_us is not None:
            sample = replace(sample, t_host=clock.place(sample.t_host, sample.t_device_us * 1000))
        while self._held_fixes and self._held_fixes[0][0] <= sample.t_host:
            self._add_fix(self._held_fixes.popleft()[1])
        self._wheels_read = log_time
        self.stats.wheel_samples += 1
        self.localizer.add_wheels(sample)
        # The wheels' speed lets the attitude filter take the robot's own acceleration
        # out of the accelerometer, and tells it when the robot stands still.
        if (speed := self.localizer.speed) is not None:
            self.attitude.add_speed(sample.t_host, speed)

    def _hold_fix(self, fix: Fix, closing_tod_ns: int | None) -> None:
        """A GNSS epoch, on the host clock by its UTC: its `t_host` becomes UTC plus the
        least arrival delay (an unloaded arrival of its first sentence). It waits until the
        wheels pass the time it was completed at (the next epoch's first sentence: its time
        of day tells when), as on an unloaded host, where the fix comes in after them."""
        if fix.utc_ns is None:
            self._held_fixes.append((fix.t_host, fix))
            return
        placed = self._gnss_clock.place(fix.t_host, fix.utc_ns)
        completed = placed
        if closing_tod_ns is not None:
            completed += (closing_tod_ns - fix.utc_ns) % NS_PER_DAY
        self._held_fixes.append((completed, replace(fix, t_host=placed)))

    def _release_fixes(self, end_of_input: bool) -> None:
        """Held fixes go in when the wheels cannot pass them: none yet, silent for
        WHEELS_GONE_NS (by read time), or the end of input."""
        wheels_silent = (
            self._wheels_read is None or self._latest - self._wheels_read > WHEELS_GONE_NS
        )
        while self._held_fixes and (end_of_input or wheels_silent):
            self._add_fix(self._held_fixes.popleft()[1])

    def _add_fix(self, fix: Fix) -> None:
        self.stats.fixes += 1
        self.localizer.add_fix(fix)

    def utm_from_odom(self, t: int) -> np.ndarray | None:
        """The 3x3 transform from `odom` to `utm` for what was at `t` in `odom`: the one the
        map was re-anchored with, for anything before then (the map moved with it as one
        piece); else the localiser's at `t`."""
        if self.anchor is not None and t <= self.anchor[0]:
            return self.anchor[1]
        return self.localizer.utm_from_odom(t)

    def _reanchor(self) -> list[ScanOutcome]:
        """A run mapping in `odom` (no fix when it started) moves its whole map to `utm`
        once the localiser has a datum and knows its heading: trees already mapped move
        with it, and later scans (the robot back along the same trees) land on them.
        Returns the scans mapped first: those the detection worker held, posed in odom."""
        if self.world_frame != "odom" or self.localizer.first_utm_time is None:
            return []
        now = self.localizer.pose()
        if now is None or now.frame != "utm" or not self._heading_known(now):
            return []
        transform = self.localizer.utm_from_odom()
        if transform is None:
            return []
        mapped = self._map_detected(wait=True)
        new_from_old = np.eye(4)
        new_from_old[:2, :2] = transform[:2, :2]
        new_from_old[:2, 3] = transform[:2, 2]
        if self.mapper.frame == "odom":
            self.mapper.reanchor(new_from_old, "utm")
        self.anchor = (now.t, transform)
        self.world_frame = "utm"
        self.stats.reanchored_at = now.t
        return mapped

    def _choose_frame(self, end_of_input: bool) -> bool:
        if self.world_frame is None:
            if self.localizer.first_utm_time is not None:
                self.world_frame = "utm"
            elif end_of_input or (
                self._pending and self._latest - scan_mid_time(self._pending[0]) > DATUM_WAIT_NS
            ):
                self.world_frame = "odom"
        return self.world_frame is not None

    def pose_at(self, t: int) -> Pose | None:
        """The pose in the run's world frame at `t`, as a scan with its middle at `t` gets
        it (before the first fix, the odometry pose carried into utm at the datum), with
        roll and pitch from the IMU (0 without one)."""
        return self._with_attitude(self._planar_pose_at(t))

    def _planar_pose_at(self, t: int) -> Pose | None:
        if self.world_frame == "odom":
            return self.localizer.pose_at(t, "odom")
        pose = self.localizer.pose_at(t)
        if pose is not None:
            return pose
        # Seen before the first fix: carry the odometry pose into utm at the datum, as
        # uncertain as the datum (a heading still unknown there is unknown here too:
        # whether a scan falls just before or just after the first fix must not decide it).
        odom = self.localizer.pose_at(t, "odom")
        first = self.localizer.first_utm_time
        transform = self.localizer.utm_from_odom(first)
        datum = self.localizer.pose_at(first) if first is not None else None
        if odom is None or transform is None or datum is None:
            return None
        x, y, _ = transform @ np.array([odom.x, odom.y, 1.0])
        yaw = odom.yaw + math.atan2(transform[1, 0], transform[0, 0])
        return Pose(t, float(x), float(y), wrap_angle(yaw), datum.covariance, "utm")

    def _with_attitude(self, pose: Pose | None) -> Pose | None:
        if pose is None:
            return None
        attitude = self.attitude.attitude_at(pose.t)
        if attitude is None:
            return pose  # no IMU (or none yet at that time): level, roll = pitch = 0
        return replace(pose, roll=attitude[0], pitch=attitude[1])

    def _deskewed(self, scan: Scan, middle: int) -> Scan:
        """The scan de-skewed to its middle with the poses across its sweep (`odom` while
        wheels come in: smooth, where a `utm` pose jumps at each fix; else the run's world
        frame), as it is when there are none or deskew is off."""
        if not self.localizer.config.deskew or len(scan.points) == 0:
            return scan
        step = round(self.localizer.config.deskew_step_s * 1e9)
        start = scan.t_host - (scan.t_end - scan.t_start)
        times = [*range(start, scan.t_host, step), scan.t_host]
        odom = self.stats.wheel_samples > 0
        kept_times, poses = [], []
        for t in times:
            pose = self.localizer.pose_at(t, "odom") if odom else self._planar_pose_at(t)
            if pose is None:
                continue
            pose = self._with_attitude(pose)
            matrix = np.eye(4)
            matrix[:3, :3] = rotation_zyx(pose.roll, pose.pitch, pose.yaw)
            matrix[:3, 3] = (pose.x, pose.y, pose.z)
            kept_times.append(t)
            poses.append(matrix)
        if len(poses) < 2:
            return scan
        self.stats.scans_deskewed += 1
        return deskew_scan(
            scan, np.array(kept_times), np.array(poses), middle, self.calibration.T_base_lidar
        )

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

    def _heading_known(self, pose: Pose) -> bool:
        limit = self.localizer.config.known_yaw_sigma_rad
        return float(pose.covariance[2, 2]) <= limit * limit

    def _settled(self, scan: Scan) -> bool:
        """The scan gets the pose (and, de-skewed, the poses across its sweep), attitude
        and frame it would get later (or has waited POSE_WAIT_NS past its middle)."""
        middle = scan_mid_time(scan)
        if self._latest - middle >= POSE_WAIT_NS:
            return True
        # De-skew needs the poses up to the scan's last firing, not only its middle.
        until = scan.t_host if self.localizer.config.deskew else middle
        settled = self.localizer.settled_until("odom")
        if settled is None or settled < until:
            return False
        if self.world_frame == "utm":
            settled = self.localizer.settled_until("utm")
            if settled is None or settled < until:
                return False
        if self._imu_seen is not None and self._latest - self._imu_seen <= IMU_SILENCE_NS:
            settled = self.attitude.settled_until()
            if settled is None or settled < until:
                return False
        if self._frame_seen is None or self._latest - self._frame_seen > FRAME_SILENCE_NS:
            return True  # no camera to wait for
        return self._frames[-1].t_capture >= middle

    def _ready(self, end_of_input: bool) -> list[ScanOutcome]:
        out: list[ScanOutcome] = []
        if not self._choose_frame(end_of_input):
            return out
        out.extend(self._reanchor())
        while self._pending and (end_of_input or self._settled(self._pending[0])):
            scan = self._pending.popleft()
            if self.behind is not None and self.behind(self._latest):
                self.stats.scans_shed += 1
                continue
            middle = scan_mid_time(scan)
            pose = self.pose_at(middle)
            if pose is None:
                self.stats.scans_without_pose += 1
            elif pose.frame == "utm" and not self._heading_known(pose):
                # Mapped with a heading that is still a guess, a scan's trees would land
                # anywhere on a circle round the robot (and stay in the accumulated clouds).
                self.stats.scans_without_heading += 1
                pose = None
            if not self._mappable(pose):
                self.stats.scans_skipped += 1
                continue
            frame = min(self._frames, key=lambda f: abs(f.t_capture - middle), default=None)
            if pose is not None:
                scan = self._deskewed(scan, middle)
            if self._worker is None:
                out.append(self._mapped(scan, pose, frame, self.mapper.process(scan, frame, pose)))
                continue
            if self._worker.full:  # the oldest mapped first: memory stays bounded
                out.extend(self._map_detected(at_least=1))
            self._worker.submit(scan, frame, (scan, pose, frame))
        out.extend(self._map_detected(wait=end_of_input))
        return out

    def _map_detected(self, wait: bool = False, at_least: int = 0) -> list[ScanOutcome]:
        """The worker's detected scans mapped in their order (`DetectionWorker.done`)."""
        out = []
        if self._worker is None:
            return out
        for detected, (scan, pose, frame) in self._worker.done(wait, at_least):
            out.append(self._mapped(scan, pose, frame, self.mapper.map_detected(detected, pose)))
        return out

    def _mapped(self, scan: Scan, pose: Pose | None, frame: Frame | None, result) -> ScanOutcome:
        """A scan the mapper has mapped, counted."""
        self.stats.scans += 1
        return ScanOutcome(scan, pose, frame, result)


def start_facts(config: ServiceConfig, calibration: Calibration, source: str) -> dict[str, Any]:
    """The facts a run begins with, replay and live alike: what made it, from what input
    (`source`: the recording's path, or "live"), with which methods and calibration."""
    return {
        "software": f"treetraits {__version__}",
        "input": source,
        "method": config.pipeline.method,
        "traits": config.traits.method,
        "calibration": calibration.to_json(),
        # What took the format's default (no camera: no NDVI), said, never silent.
        "calibration_defaults": list(calibration.defaults),
    }


def make_mapper(config: ServiceConfig, calibration: Calibration):
    """The mapper of `pipeline.method`, with the config's settings."""
    method = config.pipeline.method
    if method.startswith("rph"):
        from treetraits.pipeline.rph import RphMapper, rph_config

        preset = "vlp16" if method == "rph-vlp16" else "shipped"
        return RphMapper(rph_config(preset), calibration=calibration)
    from treetraits.pipeline.mapper import TreeMapper

    return TreeMapper(config.mapper(), calibration)


def make_processor(
    config: ServiceConfig, calibration: Calibration, lidar_model: str = "auto", live: bool = False
):
    """The processing core shared by replay and the live service (`live`: the service,
    whose `[pipeline] workers = 0` means the detection worker, on a thread with
    `detect_in = "auto"`; offline, a process: see docs/performance.md)."""
    workers = config.pipeline.workers or (2 if live else 1)
    detect_in = config.pipeline.detect_in
    if detect_in == "auto":
        detect_in = "thread" if live else "process"
    mapper = make_mapper(config, calibration)
    return SurveyProcessor(
        mapper, calibration, config.localization, lidar_model, workers, detect_in
    )
