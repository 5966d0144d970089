"""`treetraits camera info|grab` on replay sources, as a user runs them."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from treetraits.cli import main
from treetraits.drivers import recording
from treetraits.drivers.camera import open_camera_source, record_frame
from treetraits.drivers.records import Frame

MS = 1_000_000
T0 = 1_780_000_000_000_000_000


def jpeg(k: int) -> bytes:
    img = np.zeros((90, 120, 3), np.uint8)
    img[:, :, 0] = np.arange(120, dtype=np.uint8)
    img[10 + k : 30 + k, 20:60] = (40 * k) % 256
    ok, data = cv2.imencode(".jpg", img)
    assert ok
    return data.tobytes()


@pytest.fixture
def rec(tmp_path):
    """A recording of 12 frames at 30 fps, 40 ms from exposure start to receipt."""
    frames = [
        Frame(jpeg(k), T0 + k * 33_333_333 + 40 * MS, T0 + k * 33_333_333, k) for k in range(12)
    ]
    path = tmp_path / "rec.mcap"
    with recording.RecordingWriter(path) as writer:
        for frame in frames:
            record_frame(writer, frame)
    return path, frames


@pytest.mark.parametrize(
    "command", [["camera"], ["camera", "info"], ["camera", "grab"]], ids=" ".join
)
def test_every_camera_command_has_help(command):
    result = subprocess.run(
        [sys.executable, "-m", "treetraits", *command, "--help"], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage: treetraits camera")
    assert "--help" in result.stdout


def test_grab_writes_jpegs_and_timestamps_that_read_back(rec, tmp_path, capsys):
    path, frames = rec
    out = tmp_path / "grabbed"
    assert main(["camera", "grab", str(path), "--out", str(out), "-n", "5"]) == 0
    assert "wrote 5 frames" in capsys.readouterr().out
    assert len(sorted(out.glob("*.jpg"))) == 5 and (out / "timestamps.csv").is_file()
    back = list(open_camera_source(out))
    assert [(f.jpeg, f.t_host, f.t_capture) for f in back] == [
        (f.jpeg, f.t_host, f.t_capture) for f in frames[:5]
    ]

    every = tmp_path / "every"
    assert main(["camera", "grab", str(path), "--out", str(every), "--every", "4"]) == 0
    assert [f.jpeg for f in open_camera_source(every)] == [frames[k].jpeg for k in (0, 4, 8)]

    # A second grab into the same folder is refused, not mixed in.
    assert main(["camera", "grab", str(path), "--out", str(out)]) == 2
    assert "already holds a timestamps.csv" in capsys.readouterr().err


def test_info_on_a_recording(rec, capsys):
    path, _ = rec
    assert main(["camera", "info", str(path), "--json"]) == 0
    facts = json.loads(capsys.readouterr().out)
    assert facts["kind"] == "recording"
    measured = facts["measured"]
    assert measured["frames"] == 12
    assert measured["fps_median"] == pytest.approx(30.0, rel=1e-3)
    assert measured["latency_ms_median"] == pytest.approx(40.0)
    assert (measured["width"], measured["height"]) == (120, 90)
    assert facts["t_first_ns"] == T0
    assert facts["counters"]["decoded"] == 1  # the first frame only, for its size

    assert main(["camera", "info", str(path)]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"{path} (recording)") and "fps_median" in text


def test_info_counts_corrupt_frames_only_when_asked(tmp_path, capsys):
    path = tmp_path / "rec.mcap"
    with recording.RecordingWriter(path) as writer:
        for k in range(4):
            data = jpeg(k) if k != 2 else b"\xff\xd8 garbage"
            writer.write(recording.CAMERA_JPEG, data, T0 + k * 100 * MS)
    assert main(["camera", "info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["counters"]["corrupt"] == 0
    assert main(["camera", "info", str(path), "--json", "--decode-all"]) == 0
    counters = json.loads(capsys.readouterr().out)["counters"]
    assert (counters["decoded"], counters["corrupt"]) == (4, 1)


def test_info_on_a_video_with_a_start_time(tmp_path, capsys):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (120, 90))
    for k in range(5):
        writer.write(cv2.imdecode(np.frombuffer(jpeg(k), np.uint8), cv2.IMREAD_COLOR))
    writer.release()
    start = "2026-05-28T12:00:00Z"
    assert main(["camera", "info", str(path), "--json", "--video-start", start]) == 0
    facts = json.loads(capsys.readouterr().out)
    assert (facts["codec"], facts["jpeg"]) == ("MJPG", "verbatim")
    assert facts["measured"]["frames"] == 5
    assert facts["t_first_ns"] == 1_779_969_600 * 1_000_000_000
    assert facts["t_last_ns"] - facts["t_first_ns"] == 400 * MS


def test_bad_inputs_are_one_clear_line(tmp_path, capsys):
    assert main(["camera", "info", str(tmp_path / "nope.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("treetraits: error:") and "no such file or folder" in err
    clip = tmp_path / "x.avi"
    clip.write_bytes(b"")
    assert main(["camera", "info", str(clip), "--video-start", "yesterday"]) == 2
    assert "--video-start 'yesterday'" in capsys.readouterr().err
