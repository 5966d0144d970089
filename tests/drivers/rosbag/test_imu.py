"""An IMU mounted turned: `treetraits import` gives the localiser base_link's rates and
accelerations, the rotation taken from the calibration's `T_base_imu` or from the bag's
`/tf_static`. The samples are the twin's Jackal IMU (body frame), written into a ROS 1 bag
as a turned IMU would report them."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from rosbags.typesys import get_types_from_msg
from ruamel.yaml import YAML

from tests.helpers.paths import FIXTURES
from tests.helpers.rosbag import cli, header, recorded, turned_rows, typestore, write_ros1
from tests.helpers.surveys import twin_survey
from treetraits.drivers import recording as rec
from treetraits.drivers.recording.motion import decode_imu
from treetraits.drivers.rosbag.convert import ImportOptions, import_bags
from treetraits.drivers.rosbag.topics import CITRUSFARM_T_BASE_IMU
from treetraits.firmware_bridge.jackal.records import JackalImu
from treetraits.firmware_bridge.jackal.session import JackalProtocol
from treetraits.sim.run import SurveySettings

CALIB = FIXTURES / "citrusfarm_calib"


def rz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rx(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    from scipy.spatial.transform import Rotation

    return tuple(Rotation.from_matrix(R).as_quat())  # x y z w


@pytest.fixture(scope="module")
def twin_imu(tmp_path_factory) -> list[JackalImu]:
    """The twin's IMU samples (base_link), from a short survey's MCU stream."""
    twin = twin_survey(SurveySettings(seed=2, goal=3.0))
    mcu = JackalProtocol()
    samples = []
    for m in rec.read_recording(twin.recording, [rec.WHEELS_JACKAL]):
        samples += [
            r for r in mcu.receive(m.data, m.log_time, m.log_time / 1e9) if isinstance(r, JackalImu)
        ]
        mcu.take_outgoing()
    assert len(samples) > 100
    return samples


def ros1_store():
    """ROS 1 types plus tf2_msgs/TFMessage (as tf2_msgs ships it), which rosbags lacks."""
    store = typestore(ros1=True)
    store.register(
        get_types_from_msg(
            "geometry_msgs/TransformStamped[] transforms\n", "tf2_msgs/msg/TFMessage"
        )
    )
    return store


def tf_static_row(store, t: int, links: list[tuple[str, str, np.ndarray]]) -> tuple:
    T = store.types
    transforms = []
    for parent, child, R in links:
        x, y, z, w = quaternion(R)
        transforms.append(
            T["geometry_msgs/msg/TransformStamped"](
                header=header(store, t, parent, True),
                child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=0.1, y=0.0, z=0.3),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
                ),
            )
        )
    msg = T["tf2_msgs/msg/TFMessage"](transforms=transforms)
    return (t, "/tf_static", msg.__msgtype__, msg)


def imported(path) -> np.ndarray:
    return np.array(
        [
            [*s.angular_velocity, *s.linear_acceleration]
            for s in (decode_imu(m.data, m.log_time) for m in recorded(path, rec.IMU_DATA))
        ]
    )


def body(samples: list[JackalImu]) -> np.ndarray:
    return np.array([[*s.angular_velocity, *s.linear_acceleration] for s in samples])


def test_the_bags_static_transforms_turn_the_imu_into_base_link(tmp_path, twin_imu):
    store = ros1_store()
    # base_link -> imu_mount (pitched 90 deg) -> microstrain (a further turn): a chain.
    mount, sensor = rx(90), rz(180) @ rx(-90) @ rz(30)
    R = mount @ sensor
    rows = turned_rows(store, twin_imu, R, "microstrain_link")
    rows.append(tf_static_row(store, twin_imu[0].t_host - 10**9, [
        ("base_link", "imu_mount", mount), ("imu_mount", "microstrain_link", sensor),
    ]))  # fmt: skip
    bag = write_ros1(tmp_path / "imu.bag", store, rows)

    report = import_bags([bag], tmp_path / "imu.mcap")

    assert report.imu_frames == {
        "microstrain_link": "/tf_static base_link -> imu_mount -> microstrain_link"
    }
    (tf,) = [t for t in report.topics if t.topic == "/tf_static"]
    assert tf.status.startswith("read: static transforms")
    assert np.abs(imported(tmp_path / "imu.mcap") - body(twin_imu)).max() < 1e-9


def test_the_calibrations_t_base_imu_wins_and_without_one_nothing_is_turned(tmp_path, twin_imu):
    store = ros1_store()
    R = rz(180)
    bag = write_ros1(tmp_path / "imu.bag", store, turned_rows(store, twin_imu, R, "gx5"))
    T = np.eye(4)
    T[:3, :3] = R
    calibration = {"T_base_imu": T.ravel().tolist()}

    report = import_bags([bag], tmp_path / "a.mcap", ImportOptions(calibration=calibration))
    assert report.imu_frames == {"gx5": "calibration T_base_imu"}
    assert np.abs(imported(tmp_path / "a.mcap") - body(twin_imu)).max() < 1e-9

    # No calibration, no /tf_static: the IMU's frame is taken as base_link, and said so.
    report = import_bags([bag], tmp_path / "b.mcap")
    assert report.imu_frames == {"gx5": "none: no transform to base_link, taken as base_link"}
    raw = imported(tmp_path / "b.mcap")
    assert np.abs(raw[:, :3] + body(twin_imu)[:, :3] * [1, 1, -1]).max() < 1e-9  # x, y flipped
    assert np.abs(raw[:, 5] - body(twin_imu)[:, 5]).max() < 1e-9 and raw[:, 5].mean() > 9


def _pose(text: str) -> np.ndarray:
    """`x, y, z, qx, qy, qz, qw = ...` of the CitrusFarm result files as a 4x4."""
    from scipy.spatial.transform import Rotation

    line = re.search(r"x, y, z, qx, qy, qz, qw = (.*)", text).group(1)
    x, y, z, *q = (float(v) for v in line.split(","))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = (x, y, z)
    return T


def test_the_citrusfarm_preset_carries_the_microstrains_mounting_from_the_fixtures(tmp_path):
    T_base_lidar = _pose((CALIB / "05-baselink-lidar-result.txt").read_text())
    T_lidar_blackfly = _pose((CALIB / "03-lidar-cam-result.txt").read_text())
    kalibr = YAML(typ="safe").load((CALIB / "02-imu-cam-result.yaml").read_text())
    T_blackfly_imu = np.array(kalibr["cam0"]["T_cam_imu"], dtype=float)
    expected = T_base_lidar @ T_lidar_blackfly @ T_blackfly_imu
    assert np.abs(np.array(CITRUSFARM_T_BASE_IMU).reshape(4, 4) - expected).max() < 1e-6

    store = ros1_store()
    bag = write_ros1(tmp_path / "e.bag", store, [tf_static_row(store, 10**18, [])])
    out = tmp_path / "e.mcap"
    result = cli("import", str(bag), "--out", str(out), "--preset", "citrusfarm")
    assert result.returncode == 0, result.stderr
    stored = rec.read_recording(out).metadata.calibration
    fixture = json.loads((CALIB / "citrusfarm_calibration_v1.json").read_text())
    assert stored == {**fixture, "T_base_imu": list(CITRUSFARM_T_BASE_IMU)}
