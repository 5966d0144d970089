"""`sensor_msgs/PointCloud2` through `treetraits import` and `replay`: clouds written by
this file with rosbags from real decoded scans (the fixtures' VLP-16 pcaps), in the two
layouts ROS drivers publish (velodyne_pointcloud in a ROS 1 bag, nebula in a ROS 2 bag),
come back as the same scans."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin

from tests.helpers.captures import VLP16_DIR, decode_file
from tests.helpers.rosbag import (
    VELODYNE_DTYPE,
    cloud_message,
    recorded,
    replay,
    typestore,
    write_ros1,
    write_ros2,
)
from treetraits.drivers import recording as rec
from treetraits.drivers.recording.points import decode_header, decode_points
from treetraits.drivers.rosbag.convert import import_bags
from treetraits.errors import ParseError

VELOVIEW = VLP16_DIR / "veloview_vlp16_20hz_strongest.pcap"  # 51 scans, single return
LIDARUTILS = VLP16_DIR / "lidarutils_vlp16_strongest_0x22.pcap"  # 2 scans

FLOAT32, UINT8, UINT16, UINT32 = 7, 2, 4, 6
# velodyne_pointcloud's PointXYZIRT (PCL's 16-byte aligned xyz, then intensity, ring,
# time as float32 seconds from the header stamp, which is the last packet's).
VELODYNE_FIELDS = [
    ("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32),
    ("intensity", 16, FLOAT32), ("ring", 20, UINT16), ("time", 24, FLOAT32),
]  # fmt: skip
# nebula's PointXYZIRCAEDT-like layout: uint8 intensity, uint16 channel, uint32 ns from the
# header stamp (the scan's first firing).
NEBULA_FIELDS = [
    ("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32),
    ("intensity", 12, UINT8), ("return_type", 13, UINT8), ("channel", 14, UINT16),
    ("azimuth", 16, FLOAT32), ("distance", 20, FLOAT32), ("time_stamp", 24, UINT32),
]  # fmt: skip
NEBULA_DTYPE = np.dtype({"names": [f[0] for f in NEBULA_FIELDS],
                         "formats": ["<f4", "<f4", "<f4", "u1", "u1", "<u2", "<f4", "<f4", "<u4"],
                         "offsets": [f[1] for f in NEBULA_FIELDS], "itemsize": 28})  # fmt: skip


def velodyne_rows(store, scans) -> list[tuple]:
    """Each scan as velodyne_pointcloud publishes it, stamped at its last firing (the
    driver stamps its last packet; the capture's host clock is not the sensor's, so the
    firing times stand in for it), received 2 ms later."""
    out = []
    for scan in scans:
        p = scan.points
        rows = np.zeros(len(p), dtype=VELODYNE_DTYPE)
        for name in ("x", "y", "z", "intensity", "ring"):
            rows[name] = p[name]
        stamp = int(p["t"].max())
        rows["time"] = ((p["t"] - stamp) / 1e9).astype(np.float32)
        msg = cloud_message(store, True, stamp, VELODYNE_FIELDS, rows)
        out.append((stamp + 2_000_000, "/velodyne_points", msg.__msgtype__, msg))
    return out


def nebula_rows(store, scans) -> list[tuple]:
    """Each scan in nebula's layout, as an organised 2-row cloud padded with a NaN point
    per row (no return), received 2 ms after its last firing."""
    out = []
    for scan in scans:
        p = scan.points
        stamp = int(p["t"].min())
        rows = np.zeros(len(p), dtype=NEBULA_DTYPE)
        for name in ("x", "y", "z", "intensity", "azimuth"):
            rows[name] = p[name]
        rows["channel"] = p["ring"]
        rows["distance"] = np.hypot(np.hypot(p["x"], p["y"]), p["z"])
        rows["time_stamp"] = p["t"] - stamp
        half = (len(rows) + 1) // 2
        nan = np.zeros(1, dtype=NEBULA_DTYPE)
        nan["x"] = nan["y"] = nan["z"] = np.nan
        filler = nan if len(rows) % 2 == 0 else np.concatenate([nan, nan])
        grid = np.concatenate([rows[:half], nan, rows[half:], filler])
        msg = cloud_message(store, False, stamp, NEBULA_FIELDS, grid, height=2)
        out.append(
            (int(p["t"].max()) + 2_000_000, "/sensing/lidar/pointcloud", msg.__msgtype__, msg)
        )
    return out


def assert_same_scan(ours, theirs, time_tolerance_ns: int) -> None:
    a, b = ours.points, theirs.points
    assert len(a) == len(b)
    for name in ("x", "y", "z", "intensity", "ring", "return_type", "duplicate"):
        assert np.array_equal(a[name], b[name]), name
    assert np.abs(a["t"] - b["t"]).max() <= time_tolerance_ns
    # azimuth comes back from x and y: the packet decoder's angle to float32 rounding.
    wrapped = np.angle(np.exp(1j * (a["azimuth"].astype(float) - b["azimuth"])))
    assert np.abs(wrapped).max() < 2e-5
    assert abs(ours.t_start - int(b["t"].min())) <= time_tolerance_ns
    assert abs(ours.t_end - int(b["t"].max())) <= time_tolerance_ns
    assert ours.model == theirs.model == "VLP-16"


def test_velodyne_pointcloud_clouds_in_a_ros1_bag_are_the_pcaps_scans(tmp_path):
    scans, _ = decode_file(VELOVIEW)
    store = typestore(ros1=True)
    bag = write_ros1(tmp_path / "points.bag", store, velodyne_rows(store, scans))
    out = tmp_path / "points.mcap"

    report = import_bags([bag], out)

    assert report.format_version == "1.1"
    assert report.channels == {rec.LIDAR_POINTS: len(scans)}
    messages = recorded(out, rec.LIDAR_POINTS)
    assert len(messages) == len(scans) == 51
    for message, scan in zip(messages, scans, strict=True):
        head, _ = decode_header(message.data)
        assert head.frame_id == "velodyne"
        assert head.fields == ("x", "y", "z", "intensity", "ring", "t")
        assert message.publish_time == head.stamp == scan.points["t"].max()
        assert message.log_time == head.stamp + 2_000_000
        # time is float32 seconds from the stamp: a few ns of rounding at 50 ms.
        assert_same_scan(decode_points(message.data), scan, time_tolerance_ns=4)
    assert replay(out, tmp_path / "run")["scans"] == len(scans)


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
def test_nebula_clouds_in_a_ros2_bag_are_the_pcaps_scans(tmp_path, storage):
    scans, _ = decode_file(LIDARUTILS)
    store = typestore(ros1=False)
    bag = write_ros2(tmp_path / "points", store, nebula_rows(store, scans), storage)
    out = tmp_path / "points.mcap"

    report = import_bags([bag], out)

    (topic,) = [t for t in report.topics if t.topic == "/sensing/lidar/pointcloud"]
    assert (topic.kind, topic.status, topic.written) == ("points", "imported", len(scans))
    # The organised clouds' NaN points (one or two per row) are dropped and counted.
    nans = sum(2 if len(s.points) % 2 == 0 else 3 for s in scans)
    assert topic.skip_reasons == {"points without finite x, y, z (dropped)": nans}
    messages = recorded(out, rec.LIDAR_POINTS)
    assert len(messages) == len(scans) == 2
    for message, scan in zip(messages, scans, strict=True):
        assert_same_scan(decode_points(message.data), scan, time_tolerance_ns=0)
    assert replay(out, tmp_path / "run")["scans"] == len(scans)


def test_a_damaged_points_message_is_a_parse_error():
    scans, _ = decode_file(LIDARUTILS)
    store = typestore(ros1=False)
    from treetraits.drivers.rosbag.convert import TopicReport, point_cloud

    msg = nebula_rows(store, scans[:1])[0][3]
    (good,) = point_cloud(msg, 0, TopicReport("/p", None, 1))
    with pytest.raises(ParseError):
        decode_points(good.data[:-5])
    with pytest.raises(ParseError):
        decode_points(b"\x10\x00\x00\x00{not json")
