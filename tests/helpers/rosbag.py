"""ROS bags written with rosbags' own writers, and what `treetraits import` makes of them:
the message definitions rosbags lacks, headers and rows (time, topic, type, message),
ROS 1 and ROS 2 writers, and the CLI and the recordings it writes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from treetraits.drivers import recording as rec
from treetraits.drivers.gnss.epochs import EpochAssembler
from treetraits.drivers.gnss.sentences import decode
from treetraits.drivers.records import Fix
from treetraits.firmware_bridge.jackal.records import JackalImu

CLI = [sys.executable, "-m", "treetraits"]

# The message definitions as the ROS packages ship them (ros-drivers/velodyne,
# ros-drivers/nmea_msgs); rosbags' default type stores lack them.
ROS1_DEFS = {
    "velodyne_msgs/msg/VelodynePacket": "time stamp\nuint8[1206] data\n",
    "velodyne_msgs/msg/VelodyneScan": "Header header\nVelodynePacket[] packets\n",
    "nmea_msgs/msg/Sentence": "Header header\nstring sentence\n",
}


ROS2_DEFS = {
    "velodyne_msgs/msg/VelodynePacket": "builtin_interfaces/Time stamp\nuint8[1206] data\n",
    "velodyne_msgs/msg/VelodyneScan": (
        "std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets\n"
    ),
    "nmea_msgs/msg/Sentence": "std_msgs/Header header\nstring sentence\n",
}


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True)


def typestore(ros1: bool):
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types: dict = {}
    for name, text in (ROS1_DEFS if ros1 else ROS2_DEFS).items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def stamp(store, t: int):
    return store.types["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)


def header(store, t: int, frame: str, ros1: bool):
    Header = store.types["std_msgs/msg/Header"]
    if ros1:
        return Header(seq=0, stamp=stamp(store, t), frame_id=frame)
    return Header(stamp=stamp(store, t), frame_id=frame)


def write_ros1(path: Path, store, rows: list[tuple]) -> Path:
    with Writer1(path) as writer:
        connections = {}
        for t, topic, msgtype, msg in sorted(rows, key=lambda r: r[0]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], t, store.serialize_ros1(msg, msgtype))
    return path


def write_ros2(path: Path, store, rows: list[tuple], storage: StoragePlugin) -> Path:
    with Writer2(path, version=9, storage_plugin=storage) as writer:
        connections = {}
        for t, topic, msgtype, msg in sorted(rows, key=lambda r: r[0]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(connections[topic], t, store.serialize_cdr(msg, msgtype))
    return path


def recorded(path: Path, topic: str) -> list[rec.RecordedMessage]:
    return list(rec.read_recording(path, [topic]))


def recording_fixes(path: Path) -> list[Fix]:
    assembler = EpochAssembler()
    fixes = []
    for message in recorded(path, rec.GNSS_NMEA):
        (sentence,) = _split(message.data)
        record = decode(sentence)
        if record is not None and (fix := assembler.push(record)) is not None:
            fixes.append(fix)
    if (fix := assembler.flush()) is not None:
        fixes.append(fix)
    return fixes


def _split(data: bytes) -> list:
    from treetraits.drivers.gnss.stream import SentenceSplitter

    splitter = SentenceSplitter()
    return [*splitter.push(data, 0), *splitter.flush()]


def replay(recording: Path, out: Path, *options: str) -> dict:
    result = cli("replay", str(recording), "--out", str(out), "--json", *options)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def _vector(store, x: float, y: float, z: float):
    return store.types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def odometry_row(store, t: int, speed: float, turn: float) -> tuple:
    T = store.types
    twist = T["geometry_msgs/msg/Twist"](
        linear=_vector(store, speed, 0.0, 0.0), angular=_vector(store, 0.0, 0.0, turn)
    )
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    msg = T["nav_msgs/msg/Odometry"](
        header=header(store, t, "odom", True),
        child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )
    return (t, "/jackal_velocity_controller/odom", msg.__msgtype__, msg)


def imu_row(store, record) -> tuple:
    T = store.types
    msg = T["sensor_msgs/msg/Imu"](
        header=header(store, record.t_host, "imu_link", True),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.array([-1.0, *[0.0] * 8]),
        angular_velocity=_vector(store, *record.angular_velocity),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=_vector(store, *record.linear_acceleration),
        linear_acceleration_covariance=np.zeros(9),
    )
    return (record.t_host, "/imu/data", msg.__msgtype__, msg)


def turned_rows(store, samples: list[JackalImu], R_base_imu: np.ndarray, frame: str) -> list:
    """The samples as an IMU turned by R_base_imu reports them: v_imu = R^T v_base."""
    rows = []
    for s in samples:
        t, _, msgtype, msg = imu_row(store, s)
        msg.header.frame_id = frame
        w = R_base_imu.T @ np.asarray(s.angular_velocity)
        a = R_base_imu.T @ np.asarray(s.linear_acceleration)
        msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = w
        msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = a
        rows.append((t, "/microstrain/imu/data", msgtype, msg))
    return rows


# velodyne_pointcloud's PointXYZIRT (PCL's 16-byte aligned xyz, then intensity, ring,
# time as float32 seconds from the header stamp), 32 bytes a point.
VELODYNE_DTYPE = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "time"],
                           "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
                           "offsets": [0, 4, 8, 16, 20, 24], "itemsize": 32})  # fmt: skip


def cloud_message(store, ros1: bool, stamp: int, fields, rows: np.ndarray, height: int = 1):
    T = store.types
    PointField = T["sensor_msgs/msg/PointField"]
    width = len(rows) // height
    return T["sensor_msgs/msg/PointCloud2"](
        header=header(store, stamp, "velodyne", ros1),
        height=height,
        width=width,
        fields=[PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        is_bigendian=False,
        point_step=rows.dtype.itemsize,
        row_step=rows.dtype.itemsize * width,
        data=np.frombuffer(rows.tobytes(), dtype=np.uint8).copy(),
        is_dense=False,
    )
