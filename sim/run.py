"""One simulated survey: an orchard, a path, and every sensor's bytes written to a
recording (format v1) exactly as the real sensors would send them, with the ground truth
and the field map beside it.

Clocks: the run starts at a fixed UTC time (so a seed gives the same recording); each
message's `log_time` is when the host would receive it (sensor time + a small latency).
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import Calibration, load_calibration
from treetraits.drivers.gnss.compose import lat_field, lon_field, sentence
from treetraits.drivers.velodyne import models as m
from treetraits.drivers.velodyne.encode import encode_position
from treetraits.drivers.velodyne.packet import lidar_publish_time
from treetraits.drivers.velodyne.telemetry import PPS_LOCKED
from treetraits.sim.camera import CameraSettings, Survey3Emulator
from treetraits.sim.clutter import MATERIALS, ClutterSettings, ObjectTruth, place_clutter
from treetraits.sim.gnss import GnssEmulator, GnssSettings, UtmZone
from treetraits.sim.lidar import LidarSettings, Scene, Vlp16Emulator, _poses
from treetraits.sim.orchard import (
    Ground,
    TerrainSettings,
    TreeSettings,
    TreeTruth,
    WindSettings,
    grid_orchard,
    ground_mesh,
    measure_truth,
    missing_truth,
    tree_foliage,
    tree_mesh,
    tree_sways,
    vary_trees,
)
from treetraits.sim.paths import (
    DriveSettings,
    drive,
    riding_trajectory,
    trajectory_function,
    waypoints,
)
from treetraits.sim.wheels import JackalMcuEmulator, WheelSettings, imu_truth

DEFAULT_CALIBRATION = Path(__file__).parent / "data" / "citrusfarm_calibration_v1.json"
START_UTC = dt.datetime(2026, 5, 12, 17, 0, 0, tzinfo=dt.UTC)
# Where the grove is: near Riverside, California (UTM 11N), the paper's home.
ORIGIN_UTM = (467_000.0, 3_758_000.0)
UTM_ZONE = 11
LATENCY_NS = {"lidar": 300_000, "camera": 30_000_000, "gnss": 60_000_000, "wheels": 2_000_000}
# A VLP-16 sends a position packet about every 14 data packets (VLP-16 manual Rev D 9.3.3).
POSITION_EVERY = 14


@dataclass(frozen=True)
class SurveySettings:
    path: str = "straight"
    width: float = 5.0  # column spacing (m): the paper's "5x5" is 5 m x 5 m
    length: float = 5.0  # row spacing along the path (m)
    columns: int = 2
    rows: int = 3
    seed: int = 0
    slope: float = 0.0  # ground slope along the path (rise over run)
    goal: float = 23.0  # m ahead of the start, as in the paper
    # Shift of the orchard across the path (m): with an odd number of columns the centre
    # lane would run through the middle column; half a spacing puts the lanes between.
    offset_y: float = 0.0
    # Where the path's +x points in the world, degrees counter-clockwise from east: real
    # blocks are planted at any bearing, and a heading or anchoring error that a field
    # aligned with the grid hides (east-west errors all along x) shows once it is turned.
    field_heading_deg: float = 0.0
    # The GNSS antenna's position on the robot (x forward, y left, z up; metres from
    # base_link), replacing the calibration's: written into the recording's calibration,
    # so replay removes the lever arm the receiver saw. None: the calibration's.
    antenna: tuple[float, float, float] | None = None
    # The LiDAR's height above base_link (m), replacing the calibration's: a tractor's
    # (1.5-3 m: its bonnet, its cab) instead of the Jackal's 0.38 m. Written into the
    # recording's calibration, as the antenna. None: the calibration's.
    lidar_height: float | None = None
    # The host's realtime clock minus UTC (s): a robot without NTP in the field. Every
    # message's log_time (and the camera's and wheels' host-clock stamps) carries it.
    host_clock_offset_s: float = 0.0
    camera_rate_hz: float = 10.0  # 0: no camera in the recording
    camera: CameraSettings = field(default_factory=lambda: CameraSettings(render_scale=0.25))
    lidar: LidarSettings = field(default_factory=LidarSettings)
    gnss: GnssSettings = field(default_factory=GnssSettings)
    wheels: WheelSettings = field(default_factory=WheelSettings)
    drive: DriveSettings = field(default_factory=DriveSettings)
    wind: WindSettings = field(default_factory=WindSettings)  # still air by default
    # A real grove's conditions (all off by default: the paper's flat, bare, uniform twin).
    terrain: TerrainSettings = field(default_factory=TerrainSettings)
    trees: TreeSettings = field(default_factory=TreeSettings)
    clutter: ClutterSettings = field(default_factory=ClutterSettings)


@dataclass(frozen=True)
class SurveyResult:
    recording: Path
    truth_csv: Path
    field_map: Path
    trees: list[TreeTruth]
    duration_s: float
    counts: dict[str, int]
    objects_csv: Path | None = None
    objects: tuple[ObjectTruth, ...] = ()


@dataclass(frozen=True)
class World:
    scene: Scene
    trees: list[TreeTruth]
    ground: Ground
    objects: tuple[ObjectTruth, ...]


@dataclass(frozen=True)
class Placement:
    """The twin's local frame (x along the path) in UTM: an origin and a bearing."""

    origin: tuple[float, float] = ORIGIN_UTM
    heading_rad: float = 0.0

    def utm(self, x: float, y: float) -> tuple[float, float]:
        c, s = math.cos(self.heading_rad), math.sin(self.heading_rad)
        return self.origin[0] + c * x - s * y, self.origin[1] + s * x + c * y

    def offset(self, x: float, y: float, yaw: float) -> tuple[float, float, float]:
        """A local pose as (east, north) from the origin and a yaw from east."""
        easting, northing = self.utm(x, y)
        return easting - self.origin[0], northing - self.origin[1], yaw + self.heading_rad


