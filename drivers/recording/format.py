"""Recording format v1: every sensor's raw bytes in one MCAP file, written and read back.

The onboard recorder writes what each sensor sent, exactly as received, so a field day can
be replayed through the same drivers later. The format (frozen, see docs/architecture.md):

- one MCAP file, zstd-compressed chunks;
- one channel per sensor stream, no schema (schema id 0), the `message_encoding` naming the
  wire format (`TOPIC_ENCODINGS`);
- `log_time` = host receive time, `publish_time` = the sensor's own UTC time where it has
  one, else the host time; both in ns since the Unix epoch;
- a metadata record named `treetraits` holding `format_version` ("1"; "1.1" for a
  recording that carries the motion and points channels of `V11_TOPICS`), `software` and
  `calibration` (a JSON object as a string);
- attachments may hold the field map (`field_map.geojson`).

`RecordingWriter` writes such a file; `read_recording` reads one linearly, so a file cut by
a power failure still yields every message of every chunk completed before the cut, and a
damaged chunk is skipped (reading resumes at the next good one) and accounted for.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import treetraits

FORMAT_VERSION = "1"
# Format 1.1 adds the motion and points channels (`V11_TOPICS`); a writer marks a recording 1.1 only
# when asked to, so a recording without them stays readable by format-1 readers.
FORMAT_VERSION_MOTION = "1.1"
READ_VERSIONS = (FORMAT_VERSION, FORMAT_VERSION_MOTION)
METADATA_NAME = "treetraits"
SOFTWARE = f"treetraits {treetraits.__version__}"

LIDAR_PACKETS = "/lidar/packets"
LIDAR_TELEMETRY = "/lidar/telemetry"
CAMERA_JPEG = "/camera/jpeg"
GNSS_NMEA = "/gnss/nmea"
WHEELS_JACKAL = "/wheels/jackal"
WHEELS_BRIDGE = "/wheels/bridge"
WHEELS_ODOMETRY = "/wheels/odometry"
IMU_DATA = "/imu/data"
LIDAR_POINTS = "/lidar/points"

# Topic -> message_encoding, the only channels a v1 recording is written with.
TOPIC_ENCODINGS: Mapping[str, str] = {
    LIDAR_PACKETS: "velodyne-data",  # one 1206-byte UDP payload from port 2368
    LIDAR_TELEMETRY: "velodyne-position",  # one 512-byte UDP payload from port 8308
    CAMERA_JPEG: "jpeg",
    GNSS_NMEA: "nmea0183",
    WHEELS_JACKAL: "rosserial",
    WHEELS_BRIDGE: "treetraits-bridge",
    # Format 1.1 (drivers/recording/motion.py): a robot's odometry and an IMU given as numbers.
    WHEELS_ODOMETRY: "treetraits-odometry",
    IMU_DATA: "treetraits-imu",
    # Format 1.1 (drivers/recording/points.py): a decoded point cloud, one message per scan.
    LIDAR_POINTS: "treetraits-points",
}
V11_TOPICS = frozenset({WHEELS_ODOMETRY, IMU_DATA, LIDAR_POINTS})

FIELD_MAP_NAME = "field_map.geojson"
FIELD_MAP_MEDIA_TYPE = "application/geo+json"

# Chunks are compressed and written whole, so a power cut loses the chunk in progress:
# 256 KiB is about a second of VLP-16 traffic.
DEFAULT_CHUNK_SIZE = 256 * 1024
# No record of a v1 recording (chunk, attachment), compressed or not, is larger than this;
# a bigger length read from a file is garbage (a torn write) and ends the reading.
RECORD_SIZE_LIMIT = 64 * 1024 * 1024

MCAP_MAGIC = b"\x89MCAP0\r\n"
U32 = 1 << 32
U64 = 1 << 64


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One message of a recording: the sensor's bytes exactly as received.

    `log_time` is the host receive time, `publish_time` the sensor's own UTC time (or the
    host time when the sensor has none), both ns since the Unix epoch; `sequence` counts the
    messages of the topic from 0 in the writer.
    """

    topic: str
    log_time: int
    publish_time: int
    sequence: int
    data: bytes


@dataclass(frozen=True, slots=True)
class RecordingMetadata:
    """The `treetraits` metadata record of a recording, calibration parsed back to a dict."""

    format_version: str
    software: str
    calibration: dict[str, Any]


@dataclass(frozen=True, slots=True)
class RecordedAttachment:
    """An attachment of a recording (e.g. the field map)."""

    name: str
    media_type: str
    log_time: int
    create_time: int
    data: bytes
