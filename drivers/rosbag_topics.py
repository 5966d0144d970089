"""What `treetraits import` reads from a bag: the kinds of topic, their ROS types, the
presets' topic names. No heavy imports: the command line builds its help from these."""

from __future__ import annotations

from collections.abc import Mapping

from treetraits.errors import ConfigError

# Kinds a topic can be imported as (`--topics KIND=TOPIC`), and the ROS types of each.
KIND_TYPES: Mapping[str, tuple[str, ...]] = {
    "lidar": ("velodyne_msgs/msg/VelodyneScan",),
    "gnss": ("nmea_msgs/msg/Sentence", "sensor_msgs/msg/NavSatFix"),
    "camera": ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"),
    # Recording format 1.1 (drivers/motion.py).
    "odom": ("nav_msgs/msg/Odometry",),
    "imu": ("sensor_msgs/msg/Imu",),
}
MOTION_KINDS = frozenset({"odom", "imu"})
# Types a survey needs that this importer cannot convert yet: listed in the summary.
NOT_IMPORTED_YET: Mapping[str, str] = {
    "sensor_msgs/msg/PointCloud2": "points",
}
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
