"""`treetraits export foxglove`: a survey as an MCAP that Foxglove opens as it is.

The recording is run through the same `SurveyProcessor` as `replay` (same config, same
calibration rules), and what the pipeline saw is written with the published Foxglove
protobuf schemas (`foxglove_schemas_protobuf`; each channel's schema is its message's
`FileDescriptorSet`, message encoding `protobuf`). docs/data.md, "Looking at a survey in
Foxglove", lists the channels.

Frames (`/tf`), whatever sensors the recording has, so that every message's frame_id
reaches `map`:

- `map`: with poses (GNSS, wheels), the run's world frame (`utm` or `odom`) moved to the
  first posed scan (so that Foxglove's float32 scene keeps centimetres; a run moved from
  `odom` to `utm` at a late first fix keeps it where it began); without any, the
  frame the replay maps in, which stands still (no motion is given to the mapper): the
  robot's base_link where it stood, z up on its ground. `map_from_world` (and the origin
  of a posed run) is in the metadata record `treetraits-export`;
- `base_link`: the pose at each mapped scan's middle (identity without poses);
- `lidar` and `gnss` on base_link, `camera` on lidar: fixed by the calibration, published
  once with the recording's first message.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from treetraits.damage import integrity_facts
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import Calibration
from treetraits.drivers.gnss.epochs import EpochAssembler
from treetraits.drivers.gnss.sentences import decode
from treetraits.drivers.gnss.stream import SentenceSplitter
from treetraits.drivers.records import Fix, Frame, Scan
from treetraits.drivers.rosbag.detect import refuse_ros_bag
from treetraits.errors import ConfigError, ParseError, SourceError
from treetraits.files import check_output_file, write_atomically
from treetraits.pipeline.classify import TREE
from treetraits.pipeline.localization.pose import Pose
from treetraits.pipeline.localization.utm import wrap_angle
from treetraits.pipeline.trees import COUNT, FLAG, height_bounded, marked, width_bounded

if TYPE_CHECKING:
    from treetraits.service.survey import ScanOutcome, SurveyProcessor

MAP_FRAME = "map"
BASE_FRAME = "base_link"
LIDAR_FRAME = "lidar"
CAMERA_FRAME = "camera"
GNSS_FRAME = "gnss"
METADATA_NAME = "treetraits-export"

# Channel topics of the view.
POINTS = "/lidar/points"
POSE = "/pose"
PATH = "/path"
TF = "/tf"
FIX = "/gnss/fix"
IMAGE = "/camera/image"
NDVI = "/camera/ndvi"
TREES = "/trees"
# Trees without NDVI: grey, half transparent.
NO_NDVI_RGBA = (0.5, 0.5, 0.5, 0.6)
# A scan's points: x y z float32, intensity and ring uint8 (14 bytes a point).
_CLOUD_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1"), ("ring", "u1")]
)
# x y z are rounded to this grid (2^-9 m = 1.95 mm, exact in float32 to 32 km): the VLP-16
# measures distance in 2 mm steps to about 3 cm, so a viewer sees the same cloud, and the
# low mantissa bits, now zero, let zstd store the clouds in 56 % of the bytes (docs/data.md).
POINT_STEP_M = 2.0**-9


@dataclass
class ExportReport:
    input: str
    output: str
    channels: dict[str, int] = field(default_factory=dict)  # topic -> messages
    scans: int = 0
    trees: int = 0
    world_frame: str | None = None  # the frame the mapper held the trees in
    origin: tuple[float, float] | None = None  # map origin in the world frame (posed runs)
    map_from_world: list[float] | None = None  # 4x4, row-major: world_frame into map
    # What of the recording could not be read (treetraits/damage.py): the view is of the rest.
    integrity: dict[str, Any] = field(default_factory=integrity_facts)

    def as_dict(self) -> dict[str, Any]:
        facts = {k: v for k, v in vars(self).items() if k != "integrity"}
        return {**facts, "origin": list(self.origin) if self.origin else None, **self.integrity}


def ns_timestamp(message_field: Any, t_ns: int) -> None:
    message_field.FromNanoseconds(int(t_ns))


def quaternion_zyx(yaw: float, pitch: float, roll: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll), the `Pose` convention."""
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def matrix_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return float(x), float(y), float(z), float(w)