def placement(settings: SurveySettings) -> Placement:
    return Placement(ORIGIN_UTM, math.radians(settings.field_heading_deg))


def with_antenna(calibration: Calibration, xyz: tuple[float, float, float]) -> Calibration:
    """The calibration with the GNSS antenna moved to `xyz` (metres in base_link)."""
    T_base_gnss = np.array(calibration.T_base_gnss, dtype=float)
    T_base_gnss[:3, 3] = xyz
    return replace(calibration, T_base_gnss=T_base_gnss)


def with_lidar_height(calibration: Calibration, height_m: float) -> Calibration:
    """The calibration with the LiDAR raised or lowered to `height_m` above base_link;
    the camera, fixed to the LiDAR (`T_camera_lidar`), moves with it."""
    T_base_lidar = np.array(calibration.T_base_lidar, dtype=float)
    T_base_lidar[2, 3] = height_m
    return replace(calibration, T_base_lidar=T_base_lidar)


def make_ground(settings: SurveySettings) -> Ground:
    t = settings.terrain
    for name, value, limit in (
        ("slope", settings.slope, 0.5),
        ("terrain.slope_across", t.slope_across, 0.5),
        ("terrain.undulation_m", t.undulation_m, 0.5),
        ("terrain.furrow_m", t.furrow_m, 0.5),
        ("terrain.bed_height_m", t.bed_height_m, 1.0),
    ):
        if not math.isfinite(value) or abs(value) > limit:
            raise ValueError(f"{name} must be finite and within +-{limit}, got {value}")
    if not t.furrow_spacing_m > 0:
        raise ValueError(f"terrain.furrow_spacing_m must be > 0, got {t.furrow_spacing_m}")
    beds = ()
    if t.raised_beds:
        offset_y = -(settings.columns - 1) * settings.width / 2 + settings.offset_y
        beds = tuple(offset_y + c * settings.width for c in range(settings.columns))
    return Ground(
        slope_x=settings.slope,
        slope_y=t.slope_across,
        undulation_m=t.undulation_m,
        furrow_m=t.furrow_m,
        furrow_spacing_m=t.furrow_spacing_m,
        bed_rows_y=beds,
        bed_height_m=t.bed_height_m,
        phase_seed=settings.seed,
    )


def build_orchard(settings: SurveySettings, rng: np.random.Generator):
    """The scene and the truth: columns at y = +-width/2, rows from x = length on (no
    clutter: `build_world` adds it)."""
    world = build_world(settings, rng)
    return world.scene, world.trees, world.ground


