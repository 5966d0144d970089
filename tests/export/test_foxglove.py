"""`treetraits export foxglove`: a twin survey written as a Foxglove MCAP and read back
with `mcap` alone. Every message is decoded with the schema its channel declares (a
protobuf FileDescriptorSet, loaded into a fresh descriptor pool, not the installed
classes), and what it says is checked against the recording and the replay's outputs."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from tests.helpers.captures import decode_file
from tests.helpers.surveys import twin_survey
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import load_calibration
from treetraits.drivers.gnss.epochs import EpochAssembler
from treetraits.drivers.gnss.sentences import decode
from treetraits.drivers.gnss.stream import SentenceSplitter
from treetraits.sim.run import SurveySettings

CLI = [sys.executable, "-m", "treetraits"]
EXPECTED_SCHEMAS = {
    "/lidar/points": "foxglove.PointCloud",
    "/pose": "foxglove.PoseInFrame",
    "/path": "foxglove.PosesInFrame",
    "/tf": "foxglove.FrameTransform",
    "/gnss/fix": "foxglove.LocationFix",
    "/camera/image": "foxglove.CompressedImage",
    "/camera/ndvi": "foxglove.CompressedImage",
    "/trees": "foxglove.SceneUpdate",
}


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True)


def message_class(schema):
    """The message class built from the schema's own FileDescriptorSet."""
    files = descriptor_pb2.FileDescriptorSet.FromString(schema.data).file
    pool = descriptor_pool.DescriptorPool()
    added: set[str] = set()
    pending = list(files)
    while pending:  # dependencies first
        ready = [f for f in pending if set(f.dependency) <= added]
        assert ready, f"{schema.name}: the schema lacks a file it imports"
        for f in ready:
            pool.Add(f)
            added.add(f.name)
            pending.remove(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))


def read_view(path: Path) -> dict[str, list]:
    """topic -> decoded messages, checking every channel's schema and every message."""
    out: dict[str, list] = {}
    classes = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            assert schema.name == EXPECTED_SCHEMAS[channel.topic], channel.topic
        for schema, channel, message in reader.iter_messages():
            cls = classes.get(schema.id) or classes.setdefault(schema.id, message_class(schema))
            decoded = cls.FromString(message.data)
            # Every byte is a field the schema knows: nothing unknown is carried.
            assert decoded.SerializeToString() == message.data
            out.setdefault(channel.topic, []).append((message, decoded))
    return out


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    root = tmp_path_factory.mktemp("foxglove")
    twin = twin_survey(SurveySettings(seed=2, goal=8.0))
    run = root / "run"
    replay = cli("replay", str(twin.recording), "--out", str(run), "--json")
    assert replay.returncode == 0, replay.stderr
    view = root / "view.mcap"
    result = cli("export", "foxglove", str(twin.recording), "--out", str(view), "--json")
    assert result.returncode == 0, result.stderr
    return twin, run, json.loads(replay.stdout), view, json.loads(result.stdout)


def test_every_channel_has_a_foxglove_schema_and_every_message_decodes(survey):
    _, _, replayed, view, report = survey
    messages = read_view(view)
    assert set(messages) == set(EXPECTED_SCHEMAS)
    assert {topic: len(m) for topic, m in messages.items()} == report["channels"]
    assert report["scans"] == replayed["scans"] and report["trees"] == replayed["trees"] >= 4


def test_the_scans_are_the_recordings_scans(survey):
    twin, _, replayed, view, _ = survey
    clouds = [m for _, m in read_view(view)["/lidar/points"]]
    scans, _ = decode_file(twin.recording)
    assert len(clouds) == replayed["scans"]
    # Every scan the pipeline processed, in order (the decoder's scans, less any the
    # pipeline could not place: at most the partial ones at the ends), as it mapped them:
    # de-skewed (localization.deskew), each point moved by the robot's motion between its
    # firing and the scan's middle, a few centimetres at the twin's speed.
    assert len(scans) - 2 <= len(clouds) <= len(scans)
    layout = np.dtype({"names": ["x", "y", "z", "intensity", "ring"],
                       "formats": ["<f4", "<f4", "<f4", "u1", "u1"],
                       "offsets": [0, 4, 8, 12, 13], "itemsize": 14})  # fmt: skip
    j, moved = 0, []
    for cloud in clouds:
        assert cloud.frame_id == "lidar" and cloud.point_stride == 14
        fields = {f.name: (f.offset, f.type) for f in cloud.fields}
        assert fields == {
            "x": (0, 7),
            "y": (4, 7),
            "z": (8, 7),
            "intensity": (12, 1),
            "ring": (13, 1),
        }
        rows = np.frombuffer(cloud.data, dtype=layout)
        while not (
            len(scans[j].distinct) == len(rows)
            and np.array_equal(scans[j].distinct["ring"], rows["ring"])
        ):
            j += 1  # a scan the pipeline left out
        points = scans[j].distinct
        assert np.array_equal(rows["intensity"], points["intensity"])
        shift = np.sqrt(sum((rows[a] - points[a]).astype(float) ** 2 for a in ("x", "y", "z")))
        assert shift.max() < 0.15
        moved.append(shift.max())
        j += 1
    assert max(moved) > 0.001  # the twin drives: de-skewing moved points