def ndvi_rgba(ndvi: float | None) -> tuple[float, float, float, float]:
    """A tree's colour: the RdYlGn map over NDVI [-1, 1] of the camera views
    (`pipeline.fusion.NDVI_LUT`), grey without NDVI."""
    from treetraits.pipeline.fusion import NDVI_LUT

    if ndvi is None or not math.isfinite(ndvi):
        return NO_NDVI_RGBA
    b, g, r = NDVI_LUT[round((min(max(ndvi, -1.0), 1.0) + 1.0) * 127.5)]
    return r / 255, g / 255, b / 255, 0.8


class FoxgloveWriter:
    """Thin MCAP writer: one protobuf channel per topic, registered on first use."""

    def __init__(self, stream):
        from mcap.writer import CompressionType, Writer

        self._writer = Writer(stream, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=f"{rec.SOFTWARE} export foxglove")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def _schema(self, message: Any) -> int:
        name = message.DESCRIPTOR.full_name
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_schema(
                name=name, encoding="protobuf", data=file_descriptor_set(message)
            )
        return self._schemas[name]

    def write(self, topic: str, message: Any, log_time: int, publish_time: int) -> None:
        if topic not in self._channels:
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="protobuf", schema_id=self._schema(message)
            )
        self._writer.add_message(
            channel_id=self._channels[topic],
            log_time=int(log_time),
            publish_time=int(publish_time),
            data=message.SerializeToString(),
            sequence=self.counts.get(topic, 0),
        )
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, data)

    def finish(self) -> None:
        self._writer.finish()


def file_descriptor_set(message: Any) -> bytes:
    """The schema of a protobuf message: its .proto file and every one it imports."""
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    files = FileDescriptorSet()
    seen: set[str] = set()
    todo = [message.DESCRIPTOR.file]
    while todo:
        proto = todo.pop()
        if proto.name in seen:
            continue
        seen.add(proto.name)
        proto.CopyToProto(files.file.add())
        todo.extend(proto.dependencies)
    return files.SerializeToString()


def point_cloud(scan: Scan, t: int) -> Any:
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud

    points = scan.distinct if scan.points["duplicate"].any() else scan.points
    rows = np.empty(len(points), dtype=_CLOUD_DTYPE)
    for name in _CLOUD_DTYPE.names:
        rows[name] = points[name]
    for name in ("x", "y", "z"):
        rows[name] = np.round(rows[name] / POINT_STEP_M) * POINT_STEP_M
    kinds = {"f": PackedElementField.FLOAT32, "u": PackedElementField.UINT8}
    message = PointCloud(
        frame_id=LIDAR_FRAME,
        point_stride=_CLOUD_DTYPE.itemsize,
        fields=[
            PackedElementField(
                name=name, offset=_CLOUD_DTYPE.fields[name][1], type=kinds[_CLOUD_DTYPE[name].kind]
            )
            for name in _CLOUD_DTYPE.names
        ],
        data=rows.tobytes(),
    )
    message.pose.orientation.w = 1.0
    ns_timestamp(message.timestamp, t)
    return message


def pose_in_map(pose: Pose, origin: tuple[float, float]) -> Any:
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    message = PoseInFrame(frame_id=MAP_FRAME)
    ns_timestamp(message.timestamp, pose.t)
    p = message.pose
    p.position.x, p.position.y, p.position.z = pose.x - origin[0], pose.y - origin[1], pose.z
    q = quaternion_zyx(pose.yaw, pose.pitch, pose.roll)
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = q
    return message


def path_in_map(poses: list[Pose], origin: tuple[float, float], t: int) -> Any:
    """Every pose of the run as one path in `map`."""
    from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame

    message = PosesInFrame(frame_id=MAP_FRAME)
    ns_timestamp(message.timestamp, t)
    for pose in poses:
        p = message.poses.add()
        p.position.x, p.position.y, p.position.z = pose.x - origin[0], pose.y - origin[1], pose.z
        q = quaternion_zyx(pose.yaw, pose.pitch, pose.roll)
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = q
    return message


def frame_transform(
    t: int, parent: str, child: str, translation, rotation: tuple[float, float, float, float]
) -> Any:
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform

    message = FrameTransform(parent_frame_id=parent, child_frame_id=child)
    ns_timestamp(message.timestamp, t)
    message.translation.x, message.translation.y, message.translation.z = (
        float(v) for v in translation
    )
    r = message.rotation
    r.x, r.y, r.z, r.w = rotation
    return message


