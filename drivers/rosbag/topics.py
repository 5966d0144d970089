"""What `treetraits import` reads from a bag: the kinds of topic, their ROS types, the
presets' topic names. No heavy imports: the command line builds its help from these."""

from __future__ import annotations

from collections.abc import Mapping

from treetraits.errors import ConfigError

# Kinds a topic can be imported as (`--topics KIND=TOPIC`), and the ROS types of each.
KIND_TYPES: Mapping[str, tuple[str, ...]] = {
    "lidar": ("velodyne_msgs/msg/VelodyneScan",),
    # Recording format 1.1 (drivers/recording/points.py): decoded clouds, no packets.
    "points": ("sensor_msgs/msg/PointCloud2",),
    "gnss": ("nmea_msgs/msg/Sentence", "sensor_msgs/msg/NavSatFix"),
    "camera": ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"),
    # Recording format 1.1 (drivers/recording/motion.py).
    "odom": ("nav_msgs/msg/Odometry",),
    "imu": ("sensor_msgs/msg/Imu",),
}
# Kinds whose channels exist from recording format 1.1 on.
V11_KINDS = frozenset({"points", "odom", "imu"})
# Types a survey needs that this importer cannot convert yet: listed in the summary.
NOT_IMPORTED_YET: Mapping[str, str] = {}
KINDS = (*KIND_TYPES, *NOT_IMPORTED_YET.values())

# The CitrusFarm data set's topics (Teng et al., ISVC 2023; the paper's lab, a Jackal).
CITRUSFARM_TOPICS: Mapping[str, str] = {
    "points": "/velodyne_points",
    "camera": "/mapir_cam/image_raw",
    "gnss": "/piksi/navsatfix_best_fix",
    "odom": "/jackal_velocity_controller/odom",
    "imu": "/microstrain/imu/data",
}
# /piksi/navsatfix_best_fix carries RTK fixed solutions.
CITRUSFARM_GNSS_QUALITY = 4
# The MicroStrain GX5 of /microstrain/imu/data in base_link (calibration v1 `T_base_imu`,
# row-major): T_base_lidar (05-baselink-lidar-result.txt) . T_lidar_blackfly (the
# quaternion of 03-lidar-cam-result.txt) . T_blackfly_imu (Kalibr's cam0 T_cam_imu of
# 02-imu-cam-result.yaml), tests/fixtures/citrusfarm_calib/, to 6 decimals. The IMU is
# turned 180 deg about z: its x points backward, its y right.
CITRUSFARM_T_BASE_IMU: tuple[float, ...] = (
    -0.99998, 0.002759, 0.005742, 0.068042,
    -0.002748, -0.999994, 0.001973, 0.009028,
    0.005748, 0.001957, 0.999982, 0.300952,
    0.0, 0.0, 0.0, 1.0,
)  # fmt: skip


def parse_topics(items: list[str]) -> dict[str, str]:
    """`KIND=TOPIC` strings to a mapping; ConfigError for a bad item or an unknown kind."""
    topics: dict[str, str] = {}
    for item in items:
        kind, sep, topic = item.partition("=")
        if not sep or not topic:
            raise ConfigError(f"--topics takes KIND=TOPIC, got {item!r}")
        if kind not in KINDS:
            raise ConfigError(f"--topics: unknown kind {kind!r}; kinds: {', '.join(KINDS)}")
        topics[kind] = topic if topic.startswith("/") else f"/{topic}"
    return topics
