"""ROS 1 and ROS 2 bags to a recording v1 (`treetraits import`), without ROS.

Each selected topic becomes the bytes a treetraits sensor driver would have received, on
the recording's channels (docs/import.md):

- `velodyne_msgs/VelodyneScan`: each packet's 1206-byte payload on `/lidar/packets`,
  `log_time` = the packet's own `stamp` (the ROS driver's receive time);
- `nmea_msgs/Sentence`: the sentence + CRLF on `/gnss/nmea`;
- `sensor_msgs/NavSatFix`: GGA, RMC and GST sentences made from the numbers
  (`drivers/gnss/compose.py`), at the header stamp as UTC;
- `sensor_msgs/Image` (rgb8, bgr8, mono8) JPEG-encoded, `sensor_msgs/CompressedImage`
  (JPEG as is, others re-encoded) on `/camera/jpeg`;
- `sensor_msgs/PointCloud2`: the scan's points on `/lidar/points` (format 1.1,
  `drivers/recording/points.py`, `drivers/rosbag/pointcloud2.py`);
- `nav_msgs/Odometry` (its twist) on `/wheels/odometry` and `sensor_msgs/Imu` (rates and
  accelerations) on `/imu/data`: format 1.1 (`drivers/recording/motion.py`), so a recording holding
  them is marked 1.1.

Other messages keep the bag's receive time as `log_time`; `publish_time` follows the
format's rules (LiDAR: the packet's ToH; GNSS: the epoch's UTC; camera: the header stamp).
The recording is written in `log_time` order, as the live recorder writes it. Several bags
(a data set split by modality, ROS 1 and ROS 2 mixed) are merged by time.
"""

from __future__ import annotations

import contextlib
import heapq
import math
import os
import struct
from collections import defaultdict, deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from treetraits.drivers import recording as rec
from treetraits.drivers.gnss.compose import fix_sentences
from treetraits.drivers.gnss.times import NmeaClock
from treetraits.drivers.recording.motion import encode_imu, encode_odometry
from treetraits.drivers.recording.points import encode_points
from treetraits.drivers.rosbag.frames import BASE_FRAME, StaticFrames, quaternion_matrix, rotate
from treetraits.drivers.rosbag.topics import (
    KIND_TYPES,
    NOT_IMPORTED_YET,
    V11_KINDS,
)
from treetraits.drivers.velodyne.models import DATA_PACKET_SIZE
from treetraits.drivers.velodyne.packet import resolve_hour
from treetraits.errors import ConfigError, SourceError
from treetraits.files import check_output_file

# A NavSatFix with STATUS_GBAS_FIX (ground-based augmentation: RTK) is RTK fixed when its
# horizontal sigma is at most this, else RTK float (NavSatFix cannot say which).
RTK_FIXED_MAX_SIGMA_M = 0.05
# NavSatStatus.status -> GGA quality (GBAS: see above; -1 NO_FIX is quality 0).
_STATUS_QUALITY = {0: 1, 1: 2}
_GBAS_FIX = 2
_COVARIANCE_UNKNOWN = 0

# NavSatFix course made good (`CourseMadeGood`): over about this long, from this far.
COURSE_WINDOW_NS = 1_000_000_000
COURSE_MIN_BASELINE_M = 0.2
EARTH_RADIUS_M = 6_371_000.0

# The recording is written in log_time order: a message is held until the bag's clock is
# this far past it. A VelodyneScan holds 0.1 s of packets stamped before its receive time.
REORDER_WINDOW_NS = 2_000_000_000
JPEG_QUALITY = 90
TF_STATIC = "/tf_static"

# Message definitions that the default type stores lack (ROS 2 bags before rosbag2 v8
# carry none). From ros-drivers/velodyne and ros-drivers/nmea_msgs (BSD).
_EXTRA_TYPES = {
    "velodyne_msgs/msg/VelodynePacket": "builtin_interfaces/Time stamp\nuint8[1206] data\n",
    "velodyne_msgs/msg/VelodyneScan": (
        "std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets\n"
    ),
    "nmea_msgs/msg/Sentence": "std_msgs/Header header\nstring sentence\n",
}


@dataclass
class TopicReport:
    """One topic of the bags (or of `--topics` that the bags lack)."""

    topic: str
    msgtype: str | None  # None: asked for, not in the bags
    messages: int  # in the bags
    kind: str | None = None
    status: str = "not selected"  # imported, not imported yet, unknown type, missing, ...
    written: int = 0  # recording messages made from it
    skipped: int = 0  # messages that could not be converted
    skip_reasons: dict[str, int] = field(default_factory=dict)

    def skip(self, reason: str) -> None:
        self.skipped += 1
        self.skip_reasons[reason] = self.skip_reasons.get(reason, 0) + 1