def build_world(
    settings: SurveySettings,
    rng: np.random.Generator,
    poses: np.ndarray | None = None,
    t0_s: float = 0.0,
) -> World:
    """The scene, the trees' and the other objects' truth. Clutter needs the robot's
    `poses` (t s, x, y, yaw; it keeps clear of the path) and the run's start `t0_s`."""
    ground = make_ground(settings)
    specs = grid_orchard(settings.columns, settings.rows, settings.width, settings.length, rng)
    if not settings.trees.shapes_default:
        # Their own generator: the default twin's trees are drawn exactly as before.
        specs = vary_trees(specs, settings.trees, np.random.default_rng([settings.seed, 2]))
    # grid_orchard lays rows along +x from y = 0; centre the columns on the path.
    offset_y = -(settings.columns - 1) * settings.width / 2 + settings.offset_y
    # Table I names the rows along the path front, middle and back.
    names = ["front", "middle", "back"] if settings.rows == 3 else None
    specs = [
        replace(
            spec,
            tree_id=f"T{i + 1}",
            row=names[i % settings.rows] if names else str(i % settings.rows + 1),
            x=spec.x + settings.length,
            y=spec.y + offset_y,
        )
        for i, spec in enumerate(specs)
    ]
    scene = Scene()
    scene.add(*ground_mesh(ground, (-40, 60), (-40, 40)), label=0)
    meshes, truths = [], []
    # Foliage other than scattered draws from its own generator: `rng` (the default
    # twin's leaves and, after them, its sensors' noise) is drawn exactly as before.
    foliage_rng = np.random.default_rng([settings.seed, 5])
    foliage = tree_foliage(settings.trees, len(specs), foliage_rng)
    for spec, model in zip(specs, foliage, strict=True):
        if spec.kind == "missing":
            meshes.append(None)
            truths.append(missing_truth(spec))
            continue
        vertices, triangles = tree_mesh(spec, ground, rng, foliage=model, foliage_rng=foliage_rng)
        meshes.append((vertices, triangles))
        truths.append(measure_truth(spec, vertices, ground))
    # The sway's draws come from a generator of their own: the same seed grows the same
    # trees with and without wind, so the two runs compare like with like.
    planted = [t for t in truths if t.kind != "missing"]
    sways = iter(
        tree_sways(settings.wind, planted, ground, np.random.default_rng([settings.seed, 1]))
    )
    for i, mesh in enumerate(meshes):
        if mesh is not None:
            scene.add(*mesh, label=i + 1, sway=next(sways))
    objects: list[ObjectTruth] = []
    if settings.clutter.any:
        if poses is None:
            raise ValueError("clutter is placed clear of the robot's path: pass its poses")
        placed = place_clutter(
            settings.clutter,
            _row_lines(settings),
            _tree_xs(settings),
            settings.length,
            [(t.x, t.y, t.width / 2) for t in truths if t.kind != "missing"],
            poses,
            ground,
            np.random.default_rng([settings.seed, 4]),
            t0_s,
        )
        for item in placed:
            scene.add(
                item.vertices,
                item.triangles,
                label=item.truth.label,
                walk=item.walk,
                material=MATERIALS[item.truth.kind],
            )
            objects.append(item.truth)
    return World(scene, truths, ground, tuple(objects))


def _row_lines(settings: SurveySettings) -> list[float]:
    """The y of each line of trees along the path (the grid's columns)."""
    offset_y = -(settings.columns - 1) * settings.width / 2 + settings.offset_y
    return [offset_y + c * settings.width for c in range(settings.columns)]


def _tree_xs(settings: SurveySettings) -> list[float]:
    """The nominal x of the trees along each line."""
    return [settings.length * (1 + r) for r in range(settings.rows)]