def matrix_transform(t: int, parent: str, child: str, parent_from_child: np.ndarray) -> Any:
    """A FrameTransform from a 4x4 rigid transform (the child's pose in the parent)."""
    T = parent_from_child
    return frame_transform(t, parent, child, T[:3, 3], matrix_quaternion(T[:3, :3]))


def static_frames(calibration: Calibration, t: int) -> list[Any]:
    """The sensors on the robot, from the calibration: lidar and gnss on base_link, the
    camera on lidar (its extrinsics are against the LiDAR) when there is one."""
    frames = [
        matrix_transform(t, BASE_FRAME, LIDAR_FRAME, calibration.T_base_lidar),
        matrix_transform(t, BASE_FRAME, GNSS_FRAME, calibration.T_base_gnss),
    ]
    if calibration.T_camera_lidar is not None:  # the camera in the lidar frame
        camera = np.linalg.inv(calibration.T_camera_lidar)
        frames.append(matrix_transform(t, LIDAR_FRAME, CAMERA_FRAME, camera))
    return frames


@dataclass(frozen=True)
class MapFrame:
    """Where `map` is in `world`, the frame the mapper holds its trees in: a 4x4 rigid
    `map_from_world`; `origin`, a posed run's first pose (x, y) in `world`."""

    world: str
    map_from_world: np.ndarray
    origin: tuple[float, float] | None = None


def posed_map(pose: Pose) -> MapFrame:
    """The world frame moved to the first posed scan: float32 keeps centimetres there."""
    map_from_world = np.eye(4)
    map_from_world[:2, 3] = (-pose.x, -pose.y)
    return MapFrame(pose.frame, map_from_world, (pose.x, pose.y))


def unposed_map(world: str, calibration: Calibration) -> MapFrame:
    """Without poses the replay gives the mapper no motion: the robot stands still in the
    frame the mapper holds its trees in (TreeMapper: the LiDAR's, `lidar`; RPH:
    `base_footprint`). `map` is the robot's base there, so that the view is upright with
    the ground at z = 0 even for a LiDAR mounted on its side."""
    if world == LIDAR_FRAME:
        return MapFrame(world, np.asarray(calibration.T_base_lidar, dtype=float))
    return MapFrame(world, np.eye(4))


def odom_pose(pose: Pose, utm_from_odom: np.ndarray) -> Pose:
    """A `utm` pose in the `odom` frame its run began in, through the 3x3 transform the
    run's map was moved into `utm` with (`SurveyProcessor.anchor`)."""
    x, y, _ = np.linalg.solve(utm_from_odom, (pose.x, pose.y, 1.0))
    yaw = wrap_angle(pose.yaw - math.atan2(utm_from_odom[1, 0], utm_from_odom[0, 0]))
    return replace(pose, x=float(x), y=float(y), yaw=yaw, frame="odom")


def utm_map(where: MapFrame, utm_from_odom: np.ndarray) -> MapFrame:
    """The `map` of a run begun in `odom`, seen from `utm`, where its trees ended."""
    utm_from_odom_4 = np.eye(4)
    utm_from_odom_4[:2, :2] = utm_from_odom[:2, :2]
    utm_from_odom_4[:2, 3] = utm_from_odom[:2, 2]
    map_from_utm = where.map_from_world @ np.linalg.inv(utm_from_odom_4)
    origin = where.origin or (0.0, 0.0)
    x, y, _ = utm_from_odom @ (origin[0], origin[1], 1.0)
    return MapFrame("utm", map_from_utm, (float(x), float(y)))


def base_in_map(pose: Pose | None, where: MapFrame, t: int) -> Any:
    """map -> base_link at a mapped scan: its pose; without one the robot's base, which
    `map` is (`unposed_map`)."""
    if pose is None:
        return matrix_transform(t, MAP_FRAME, BASE_FRAME, np.eye(4))
    origin = where.origin or (0.0, 0.0)
    translation = (pose.x - origin[0], pose.y - origin[1], pose.z)
    rotation = quaternion_zyx(pose.yaw, pose.pitch, pose.roll)
    return frame_transform(t, MAP_FRAME, BASE_FRAME, translation, rotation)