@dataclass
class ImportReport:
    """What `import_bags` read and wrote."""

    bags: list[str]
    output: str
    topics: list[TopicReport]
    channels: dict[str, int] = field(default_factory=dict)  # recording topic -> messages
    first_log_time: int | None = None
    last_log_time: int | None = None
    out_of_order: int = 0  # written after a later log_time (beyond REORDER_WINDOW_NS)
    format_version: str = rec.FORMAT_VERSION  # 1.1 with points, odometry or IMU imported
    imu_frames: dict[str, str] = field(default_factory=dict)  # IMU frame -> its rotation's source

    def as_dict(self) -> dict[str, Any]:
        return {
            "bags": self.bags,
            "output": self.output,
            "channels": self.channels,
            "first_log_time": self.first_log_time,
            "last_log_time": self.last_log_time,
            "out_of_order": self.out_of_order,
            "format_version": self.format_version,
            "imu_frames": self.imu_frames,
            "topics": [vars(t) for t in self.topics],
            "imported": [t.topic for t in self.topics if t.status == "imported"],
            "not_imported_yet": [t.topic for t in self.topics if t.status == "not imported yet"],
            "missing": [t.topic for t in self.topics if t.status == "missing"],
        }


@dataclass(frozen=True)
class ImportOptions:
    # kind -> topic; None: every topic of a known type (the first of each kind).
    topics: Mapping[str, str] | None = None
    # GGA quality for every NavSatFix with a fix; None: from its status and covariance.
    gnss_quality: int | None = None
    calibration: Mapping[str, Any] | None = None
    jpeg_quality: int = JPEG_QUALITY
    force: bool = False  # replace an existing output


@dataclass(frozen=True, slots=True)
class _Out:
    """One recording message made from a bag message."""

    topic: str
    data: bytes
    log_time: int
    publish_time: int


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def velodyne_scan(msg: Any, report: TopicReport) -> list[_Out]:
    """A VelodyneScan's packets, byte for byte, each at its own stamp; publish_time is the
    packet's ToH on the hour of its stamp (`lidar_publish_time`, one NumPy call a scan)."""
    payloads, stamps = [], []
    for packet in msg.packets:
        data = np.asarray(packet.data, dtype=np.uint8).tobytes()
        if len(data) != DATA_PACKET_SIZE:
            report.skip(f"packet of {len(data)} bytes")
            continue
        payloads.append(data)
        stamps.append(_stamp_ns(packet.stamp))
    if not payloads:
        return []
    toh_us = [int.from_bytes(data[1200:1204], "little") for data in payloads]
    published = resolve_hour(np.array(toh_us), np.array(stamps, dtype=np.int64)).tolist()
    return [
        _Out(rec.LIDAR_PACKETS, data, t, p)
        for data, t, p in zip(payloads, stamps, published, strict=True)
    ]


def nmea_sentence(msg: Any, log_time: int, clock: NmeaClock, report: TopicReport) -> list[_Out]:
    """An nmea_msgs/Sentence as the receiver sent it: the text and CRLF (the ROS driver
    strips the line end)."""
    text = msg.sentence.rstrip("\r\n")
    try:
        data = text.encode("ascii") + b"\r\n"
    except UnicodeEncodeError:
        report.skip("not ASCII")
        return []
    return [_Out(rec.GNSS_NMEA, data, log_time, clock.stamp(data, log_time))]


def navsatfix_quality(msg: Any, forced: int | None) -> int:
    """GGA quality of a NavSatFix (docs/import.md): NO_FIX 0; `forced` for any fix when
    given; else FIX 1, SBAS 2, GBAS 4 (RTK fixed) when the horizontal sigma is at most
    RTK_FIXED_MAX_SIGMA_M, else 5 (RTK float, also when the covariance is unknown)."""
    status = int(msg.status.status)
    if status < 0:
        return 0
    if forced is not None:
        return forced
    if status != _GBAS_FIX:
        return _STATUS_QUALITY.get(status, 1)
    sigma = _horizontal_sigma(msg)
    return 4 if sigma is not None and sigma <= RTK_FIXED_MAX_SIGMA_M else 5