def simulate_survey(
    out: Path,
    settings: SurveySettings | None = None,
    calibration: Calibration | None = None,
    progress: Callable[[float], None] | None = None,
) -> SurveyResult:
    """Write REC.mcap plus `<stem>.truth.csv`, `<stem>.objects.csv` and
    `<stem>.field_map.geojson` beside it."""
    s = settings or SurveySettings()
    calibration = calibration or load_calibration(DEFAULT_CALIBRATION)
    if s.antenna is not None:
        calibration = with_antenna(calibration, s.antenna)
    if s.lidar_height is not None:
        calibration = with_lidar_height(calibration, s.lidar_height)
    rng = np.random.default_rng(s.seed)
    poses = drive(waypoints(s.path, s.width, s.length, s.goal), s.drive)
    t0_ns = int(START_UTC.timestamp() * 1e9)
    world = build_world(s, rng, poses, t0_ns / 1e9)
    scene, truths, ground = world.scene, world.trees, world.ground
    duration_s = float(poses[-1, 0])
    # The robot rides on the ground: z under it and, unless the ground is level, its pitch
    # and roll from the ground under its four wheels.
    level = ground.is_plane and ground.slope_x == 0 and ground.slope_y == 0
    if level:
        trajectory = trajectory_function(poses, t0_ns)

        def pose_at(t_ns):
            x, y, _, yaw = trajectory(np.asarray(t_ns))
            return x, y, ground.height(x, y), yaw
    else:
        pose_at = riding_trajectory(poses, t0_ns, ground)

    def pose_values(t_ns) -> tuple[float, ...]:
        return tuple(float(v) for v in pose_at(np.asarray(t_ns)))

    zone = UtmZone(UTM_ZONE)
    place = placement(s)
    lidar = Vlp16Emulator(scene, calibration.T_base_lidar, s.lidar, rng)
    with_camera = calibration.camera is not None and s.camera_rate_hz > 0
    camera = Survey3Emulator(scene, calibration, s.camera, rng) if with_camera else None
    gnss = GnssEmulator(zone, ORIGIN_UTM, calibration.T_base_gnss, s.gnss, rng)
    mcu = JackalMcuEmulator(
        calibration.wheels, s.wheels, rng, imu_rng=np.random.default_rng([s.seed, 3])
    )

    messages: list[tuple[int, str, bytes, int]] = []  # (log_time, topic, data, publish_time)
    host = round(s.host_clock_offset_s * 1e9)  # the host clock is UTC + this
    t_end = t0_ns + int(duration_s * 1e9)
    # A drive without the LiDAR (`lidar.enabled` false) records GNSS and wheels only: what
    # a test of localisation needs, without the ray casting that is most of a drive's cost.
    packets = lidar.packets(pose_at, t0_ns, t_end) if s.lidar.enabled else ()
    for index, (t, payload) in enumerate(packets):
        # A packet leaves the sensor once its 12 blocks have fired.
        log_time = t + m.PACKET_NS_SINGLE + LATENCY_NS["lidar"] + host
        stamp = lidar_publish_time(payload, log_time)  # recording format v1
        messages.append((log_time, rec.LIDAR_PACKETS, payload, stamp))
        if s.lidar.gps_sync and index % POSITION_EVERY == 0:
            position = position_packet(t, zone, place, pose_values)
            stamp = lidar_publish_time(position, log_time)
            messages.append((log_time, rec.LIDAR_TELEMETRY, position, stamp))
    if progress:
        progress(0.5)
    if camera is not None:
        for t in np.arange(t0_ns, t_end, int(1e9 / s.camera_rate_hz)):
            messages.append(
                (
                    int(t) + LATENCY_NS["camera"] + host,
                    rec.CAMERA_JPEG,
                    camera.jpeg(_poses(*pose_values(t))[0], int(t)),
                    int(t) + host,
                )
            )
    if progress:
        progress(0.8)
    step = int(1e9 / s.gnss.rate_hz)
    previous = None
    for t in np.arange(t0_ns, t_end, step):
        x, y, z, yaw, *tilt = pose_values(t)
        speed = (
            0.0 if previous is None else math.hypot(x - previous[0], y - previous[1]) / (step / 1e9)
        )
        previous = (x, y)
        utc = START_UTC + dt.timedelta(microseconds=(int(t) - t0_ns) // 1000)
        attitude = None if level else (z, *tilt)
        east, north, bearing = place.offset(x, y, yaw)
        for framed in gnss.epoch(
            (int(t) - t0_ns) / 1e9, utc, east, north, bearing, speed, attitude
        ):
            messages.append((int(t) + LATENCY_NS["gnss"] + host, rec.GNSS_NMEA, framed, int(t)))
    messages.append((t0_ns + host, rec.WHEELS_JACKAL, mcu.handshake(), t0_ns + host))
    for t in np.arange(t0_ns, t_end, int(1e9 / s.wheels.rate_hz)):
        x, y, z, yaw, *_ = pose_values(t)
        data = mcu.feedback(int(t), x, y, yaw, None if level else z)
        if s.wheels.imu:
            # The MCU publishes imu/data_raw at the Feedback's rate: both frames arrive in
            # one read of the port.
            omega, force = imu_truth(pose_at, int(t), s.wheels.imu_difference_s)
            data += mcu.imu(int(t), omega, force)
        log_time = int(t) + LATENCY_NS["wheels"] + host
        messages.append((log_time, rec.WHEELS_JACKAL, data, log_time))
    messages.sort(key=lambda message: (message[0], message[1]))

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    truth_csv = out.with_suffix(".truth.csv")
    field_map = out.with_suffix(".field_map.geojson")
    objects_csv = out.with_suffix(".objects.csv")
    _write_truth(truth_csv, truths, zone, place)
    _write_objects(objects_csv, world.objects, place)
    geojson = _field_map(truths, zone, place)
    field_map.write_text(json.dumps(geojson, indent=1))
    counts: dict[str, int] = {}
    with rec.RecordingWriter(out, calibration=calibration.to_json(), overwrite=True) as writer:
        for log_time, topic, data, publish_time in messages:
            writer.write(topic, data, log_time=log_time, publish_time=publish_time)
            counts[topic] = counts.get(topic, 0) + 1
        writer.attach(rec.FIELD_MAP_NAME, json.dumps(geojson).encode(), rec.FIELD_MAP_MEDIA_TYPE)
    if progress:
        progress(1.0)
    return SurveyResult(
        out, truth_csv, field_map, truths, duration_s, counts, objects_csv, world.objects
    )


def position_packet(t: int, zone: UtmZone, place: Placement, pose_values) -> bytes:
    """The position packet a GPS-locked VLP-16 sends at UTC `t` (ns): its ToH, PPS locked,
    and the receiver's RMC of the last whole second (the robot's position then)."""
    second = t - t % 1_000_000_000
    x, y, _, yaw, *_ = pose_values(second)
    east, north, _ = place.offset(x, y, yaw)
    lat, lon = zone.inverse(east, north)
    utc = dt.datetime.fromtimestamp(second / 1e9, dt.UTC)
    lat_text, ns = lat_field(lat)
    lon_text, ew = lon_field(lon)
    body = f"GPRMC,{utc:%H%M%S}.00,A,{lat_text},{ns},{lon_text},{ew},,,{utc:%d%m%y},,,D"
    rmc = sentence(body).decode("ascii").rstrip("\r\n")
    return encode_position(t // 1000, PPS_LOCKED, rmc)


def _write_truth(path: Path, truths: list[TreeTruth], zone: UtmZone, place: Placement) -> None:
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(
            [
                "tree_id",
                "row",
                "x",
                "y",
                "easting",
                "northing",
                "utm_zone",
                "lat",
                "lon",
                "width_m",
                "height_m",
                "kind",  # appended: tree, or missing (a field-map position with no tree)
            ]
        )
        for t in truths:
            easting, northing = place.utm(t.x, t.y)
            lat, lon = zone.inverse(easting, northing)
            out.writerow(
                [
                    t.tree_id,
                    t.row,
                    f"{t.x:.3f}",
                    f"{t.y:.3f}",
                    f"{easting:.3f}",
                    f"{northing:.3f}",
                    zone.name,
                    f"{lat:.9f}",
                    f"{lon:.9f}",
                    "" if math.isnan(t.width) else f"{t.width:.3f}",
                    "" if math.isnan(t.height) else f"{t.height:.3f}",
                    t.kind,
                ]
            )


OBJECT_COLUMNS = (
    "object_id",
    "kind",  # weed, drip_line, post, wire, person, walking_person, vehicle, wall
    "x",
    "y",
    "easting",
    "northing",
    "size_m",  # largest horizontal extent
    "length_m",  # footprint: a segment of this length through (x, y) along heading_deg
    "width_m",  # and this wide across it
    "heading_deg",  # ccw from east
    "height_m",  # top above the ground
    "label",  # the mesh's label in the scene
)


def _write_objects(path: Path, objects, place: Placement) -> None:
    """`<stem>.objects.csv`: every non-tree object (a header only when there are none)."""
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(OBJECT_COLUMNS)
        for o in objects:
            easting, northing = place.utm(o.x, o.y)
            out.writerow(
                [
                    o.object_id,
                    o.kind,
                    f"{o.x:.3f}",
                    f"{o.y:.3f}",
                    f"{easting:.3f}",
                    f"{northing:.3f}",
                    f"{o.size:.3f}",
                    f"{o.length:.3f}",
                    f"{o.width:.3f}",
                    f"{math.degrees(o.heading + place.heading_rad):.1f}",
                    f"{o.height:.3f}",
                    o.label,
                ]
            )


def _field_map(truths: list[TreeTruth], zone: UtmZone, place: Placement) -> dict:
    features = []
    for t in truths:
        lat, lon = zone.inverse(*place.utm(t.x, t.y))
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [lon, lat]},
                "properties": {"id": t.tree_id, "row": t.row},
            }
        )
    return {"type": "FeatureCollection", "features": features}