def location_fix(fix: Fix) -> Any | None:
    """A GNSS epoch with a position; its GST sigmas as a diagonal ENU covariance."""
    from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix

    if fix.lat is None or fix.lon is None or fix.quality == 0:
        return None
    message = LocationFix(
        frame_id="gnss",
        latitude=fix.lat,
        longitude=fix.lon,
        altitude=fix.altitude_ellipsoid_m or 0.0,
    )
    ns_timestamp(message.timestamp, fix.t_host)
    sigmas = (fix.std_lon_m, fix.std_lat_m, fix.std_alt_m)
    if all(s is not None for s in sigmas):
        message.position_covariance.extend(
            [sigmas[0] ** 2, 0, 0, 0, sigmas[1] ** 2, 0, 0, 0, sigmas[2] ** 2]
        )
        message.position_covariance_type = LocationFix.DIAGONAL_KNOWN
    else:
        message.position_covariance.extend([0.0] * 9)
        message.position_covariance_type = LocationFix.UNKNOWN
    return message


def compressed_image(jpeg: bytes, t: int) -> Any:
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    message = CompressedImage(frame_id=CAMERA_FRAME, data=jpeg, format="jpeg")
    ns_timestamp(message.timestamp, t)
    return message


def ndvi_jpeg(frame: Frame, calibration: Calibration, quality: int = 85) -> bytes | None:
    """The frame's NDVI as the camera views colour it (RdYlGn, NaN grey), or None without a
    camera calibration or when the JPEG does not decode."""
    import cv2

    from treetraits.pipeline.fusion import colorize_ndvi
    from treetraits.pipeline.ndvi import ndvi_image

    camera = calibration.camera
    if camera is None:
        return None
    try:
        image = frame.decode()
    except ParseError:
        return None  # a corrupt JPEG: the image channel still has it, as it is
    picture = colorize_ndvi(ndvi_image(image, camera.channels, calibration.reflectance))
    ok, data = cv2.imencode(".jpg", picture, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return data.tobytes() if ok else None


def trait_flags(tree: Any) -> tuple[bool | None, int | None]:
    """`height_top_seen` and `width_sides_seen` of a mapped tree, read as trees.csv reads
    them (`pipeline.georef`): None where the tree has none (not judged)."""
    return getattr(tree, "height_top_seen", None), getattr(tree, "width_sides_seen", None)


def tree_label(tree: Any) -> str:
    """The text above a tree: its id, then width and height as `replay`'s table prints
    them (`pipeline.trees.marked`: `>` before a lower bound), so that a viewer sees which
    traits were measured without opening the metadata."""
    top_seen, sides_seen = trait_flags(tree)
    width = marked(tree.width_m, width_bounded(sides_seen))
    height = marked(tree.height_m, height_bounded(top_seen))
    return f"{tree.tree_id}\nw {width} m  h {height} m"


def scene_update(trees: list, map_from_world: np.ndarray, t: int) -> Any:
    """The trees as upright cylinders in `map`: diameter the width, length the height,
    standing on z = 0 (base_footprint's ground), coloured by NDVI; id, traits and how
    they were measured as metadata (the flags as trees.csv writes them), a label above."""
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    update = SceneUpdate()
    for tree in trees:
        entity = update.entities.add(id=f"tree-{tree.tree_id}", frame_id=MAP_FRAME)
        ns_timestamp(entity.timestamp, t)
        top_seen, sides_seen = trait_flags(tree)
        for key, value in (
            ("tree_id", tree.tree_id),
            ("width_m", f"{tree.width_m:.3f}"),
            ("height_m", f"{tree.height_m:.3f}"),
            ("ndvi", "" if tree.ndvi is None else f"{tree.ndvi:.3f}"),
            ("observations", tree.observations),
            ("height_top_seen", FLAG.csv(top_seen)),
            ("width_sides_seen", COUNT.csv(sides_seen)),
        ):
            entity.metadata.add(key=key, value=str(value))
        cylinder = entity.cylinders.add(bottom_scale=1.0, top_scale=1.0)
        x, y, _ = map_from_world[:3, :3] @ (tree.x, tree.y, tree.z) + map_from_world[:3, 3]
        cylinder.pose.position.x, cylinder.pose.position.y = float(x), float(y)
        cylinder.pose.position.z = tree.height_m / 2
        cylinder.pose.orientation.w = 1.0
        cylinder.size.x = cylinder.size.y = tree.width_m
        cylinder.size.z = tree.height_m
        c = cylinder.color
        c.r, c.g, c.b, c.a = ndvi_rgba(tree.ndvi)
        text = entity.texts.add(
            billboard=True, font_size=14, scale_invariant=True, text=tree_label(tree)
        )
        text.pose.position.x = cylinder.pose.position.x
        text.pose.position.y = cylinder.pose.position.y
        text.pose.position.z = tree.height_m + 0.3
        text.pose.orientation.w = 1.0
        text.color.r = text.color.g = text.color.b = text.color.a = 1.0
    return update


def run_recording(run_dir: Path) -> tuple[Path, dict]:
    """The recording a replay output directory came from, and its run facts."""
    import json

    from treetraits.readonly import connect_read_only, sqlite_errors
    from treetraits.service.outputs import STORE_NAME

    store = run_dir / STORE_NAME
    if not store.is_file():
        raise SourceError(f"{run_dir}: no {STORE_NAME} (not a replay's output directory)")
    # Read-only, leaving no -wal/-shm in the run directory (treetraits/readonly.py).
    with (
        contextlib.closing(connect_read_only(store, "a run's store")) as db,
        sqlite_errors(store, "a run's store"),
    ):
        rows = list(db.execute("SELECT key, value FROM run"))
    facts = {}
    for key, value in rows:  # strings are stored as they are, the rest as JSON
        try:
            facts[key] = json.loads(value)
        except ValueError:
            facts[key] = value
    source = facts.get("input")
    if not source:
        raise SourceError(f"{store}: the run does not say which recording it came from")
    path = Path(source)
    if not path.is_absolute() and not path.exists():
        path = run_dir / path
    if not path.is_file():
        raise SourceError(f"{run_dir}: its recording {source} is not there")
    return path, facts


def export_foxglove(
    source: Path,
    output: Path,
    config,
    calibration: Path | None = None,
    force: bool = False,
    progress: Callable[[int], None] | None = None,
) -> ExportReport:
    """Write `output` (a Foxglove MCAP) from a recording, or from a replay's output
    directory (its recording, with the run's method, traits and calibration)."""
    from treetraits.service.config import with_method
    from treetraits.service.replay import ReplayOptions, open_replay

    check_output_file(output, force=force)  # a directory, an earlier view: before any work
    if output.resolve() == source.resolve():
        raise ConfigError(f"{output}: is the input")
    recording, run_calibration = source, None
    if source.is_dir():
        refuse_ros_bag(source, "a recording or a replay's output directory")
        recording, facts = run_recording(source)
        config = with_method(config, facts.get("method"), facts.get("traits"))
        run_calibration = facts.get("calibration")
    options = ReplayOptions(config=config, calibration=calibration)
    inputs = open_replay(recording, options)
    if calibration is None and run_calibration:
        from treetraits.drivers.calibration import load_calibration

        inputs = type(inputs)(inputs.source, load_calibration(run_calibration), inputs.field_map)
    report = ExportReport(os.fspath(source), os.fspath(output))

    def write(stream: IO[bytes]) -> None:
        writer = FoxgloveWriter(stream)
        _export(inputs, config, writer, report, progress)
        writer.metadata(
            METADATA_NAME,
            {
                "input": os.fspath(source),
                "recording": os.fspath(recording),
                "world_frame": report.world_frame or "",
                "origin_x": repr(report.origin[0]) if report.origin else "",
                "origin_y": repr(report.origin[1]) if report.origin else "",
                "map_from_world": json.dumps(report.map_from_world),
            },
        )
        writer.finish()
        report.channels = dict(writer.counts)
        report.integrity = inputs.source.integrity()  # once read to its end

    try:
        # Beside `output` and renamed when complete: a failed or interrupted export leaves
        # the earlier file as it was.
        write_atomically(output, write, binary=True)
    finally:
        inputs.source.close()
    return report


def _export(inputs, config, writer: FoxgloveWriter, report: ExportReport, progress) -> None:
    from treetraits.service.survey import make_processor

    processor = make_processor(config, inputs.calibration)
    view = _View(writer, inputs.calibration, report)
    splitter, epochs = SentenceSplitter(), EpochAssembler()

    def fixes(fix: Fix | None) -> None:
        if fix is not None and (message := location_fix(fix)) is not None:
            writer.write(FIX, message, fix.t_host, fix.utc_ns or fix.t_host)

    for topic, data, log_time, publish_time in inputs.source.messages:
        view.received(log_time)
        for o in processor.feed(topic, data, log_time, publish_time):
            view.scan(o, processor)
        if topic == rec.CAMERA_JPEG:
            writer.write(IMAGE, compressed_image(bytes(data), publish_time), log_time, publish_time)
        elif topic == rec.GNSS_NMEA:
            for sentence in splitter.push(data, log_time):
                if (record := decode(sentence)) is not None:
                    fixes(epochs.push(record))
        if progress:
            progress(len(data))
    for o in processor.finish():
        view.scan(o, processor)
    fixes(epochs.flush())
    trees = [
        t
        for t in processor.mapper.trees()
        if t.observations >= config.output.min_observations and t.kind == TREE
    ]
    view.finish(trees, processor)


class _View:
    """The messages written from the pipeline's scans, and what they need from each other:
    the sensors' frames before anything, `map` fixed by the first mapped scan."""

    def __init__(self, writer: FoxgloveWriter, calibration: Calibration, report: ExportReport):
        self.writer, self.calibration, self.report = writer, calibration, report
        self.map: MapFrame | None = None
        self.poses: list[Pose] = []
        self.first_scan: int | None = None  # time of the first mapped scan
        self.first_time: int | None = None  # of the first message received
        self.last_time = 0
        self.ndvi_of: int | None = None  # the sequence of the last frame written as NDVI

    def received(self, log_time: int) -> None:
        if self.first_time is None:
            # The sensors' frames first, so that every message can be placed from the start.
            self.first_time = log_time
            for message in static_frames(self.calibration, log_time):
                self.writer.write(TF, message, log_time, log_time)
        self.last_time = max(self.last_time, log_time)

    def scan(self, o: ScanOutcome, processor: SurveyProcessor) -> None:
        t = o.pose.t if o.pose is not None else o.scan.t_host
        self.report.scans += 1
        if self.map is None:
            self.map = (
                posed_map(o.pose)
                if o.pose is not None
                else unposed_map(processor.mapper.frame or LIDAR_FRAME, self.calibration)
            )
            self.first_scan = t
        pose = self.in_map_world(o.pose, processor.anchor)
        self.writer.write(TF, base_in_map(pose, self.map, t), t, t)
        if pose is not None:
            self.writer.write(POSE, pose_in_map(pose, self.map.origin or (0.0, 0.0)), t, t)
            self.poses.append(pose)
        self.writer.write(POINTS, point_cloud(o.scan, t), t, t)
        self.ndvi(o.frame, t)

    def in_map_world(self, pose: Pose | None, anchor: tuple[int, np.ndarray] | None) -> Pose | None:
        """A run mapped in `odom` until its first fix goes on in `utm` (its map moved there
        whole, `SurveyProcessor._reanchor`); `map` stays where it began, in `odom`, so the
        later poses are taken back there rather than jump to their UTM coordinates."""
        if pose is None or self.map is None or anchor is None:
            return pose
        if (self.map.world, pose.frame) == ("odom", "utm"):
            return odom_pose(pose, anchor[1])
        return pose

    def ndvi(self, frame: Frame | None, t: int) -> None:
        """The NDVI of the frame a scan used, once per frame: scans faster than the camera
        share one, and Foxglove shows it until the next."""
        if frame is None or frame.sequence == self.ndvi_of:
            return
        self.ndvi_of = frame.sequence
        if (jpeg := ndvi_jpeg(frame, self.calibration)) is not None:
            self.writer.write(NDVI, compressed_image(jpeg, frame.t_capture), t, frame.t_capture)

    def finish(self, trees: list, processor: SurveyProcessor) -> None:
        """The final map and the whole path, shown from the first scan on (Foxglove keeps a
        scene entity until it is replaced, and shows a topic's latest message)."""
        if self.map is not None and (self.map.world, processor.mapper.frame) == ("odom", "utm"):
            self.map = utm_map(self.map, processor.anchor[1])  # the trees are in utm now
        if self.map is None:
            # Nothing mapped: `map` is still the robot's base, so that what was written
            # (camera, fixes) reaches it.
            self.map = unposed_map(BASE_FRAME, self.calibration)
            if self.first_time is not None:
                base = base_in_map(None, self.map, self.last_time)
                self.writer.write(TF, base, self.last_time, self.last_time)
        self.report.trees = len(trees)
        self.report.world_frame = self.map.world
        self.report.origin = self.map.origin
        self.report.map_from_world = self.map.map_from_world.ravel().tolist()
        t0 = self.first_scan if self.first_scan is not None else self.last_time
        if self.poses:
            path = path_in_map(self.poses, self.map.origin or (0.0, 0.0), t0)
            self.writer.write(PATH, path, t0, t0)
        if trees:
            self.writer.write(TREES, scene_update(trees, self.map.map_from_world, t0), t0, t0)