def _sigmas(msg: Any) -> tuple[float, float, float] | None:
    """(east, north, up) 1-sigma from the ENU covariance's diagonal, None when unknown."""
    if int(msg.position_covariance_type) == _COVARIANCE_UNKNOWN:
        return None
    diagonal = [float(msg.position_covariance[i]) for i in (0, 4, 8)]
    if not all(math.isfinite(v) and v >= 0 for v in diagonal):
        return None
    east, north, up = (math.sqrt(v) for v in diagonal)
    return east, north, up


def _horizontal_sigma(msg: Any) -> float | None:
    sigmas = _sigmas(msg)
    return None if sigmas is None else max(sigmas[0], sigmas[1])


class CourseMadeGood:
    """Course and speed over ground from a NavSatFix stream's own positions (NavSatFix has
    no velocity, and the localiser learns its UTM heading from RMC's course): the
    displacement from the fix about COURSE_WINDOW_S before, as a receiver's course made
    good. Speed once the window spans half of it; course also needs COURSE_MIN_BASELINE_M
    of travel (RTK noise of 1-2 cm over 0.5 m is about 2 deg)."""

    def __init__(self) -> None:
        self._history: deque[tuple[int, float, float]] = deque()  # (utc ns, lat, lon)

    def push(self, utc: int, lat: float, lon: float) -> tuple[float | None, float | None]:
        if not (math.isfinite(lat) and math.isfinite(lon)):
            return None, None
        history = self._history
        while history and (history[0][0] >= utc or utc - history[0][0] > COURSE_WINDOW_NS):
            history.popleft()  # too old, or time went back (a new bag, a clock jump)
        history.append((utc, lat, lon))
        t0, lat0, lon0 = history[0]
        dt = (utc - t0) / 1e9
        if dt < COURSE_WINDOW_NS / 2e9:
            return None, None
        north = math.radians(lat - lat0) * EARTH_RADIUS_M
        east = math.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat))
        distance = math.hypot(east, north)
        course = math.degrees(math.atan2(east, north)) % 360.0
        return (course if distance >= COURSE_MIN_BASELINE_M else None), distance / dt


def navsatfix(
    msg: Any, log_time: int, forced_quality: int | None, course: CourseMadeGood
) -> list[_Out]:
    """A NavSatFix as the sentences of one epoch at its header stamp (as UTC). NavSatFix
    altitude is above the ellipsoid: GGA gets it with a geoid separation of 0, so that
    altitude + separation is the same ellipsoidal height. RMC carries the course and speed
    made good over the last second (`CourseMadeGood`)."""
    utc = _stamp_ns(msg.header.stamp)
    quality = navsatfix_quality(msg, forced_quality)
    course_deg, speed = (
        course.push(utc, float(msg.latitude), float(msg.longitude)) if quality else (None, None)
    )
    sigmas = _sigmas(msg) or (None, None, None)
    sentences = fix_sentences(
        utc,
        float(msg.latitude),
        float(msg.longitude),
        float(msg.altitude),
        quality,
        std_east_m=sigmas[0],
        std_north_m=sigmas[1],
        std_up_m=sigmas[2],
        course_deg=course_deg,
        speed_mps=speed,
    )
    # publish_time: the epoch's UTC, as the sentences carry it (rounded to the ms).
    utc = round(utc / 1e6) * 1_000_000
    return [_Out(rec.GNSS_NMEA, s, log_time, utc) for s in sentences]


def image(msg: Any, log_time: int, jpeg_quality: int, report: TopicReport) -> list[_Out]:
    """A sensor_msgs/Image (rgb8, bgr8, mono8) as a JPEG; publish_time = header stamp."""
    import cv2

    encoding = str(msg.encoding).lower()
    channels = {"rgb8": 3, "bgr8": 3, "mono8": 1}.get(encoding)
    if channels is None:
        report.skip(f"encoding {msg.encoding}")
        return []
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    raw = np.asarray(msg.data, dtype=np.uint8)
    if step < width * channels or raw.size < height * step:
        report.skip("data shorter than height x step")
        return []
    pixels = raw[: height * step].reshape(height, step)[:, : width * channels]
    pixels = pixels.reshape(height, width, channels)
    if encoding == "rgb8":  # cv2 writes BGR: keep each band where the camera put it
        pixels = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR)
    ok, jpeg = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    if not ok:
        report.skip("JPEG encoding failed")
        return []
    return [_Out(rec.CAMERA_JPEG, jpeg.tobytes(), log_time, _stamp_ns(msg.header.stamp))]