def test_camera_fixes_and_frames_follow_the_recording(survey):
    twin, _, _, view, report = survey
    messages = read_view(view)
    jpegs = list(rec.read_recording(twin.recording, [rec.CAMERA_JPEG]))
    images = [m for _, m in messages["/camera/image"]]
    assert [i.data for i in images] == [j.data for j in jpegs]
    assert all(i.format == "jpeg" and i.frame_id == "camera" for i in images)
    assert [i.timestamp.ToNanoseconds() for i in images] == [j.publish_time for j in jpegs]
    # The NDVI overlay: one JPEG per mapped scan that had a frame, the camera's size.
    import cv2

    ndvi = [m for _, m in messages["/camera/ndvi"]]
    assert len(ndvi) >= len(messages["/lidar/points"]) - 5
    picture = cv2.imdecode(np.frombuffer(ndvi[len(ndvi) // 2].data, np.uint8), cv2.IMREAD_COLOR)
    camera = load_calibration(rec.read_recording(twin.recording).metadata.calibration).camera
    assert picture.shape == (camera.height, camera.width, 3)

    splitter, epochs, expected = SentenceSplitter(), EpochAssembler(), []
    for m in rec.read_recording(twin.recording, [rec.GNSS_NMEA]):
        for sentence in splitter.push(m.data, m.log_time):
            if (record := decode(sentence)) is not None and (fix := epochs.push(record)):
                expected.append(fix)
    if (fix := epochs.flush()) is not None:
        expected.append(fix)
    expected = [f for f in expected if f.lat is not None and f.quality > 0]
    fixes = [m for _, m in messages["/gnss/fix"]]
    assert [(f.latitude, f.longitude) for f in fixes] == [(e.lat, e.lon) for e in expected]
    assert fixes[0].position_covariance_type in (0, 2)

    # Frames: map -> base_link at every pose; base_link -> lidar and lidar -> camera fixed.
    tf = [m for _, m in messages["/tf"]]
    pairs = {(t.parent_frame_id, t.child_frame_id) for t in tf}
    assert pairs == {("map", "base_link"), ("base_link", "lidar"), ("lidar", "camera")}
    calibration = load_calibration(rec.read_recording(twin.recording).metadata.calibration)
    (lidar,) = [t for t in tf if t.child_frame_id == "lidar"]
    translation = [lidar.translation.x, lidar.translation.y, lidar.translation.z]
    assert translation == pytest.approx(calibration.T_base_lidar[:3, 3].tolist())
    poses = [m for _, m in messages["/pose"]]
    assert len(poses) == sum(t.child_frame_id == "base_link" for t in tf)
    ((_, path),) = messages["/path"]
    assert [p.SerializeToString() for p in path.poses] == [
        p.pose.SerializeToString() for p in poses
    ]
    q = poses[-1].pose.orientation
    assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0, rel_tol=1e-9)
    # The origin of map is in the metadata: the first pose sits on it.
    assert abs(poses[0].pose.position.x) < 1e-9 and abs(poses[0].pose.position.y) < 1e-9
    assert report["world_frame"] == "utm"


def test_the_trees_are_the_replays_cylinders_coloured_by_ndvi(survey):
    _, run, _, view, report = survey
    (update,) = [m for _, m in read_view(view)["/trees"]]
    with open(run / "trees.csv", newline="") as f:
        rows = {r["tree_id"]: r for r in csv.DictReader(f) if r["tree_id"]}  # not the missing
    entities = {e.id.removeprefix("tree-"): e for e in update.entities}
    assert entities.keys() == rows.keys()
    ox, oy = report["origin"]
    assert any(r["ndvi"] for r in rows.values())
    for tree_id, e in entities.items():
        row, (c,) = rows[tree_id], e.cylinders
        assert e.frame_id == "map"
        assert c.size.x == c.size.y == pytest.approx(float(row["width_m"]), abs=0.0005)
        assert c.size.z == pytest.approx(float(row["height_m"]), abs=0.0005)
        assert c.pose.position.z == pytest.approx(c.size.z / 2)
        assert c.pose.position.x + ox == pytest.approx(float(row["easting"]), abs=0.005)
        assert c.pose.position.y + oy == pytest.approx(float(row["northing"]), abs=0.005)
        meta = {kv.key: kv.value for kv in e.metadata}
        assert meta["tree_id"] == tree_id
        if row["ndvi"]:
            # Both are rounded (3 decimals here, 4 in the CSV): each half a unit off at most.
            assert float(meta["ndvi"]) == pytest.approx(float(row["ndvi"]), abs=0.00055)
            if float(row["ndvi"]) > 0.3:  # foliage: the green half of RdYlGn
                assert c.color.g > c.color.r
        else:
            assert (c.color.r, c.color.g, c.color.b) == (0.5, 0.5, 0.5)


def test_a_run_directory_exports_its_own_run(survey, tmp_path):
    _, run, _, view, report = survey
    out = tmp_path / "run_view.mcap"
    result = cli("export", "foxglove", str(run), "--out", str(out), "--json")
    assert result.returncode == 0, result.stderr
    ours = read_view(out)
    theirs = read_view(view)
    assert {t: len(m) for t, m in ours.items()} == report["channels"]
    # The same trees, byte for byte (each read builds its own classes: compare the bytes).
    assert ours["/trees"][0][0].data == theirs["/trees"][0][0].data


def test_bad_inputs_are_one_line_and_nothing_is_written(survey, tmp_path):
    _, _, _, view, _ = survey
    out = tmp_path / "v.mcap"
    for bad in (tmp_path / "nope.mcap", tmp_path):  # missing; a directory without a run
        result = cli("export", "foxglove", str(bad), "--out", str(out))
        assert result.returncode == 2, result.stderr
        assert result.stderr.startswith("treetraits: error: ") and "Traceback" not in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
        assert not out.exists() and not list(tmp_path.glob("*.tmp"))
    before = view.read_bytes()
    exists = cli("export", "foxglove", str(bad), "--out", str(view))
    assert exists.returncode == 4 and "--force" in exists.stderr
    assert view.read_bytes() == before
