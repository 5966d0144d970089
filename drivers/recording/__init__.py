"""The recording format: every sensor's raw bytes in one MCAP file (docs/recording.md).

`format` holds the format's constants and records, `writer` the writer, `reader` the
damage-tolerant reader, `rotation` the recorder that rotates files by size and age, and
`motion` and `points` the channels of format 1.1. The names most callers need are here.
"""

from treetraits.drivers.recording.format import (
    CAMERA_JPEG,
    DEFAULT_CHUNK_SIZE,
    FIELD_MAP_MEDIA_TYPE,
    FIELD_MAP_NAME,
    FORMAT_VERSION,
    FORMAT_VERSION_MOTION,
    GNSS_NMEA,
    IMU_DATA,
    LIDAR_PACKETS,
    LIDAR_POINTS,
    LIDAR_TELEMETRY,
    METADATA_NAME,
    READ_VERSIONS,
    RECORD_SIZE_LIMIT,
    SOFTWARE,
    TOPIC_ENCODINGS,
    V11_TOPICS,
    WHEELS_BRIDGE,
    WHEELS_JACKAL,
    WHEELS_ODOMETRY,
    RecordedAttachment,
    RecordedMessage,
    RecordingMetadata,
)
from treetraits.drivers.recording.reader import Damage, RecordingReader, read_recording
from treetraits.drivers.recording.writer import RecordingWriter

__all__ = [
    "CAMERA_JPEG",
    "DEFAULT_CHUNK_SIZE",
    "FIELD_MAP_MEDIA_TYPE",
    "FIELD_MAP_NAME",
    "FORMAT_VERSION",
    "FORMAT_VERSION_MOTION",
    "GNSS_NMEA",
    "IMU_DATA",
    "LIDAR_PACKETS",
    "LIDAR_POINTS",
    "LIDAR_TELEMETRY",
    "METADATA_NAME",
    "READ_VERSIONS",
    "RECORD_SIZE_LIMIT",
    "SOFTWARE",
    "TOPIC_ENCODINGS",
    "V11_TOPICS",
    "WHEELS_BRIDGE",
    "WHEELS_JACKAL",
    "WHEELS_ODOMETRY",
    "Damage",
    "RecordedAttachment",
    "RecordedMessage",
    "RecordingMetadata",
    "RecordingReader",
    "RecordingWriter",
    "read_recording",
]