def compressed_image(msg: Any, log_time: int, jpeg_quality: int, report: TopicReport) -> list:
    """A CompressedImage: JPEG bytes as they are, another format decoded and re-encoded."""
    import cv2

    data = np.asarray(msg.data, dtype=np.uint8).tobytes()
    if not data.startswith(b"\xff\xd8"):
        pixels = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if pixels is None:
            report.skip(f"undecodable {msg.format or 'image'}")
            return []
        ok, jpeg = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        if not ok:
            report.skip("JPEG encoding failed")
            return []
        data = jpeg.tobytes()
    return [_Out(rec.CAMERA_JPEG, data, log_time, _stamp_ns(msg.header.stamp))]


def point_cloud(msg: Any, log_time: int, report: TopicReport) -> list[_Out]:
    """A PointCloud2 as one `/lidar/points` message (`drivers/recording/points.py`); publish_time =
    header stamp. Points without finite x, y, z are dropped and counted."""
    from treetraits.drivers.rosbag.pointcloud2 import CloudError, cloud_points

    stamp = _stamp_ns(msg.header.stamp)
    try:
        cloud = cloud_points(msg, stamp)
    except CloudError as error:
        report.skip(str(error))
        return []
    if cloud.dropped:
        reason = "points without finite x, y, z (dropped)"
        report.skip_reasons[reason] = report.skip_reasons.get(reason, 0) + cloud.dropped
    data = encode_points(cloud.header, cloud.points)
    return [_Out(rec.LIDAR_POINTS, data, log_time, stamp)]


def odometry(msg: Any, log_time: int) -> list[_Out]:
    """A nav_msgs/Odometry's twist (in its child frame, base_link): forward speed and yaw
    rate; publish_time = header stamp."""
    twist = msg.twist.twist
    data = encode_odometry(float(twist.linear.x), float(twist.angular.z))
    return [_Out(rec.WHEELS_ODOMETRY, data, log_time, _stamp_ns(msg.header.stamp))]


def imu(msg: Any, log_time: int, mounting: ImuMounting) -> list[_Out]:
    """A sensor_msgs/Imu's angular velocity and linear acceleration turned into base_link
    (`ImuMounting`; its orientation is not kept: the attitude filter makes its own);
    publish_time = header stamp."""
    w, a = msg.angular_velocity, msg.linear_acceleration
    R = mounting.rotation(str(msg.header.frame_id))
    data = encode_imu(rotate(R, (w.x, w.y, w.z)), rotate(R, (a.x, a.y, a.z)))
    return [_Out(rec.IMU_DATA, data, log_time, _stamp_ns(msg.header.stamp))]


class ImuMounting:
    """R_base_imu per IMU frame: the calibration's `T_base_imu`, else the bag's static
    transforms, else identity (`drivers/rosbag/frames.py`). `sources` says, per frame,
    where its rotation came from (the import summary shows it)."""

    def __init__(self, calibration: Mapping[str, Any] | None, frames: StaticFrames):
        self._given = None
        if calibration and "T_base_imu" in calibration:
            self._given = np.asarray(calibration["T_base_imu"], dtype=float).reshape(4, 4)[:3, :3]
        self._frames = frames
        self._cache: dict[str, np.ndarray] = {}
        self.sources: dict[str, str] = {}

    def rotation(self, frame: str) -> np.ndarray:
        if (R := self._cache.get(frame)) is not None:
            return R
        if self._given is not None:
            R, source = self._given, "calibration T_base_imu"
        elif (found := self._frames.rotation(BASE_FRAME, frame)) is not None:
            R, path = found
            source = "same frame" if len(path) == 1 else "/tf_static " + " -> ".join(path)
        else:
            R, source = np.eye(3), f"none: no transform to {BASE_FRAME}, taken as {BASE_FRAME}"
        self._cache[frame] = R
        self.sources[frame or "(empty frame_id)"] = source
        return R


def static_frames(readers: list[Any], reports: Mapping[str, TopicReport]) -> StaticFrames:
    """Every transform of the bags' `/tf_static` topics (marked as read in the summary)."""
    frames = StaticFrames()
    for reader in readers:
        chosen = [
            c
            for c in reader.connections
            if c.topic == TF_STATIC and c.msgtype == "tf2_msgs/msg/TFMessage"
        ]
        if not chosen:
            continue
        reports[TF_STATIC].status = "read: static transforms (IMU mounting)"
        for connection, _, raw in reader.messages(connections=chosen):
            for t in reader.deserialize(raw, connection.msgtype).transforms:
                q = t.transform.rotation
                R = quaternion_matrix(q.x, q.y, q.z, q.w)
                frames.add(str(t.header.frame_id), str(t.child_frame_id), R)
    return frames


