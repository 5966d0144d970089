"""Camera replay sources on real files made here: JPEGs from cv2.imencode, an MJPG AVI and
an MPEG-4 MP4 from cv2.VideoWriter, recordings from RecordingWriter. Plus the ring's
nearest-frame lookup, which the pipeline uses once per scan.
"""

from __future__ import annotations

import csv
import shutil

import cv2
import numpy as np
import pytest

from treetraits.drivers import recording
from treetraits.drivers.camera import (
    FolderWriter,
    FrameRing,
    ImageFolderSource,
    RecordingSource,
    VideoFileSource,
    open_camera_source,
    record_frame,
)
from treetraits.drivers.camera.frames import CameraStats, interval_summary, nearest_index
from treetraits.drivers.camera.replay import parse_timestamps
from treetraits.drivers.records import Frame
from treetraits.errors import ParseError, SourceError

MS = 1_000_000
T0 = 1_780_000_000_000_000_000  # 2026-05-28, ns since the Unix epoch


def image(k: int, width: int = 160, height: int = 120) -> np.ndarray:
    """A real image that differs per k: gradients and a bright bar at a k-dependent place."""
    y, x = np.mgrid[0:height, 0:width]
    img = np.dstack([x * 255 // width, y * 255 // height, np.full_like(x, (37 * k) % 256)])
    img = img.astype(np.uint8)
    img[:, (11 * k) % (width - 6) :][:, :6] = 255
    return img


def jpeg(k: int, **size) -> bytes:
    ok, data = cv2.imencode(".jpg", image(k, **size))
    assert ok
    return data.tobytes()


# --- folder of JPEGs + timestamps.csv ----------------------------------------------------


@pytest.fixture
def folder(tmp_path):
    """Five good JPEGs, a corrupt one, a listed-but-missing one, an unlisted one and a bad
    row; rows not in time order, some with a host time."""
    out = tmp_path / "frames"
    out.mkdir()
    files = {f"img_{k}.jpg": jpeg(k) for k in range(5)}
    files["broken.jpg"] = b"\xff\xd8\xff\xe0" + bytes(range(256)) * 8  # a JPEG in name only
    for name, data in files.items():
        (out / name).write_bytes(data)
    (out / "stray.JPG").write_bytes(jpeg(9))  # not listed
    rows = [
        "file,t_capture_ns,t_host_ns",
        f"img_2.jpg,{T0 + 200 * MS},{T0 + 245 * MS}",
        f"img_0.jpg,{T0}",
        f"img_1.jpg,{T0 + 100 * MS},{T0 + 140 * MS}",
        f"broken.jpg,{T0 + 250 * MS}",
        f"gone.jpg,{T0 + 275 * MS}",
        "img_3.jpg,not-a-time",
        f"img_3.jpg,{T0 + 300 * MS}",
        "",
        f"img_4.jpg,{T0 + 400 * MS}",
    ]
    (out / "timestamps.csv").write_text("\n".join(rows) + "\n")
    return out, files


def test_folder_keeps_bytes_verbatim_and_times_from_the_list(folder, decode_calls):
    path, files = folder
    source = open_camera_source(path)
    assert isinstance(source, ImageFolderSource) and not source.is_live
    frames = list(source)
    names = ["img_0.jpg", "img_1.jpg", "img_2.jpg", "broken.jpg", "img_3.jpg", "img_4.jpg"]
    assert [f.jpeg for f in frames] == [files[n] for n in names]  # time order, bytes as is
    assert [f.t_capture - T0 for f in frames] == [
        0,
        100 * MS,
        200 * MS,
        250 * MS,
        300 * MS,
        400 * MS,
    ]
    assert [f.t_host - T0 for f in frames] == [0, 140 * MS, 245 * MS, 250 * MS, 300 * MS, 400 * MS]
    stats = source.stats
    assert (stats.frames, stats.missing, stats.unlisted, stats.bad_rows) == (6, 1, 1, 1)
    assert stats.bytes == sum(len(f.jpeg) for f in frames)
    # Reading decoded nothing; the corrupt file is not known yet.
    assert decode_calls == [] and stats.corrupt == 0

    for frame in frames:
        name = _name(files, frame)
        if name == "broken.jpg":
            with pytest.raises(ParseError, match="not a decodable JPEG"):
                source.decode(frame)
            continue
        picture = source.decode(frame)
        assert np.abs(picture.astype(int) - image(int(name[4])).astype(int)).mean() < 3
    assert (stats.decoded, stats.corrupt) == (6, 1)
    source.close()


def _name(files: dict[str, bytes], frame: Frame) -> str:
    return next(n for n, data in files.items() if data == frame.jpeg)


def test_folder_without_timestamps_is_a_clear_error(tmp_path):
    (tmp_path / "a.jpg").write_bytes(jpeg(0))
    with pytest.raises(SourceError, match=r"no timestamps.csv.*file,t_capture_ns\[,t_host_ns\]"):
        open_camera_source(tmp_path)


def test_parse_timestamps_rules():
    rows, bad = parse_timestamps(
        [
            "# made by hand",
            "a.jpg,10",
            " b.jpg , 20 , 25 ",
            "c.jpg,-5",
            "../escape.jpg,30",
            "/abs.jpg,30",
            "d.jpg,40,41,42",
            ",50",
        ]
    )
    assert [(r.file, r.t_capture, r.t_host) for r in rows] == [("a.jpg", 10, 10), ("b.jpg", 20, 25)]
    assert bad == 5
    rows, bad = parse_timestamps(["name,time", "x.jpg,1"])
    assert len(rows) == 1 and bad == 0  # a header of any wording


def test_folder_writer_output_reads_back(tmp_path):
    frames = [Frame(jpeg(k), T0 + k * 33 * MS + 40 * MS, T0 + k * 33 * MS, k) for k in range(4)]
    with FolderWriter(tmp_path / "out") as writer:
        for frame in frames:
            writer.write(frame)
    back = list(open_camera_source(tmp_path / "out"))
    assert [(f.jpeg, f.t_host, f.t_capture) for f in back] == [
        (f.jpeg, f.t_host, f.t_capture) for f in frames
    ]
    with open(tmp_path / "out" / "timestamps.csv") as f:
        assert next(csv.reader(f)) == ["file", "t_capture_ns", "t_host_ns"]
    with pytest.raises(SourceError, match="already holds"):
        FolderWriter(tmp_path / "out")


# --- video files ---------------------------------------------------------------------


def write_video(path, fourcc: str, count: int, fps: float = 10.0) -> list[np.ndarray]:
    images = [image(k, 320, 240) for k in range(count)]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (320, 240))
    assert writer.isOpened(), f"this OpenCV cannot write {fourcc}"
    for img in images:
        writer.write(img)
    writer.release()
    return images


def test_mjpg_video_keeps_its_jpeg_packets_and_frame_times(tmp_path, decode_calls):
    path = tmp_path / "clip.avi"
    images = write_video(path, "MJPG", 12)
    source = open_camera_source(path, video_start_ns=T0)
    assert isinstance(source, VideoFileSource) and source.passthrough
    frames = list(source)
    assert len(frames) == 12
    assert [f.t_capture - T0 for f in frames] == [k * 100 * MS for k in range(12)]
    assert all(f.t_host == f.t_capture for f in frames)
    assert [f.sequence for f in frames] == list(range(12))
    assert source.stats.reencoded == 0 and source.stats.bad_times == 0
    assert all(f.jpeg[:2] == b"\xff\xd8" and f.jpeg[-2:] == b"\xff\xd9" for f in frames)
    assert len(decode_calls) == 0  # the packets were not decoded on read (the probe read one)
    for frame, original in zip(frames, images, strict=True):
        decoded = source.decode(frame)
        assert np.abs(decoded.astype(int) - original.astype(int)).mean() < 4


def test_other_codecs_are_reencoded_once_on_read(tmp_path):
    path = tmp_path / "clip.mp4"
    images = write_video(path, "mp4v", 6, fps=5.0)
    source = open_camera_source(path, video_start_ns=T0)
    assert not source.passthrough
    frames = list(source)
    assert len(frames) == 6 and source.stats.reencoded == 6
    assert [f.t_capture - T0 for f in frames] == [k * 200 * MS for k in range(6)]
    for frame, original in zip(frames, images, strict=True):
        assert np.abs(source.decode(frame).astype(int) - original.astype(int)).mean() < 8


# --- recordings -----------------------------------------------------------------------


def test_recording_round_trip(tmp_path):
    frames = [
        Frame(jpeg(k), T0 + k * 33_333_333 + 41 * MS, T0 + k * 33_333_333, k) for k in range(8)
    ]
    path = tmp_path / "rec.mcap"
    with recording.RecordingWriter(path) as writer:
        for frame in frames:
            record_frame(writer, frame)
            writer.write(recording.GNSS_NMEA, b"$GPGGA,,,,,,0,,,,,,,,*66\r\n", frame.t_host)
    source = open_camera_source(path)
    assert isinstance(source, RecordingSource)
    assert list(source) == frames  # bytes, t_host, t_capture and sequence
    assert source.stats.frames == 8 and not source.stats.truncated

    # Cut short by a power failure: the readable prefix, flagged.
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    with RecordingSource(cut) as short:
        prefix = list(short)
        assert prefix == frames[: len(prefix)] and short.stats.truncated


def test_unknown_inputs_are_clear_errors(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(SourceError, match="not a camera input"):
        open_camera_source(text)
    with pytest.raises(SourceError, match="no such file or folder"):
        open_camera_source(tmp_path / "nothing.avi")
    broken = tmp_path / "broken.avi"
    broken.write_bytes(b"RIFF....AVI junk" * 10)
    with pytest.raises(SourceError, match="OpenCV cannot read this video"):
        open_camera_source(broken)


# --- nearest frame -------------------------------------------------------------------


def test_nearest_index_picks_the_closest_and_rejects_beyond_the_skew():
    times = [0, 100, 200, 300]
    assert nearest_index(times, 140, 50) == 1
    assert nearest_index(times, 160, 50) == 2
    assert nearest_index(times, 150, 50) == 1  # a tie goes to the earlier frame
    assert nearest_index(times, 360, 50) is None
    assert nearest_index(times, 350, 50) == 3  # the skew is inclusive
    assert nearest_index([], 0, 10) is None


def test_ring_frame_near_decodes_nothing_and_counts(decode_calls):
    stats = CameraStats()
    ring = FrameRing(4, stats)
    frames = [Frame(jpeg(k), T0 + k * 33 * MS + 40 * MS, T0 + k * 33 * MS, k) for k in range(6)]
    for frame in frames:
        ring.push(frame)
    assert ring.frames() == frames[2:]
    assert (stats.overwritten, stats.dropped) == (2, 2)
    assert ring.frame_near(T0 + 100 * MS, 10 * MS) is frames[3]  # 99 ms: 1 ms away
    assert ring.frame_near(T0 + 10 * MS, 10 * MS) is None  # frame 0 was overwritten
    assert stats.near_misses == 1
    ring.push(Frame(jpeg(6), 0, T0 + 6 * 33 * MS, 6))
    ring.push(Frame(jpeg(7), 0, T0 + 7 * 33 * MS, 7))
    # frame 3 had been handed out: overwritten but not dropped
    assert (stats.overwritten, stats.dropped) == (4, 3)
    assert decode_calls == []
    frames[3].decode(2)  # what the counter sees: a frame's decode
    assert len(decode_calls) == 1


def test_replay_frame_near_reads_forward_as_scans_ask(tmp_path, decode_calls):
    frames = [Frame(jpeg(k), T0 + k * 100 * MS, T0 + k * 100 * MS, k) for k in range(30)]
    with FolderWriter(tmp_path / "f") as writer:
        for frame in frames:
            writer.write(frame)
    source = open_camera_source(tmp_path / "f")
    scan_times = [T0 + k * 250 * MS for k in range(12)]  # a 4 Hz "LiDAR"
    picked = [source.frame_near(t, 30 * MS) for t in scan_times]
    expected = [frames[round(k * 2.5 - 0.01)] for k in range(12)]
    # k * 250 ms falls on a frame (even k) or midway between two (odd k: 50 ms > 30 ms)
    assert [p.sequence if p else None for p in picked] == [
        e.sequence if k % 2 == 0 else None for k, e in enumerate(expected)
    ]
    assert source.stats.near_misses == 6
    # Read only up to the first frame past the last scan's window (2780 ms): frame 28.
    assert source.stats.frames == 29 and source.ring.frames()[-1].sequence == 28
    assert decode_calls == []
    shutil.rmtree(tmp_path / "f")


def test_interval_summary():
    times = [0, 100, 200, 400, 500]  # one frame missing
    facts = interval_summary([t * MS for t in times])
    assert facts["fps_median"] == pytest.approx(10.0)
    assert facts["fps_mean"] == pytest.approx(8.0)
    assert facts["max_interval_ms"] == pytest.approx(200.0)
    assert interval_summary([5])["fps_mean"] is None