def default_typestore() -> Any:
    """The type store for bags that carry no message definitions: ROS 2 Humble's types
    plus velodyne_msgs and nmea_msgs."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in _EXTRA_TYPES.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def _bag_errors() -> tuple[type[BaseException], ...]:
    """What rosbags and its storage back ends raise on a damaged or foreign file."""
    import apsw
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    return (
        AnyReaderError,
        Reader1Error,
        Reader2Error,
        SerdeError,
        TypesysError,
        apsw.Error,
        OSError,
        ValueError,
        KeyError,
        IndexError,
        AssertionError,
        struct.error,
        EOFError,
    )


def _open_bag(path: Path, store: Any, errors: tuple) -> Any:
    from rosbags.highlevel import AnyReader

    if not path.exists():
        raise SourceError(f"{path}: no such bag (a ROS 1 .bag file or a ROS 2 bag directory)")
    try:
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except errors as error:
        raise SourceError(f"{path}: not a readable ROS bag ({_reason(error)})") from None
    return reader


def _reason(error: BaseException) -> str:
    text = " ".join(str(a) for a in error.args) or type(error).__name__
    return text.splitlines()[0][:200] if text else type(error).__name__


def _select(readers: list[Any], wanted: Mapping[str, str] | None) -> dict[str, TopicReport]:
    """Every topic of the bags with its kind and status; kinds chosen by `wanted` or by
    type (the first topic of each kind)."""
    reports: dict[str, TopicReport] = {}
    for reader in readers:
        for connection in reader.connections:
            report = reports.get(connection.topic)
            if report is None:
                report = reports[connection.topic] = TopicReport(
                    connection.topic, connection.msgtype, 0
                )
            report.messages += connection.msgcount
    kind_of = {t: k for k, types in KIND_TYPES.items() for t in types}
    taken: dict[str, str] = {}
    by_topic = {topic: kind for kind, topic in (wanted or {}).items()}
    for report in sorted(reports.values(), key=lambda r: r.topic):  # first by name wins
        kind = kind_of.get(report.msgtype or "")
        if report.msgtype in NOT_IMPORTED_YET:
            report.kind = NOT_IMPORTED_YET[report.msgtype]
            report.status = "not imported yet"
        elif wanted is not None and report.topic not in by_topic:
            report.status = "not selected" if kind else "unknown type"
        elif kind is None:
            report.status = "unknown type"
        elif wanted is not None and by_topic[report.topic] != kind:
            report.status = f"type {report.msgtype} is not a {by_topic[report.topic]} type"
        elif kind in taken:
            report.status = f"another {kind} topic ({taken[kind]}) is imported; use --topics"
        else:
            report.kind, report.status = kind, "imported"
            taken[kind] = report.topic
    for kind, topic in (wanted or {}).items():
        if topic not in reports:
            reports[topic] = TopicReport(topic, None, 0, kind, "missing")
    return reports


def _bag_messages(reader: Any, connections: list, index: int) -> Iterator[tuple]:
    for connection, timestamp, raw in reader.messages(connections=connections):
        yield timestamp, index, connection, raw


def import_bags(
    bags: list[Path],
    output: Path,
    options: ImportOptions = ImportOptions(),
    progress: Callable[[int, int], None] | None = None,
) -> ImportReport:
    """Convert the bags (merged by time) into one recording v1 at `output`.

    `progress(done, total)` is called after each bag message read (of those imported).
    Raises SourceError for a missing or unreadable bag (nothing is left at `output`),
    `OutputExistsError` (exit 4) for an output that exists (unless `options.force`), and
    `OutputPathError` (exit 2) for a directory there.
    """
    if not bags:
        raise ConfigError("no bag given")
    check_output_file(output, force=options.force)
    errors = _bag_errors()
    store = default_typestore()
    readers: list[Any] = []
    with contextlib.ExitStack() as stack:
        for path in bags:
            reader = _open_bag(Path(path), store, errors)
            stack.callback(reader.close)
            readers.append(reader)
        reports = _select(readers, options.topics)
        frames = StaticFrames()
        if any(r.kind == "imu" and r.status == "imported" for r in reports.values()):
            try:
                frames = static_frames(readers, reports)
            except errors as error:
                raise SourceError(f"{TF_STATIC}: damaged ROS bag ({_reason(error)})") from None
        mounting = ImuMounting(options.calibration, frames)
        report = ImportReport([os.fspath(b) for b in bags], os.fspath(output), [])
        report.topics = sorted(reports.values(), key=lambda r: (r.status != "imported", r.topic))
        report.imu_frames = mounting.sources
        try:
            _convert(readers, bags, reports, output, options, mounting, report, errors, progress)
        except BaseException:
            with contextlib.suppress(OSError):
                output.unlink()
            raise
    return report


def _convert(
    readers: list[Any],
    bags: list[Path],
    reports: Mapping[str, TopicReport],
    output: Path,
    options: ImportOptions,
    mounting: ImuMounting,
    report: ImportReport,
    errors: tuple,
    progress: Callable[[int, int], None] | None,
) -> None:
    streams = []
    total = sum(r.messages for r in reports.values() if r.status == "imported")
    for index, reader in enumerate(readers):
        chosen = [c for c in reader.connections if reports[c.topic].status == "imported"]
        if chosen:
            streams.append(_bag_messages(reader, chosen, index))
    clock = NmeaClock()
    courses: dict[str, CourseMadeGood] = defaultdict(CourseMadeGood)  # per NavSatFix topic
    held: list[tuple[int, int, _Out]] = []  # (log_time, order, message): the reorder heap
    order = 0
    last_written = -1

    def write(writer: rec.RecordingWriter, until: int) -> None:
        nonlocal last_written
        while held and held[0][0] <= until:
            log_time, _, out = heapq.heappop(held)
            if log_time < last_written:
                report.out_of_order += 1
            last_written = max(last_written, log_time)
            writer.write(out.topic, out.data, out.log_time, out.publish_time)
            report.channels[out.topic] = report.channels.get(out.topic, 0) + 1
            if report.first_log_time is None:
                report.first_log_time = log_time
            report.last_log_time = max(report.last_log_time or 0, log_time)

    merged = heapq.merge(*streams, key=lambda item: (item[0], item[1]))
    motion = any(r.kind in V11_KINDS and r.status == "imported" for r in reports.values())
    with rec.RecordingWriter(
        output,
        calibration=options.calibration,
        overwrite=options.force,
        format_version=rec.FORMAT_VERSION_MOTION if motion else rec.FORMAT_VERSION,
    ) as writer:
        report.format_version = writer.format_version
        index = 0
        try:
            for done, (timestamp, index, connection, raw) in enumerate(merged, 1):
                topic = reports[connection.topic]
                message = readers[index].deserialize(raw, connection.msgtype)
                outs = _messages(topic, message, timestamp, clock, options, mounting, courses)
                for out in outs:
                    heapq.heappush(held, (out.log_time, order, out))
                    order += 1
                    topic.written += 1
                write(writer, timestamp - REORDER_WINDOW_NS)
                if progress is not None:
                    progress(done, total)
        except errors as error:
            raise SourceError(
                f"{bags[index]}: damaged ROS bag, stopped reading ({_reason(error)}); "
                "no recording written"
            ) from None
        write(writer, 1 << 63)


def _messages(
    topic: TopicReport,
    message: Any,
    log_time: int,
    clock: NmeaClock,
    options: ImportOptions,
    mounting: ImuMounting,
    courses: dict[str, CourseMadeGood],
) -> list[_Out]:
    msgtype = topic.msgtype
    if msgtype == "velodyne_msgs/msg/VelodyneScan":
        return velodyne_scan(message, topic)
    if msgtype == "sensor_msgs/msg/PointCloud2":
        return point_cloud(message, log_time, topic)
    if msgtype == "nmea_msgs/msg/Sentence":
        return nmea_sentence(message, log_time, clock, topic)
    if msgtype == "sensor_msgs/msg/NavSatFix":
        return navsatfix(message, log_time, options.gnss_quality, courses[topic.topic])
    if msgtype == "sensor_msgs/msg/Image":
        return image(message, log_time, options.jpeg_quality, topic)
    if msgtype == "sensor_msgs/msg/CompressedImage":
        return compressed_image(message, log_time, options.jpeg_quality, topic)
    if msgtype == "nav_msgs/msg/Odometry":
        return odometry(message, log_time)
    if msgtype == "sensor_msgs/msg/Imu":
        return imu(message, log_time, mounting)
    raise AssertionError(f"no conversion for {msgtype}")  # _select imports only the above
