"""RotatingRecorder: rotation, crash safety (real kill -9, truncation at every chunk
boundary), disk full (RLIMIT_FSIZE in a subprocess), and RecordingWriter's streaming mode.

Disk full is simulated with RLIMIT_FSIZE in a child process: with SIGXFSZ ignored, a write
past the limit fails with EFBIG, as a full disk fails with ENOSPC, and needs no root or tmpfs.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from tests.helpers.paths import REPO
from treetraits.drivers.recording import (
    CAMERA_JPEG,
    FIELD_MAP_NAME,
    GNSS_NMEA,
    LIDAR_PACKETS,
    RecordingWriter,
    read_recording,
)
from treetraits.drivers.recording.rotation import RecordingError, RotatingRecorder, rotated_path
from treetraits.errors import EXIT_OUTPUT_EXISTS, TreetraitsError

CALIBRATION = {"format_version": "1", "T_base_lidar": [[1, 0, 0, 0.5]]}
FIELD_MAP = b'{"type": "FeatureCollection", "features": []}'
T0 = 1_700_000_000_000_000_000


def _messages(count: int, seed: int = 0) -> list[tuple[str, bytes, int]]:
    """LiDAR-like incompressible packets with GNSS sentences and a JPEG-sized blob between."""
    rng = random.Random(seed)
    out = []
    for i in range(count):
        if i % 50 == 49:
            topic, data = CAMERA_JPEG, rng.randbytes(20_000)
        elif i % 10 == 9:
            topic, data = GNSS_NMEA, b"$GPGGA,120000.00,4807.038,N,01131.000,E,1,08,0.9*47\r\n"
        else:
            topic, data = LIDAR_PACKETS, rng.randbytes(1206)
        out.append((topic, data, T0 + i * 1_000_000))
    return out


def _read_all(path: Path):
    reader = read_recording(path)
    messages = [(m.topic, m.data, m.log_time) for m in reader]
    return reader, messages


def test_rotation_files_each_complete_with_calibration_and_field_map(tmp_path):
    first = tmp_path / "REC.mcap"
    written = _messages(1200)
    with RotatingRecorder(
        first,
        max_bytes=300_000,
        chunk_bytes=32_000,
        fsync_every_s=60.0,
        calibration=CALIBRATION,
        field_map=FIELD_MAP,
    ) as recorder:
        for topic, data, t in written:
            recorder.write(topic, data, t, t)
    files = recorder.files
    # ~1.9 MB of incompressible payload in files of ~300 kB
    assert len(files) >= 5
    assert files[:3] == [tmp_path / "REC.mcap", tmp_path / "REC.1.mcap", tmp_path / "REC.2.mcap"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in files)
    assert recorder.bytes_written == sum(p.stat().st_size for p in files)
    recovered = []
    for path in files:
        reader, messages = _read_all(path)
        assert not reader.truncated, path
        assert reader.metadata is not None and reader.metadata.calibration == CALIBRATION
        assert reader.attachments[FIELD_MAP_NAME].data == FIELD_MAP
        recovered += messages
        # rotation happens at the first chunk boundary past max_bytes: one chunk plus
        # the summary over at most
        assert path.stat().st_size < 300_000 + 32_000 + 22_000 + 40_000, path
    assert recovered == written
    for path in files[:-1]:
        assert path.stat().st_size >= 300_000


def test_rotated_names():
    assert rotated_path(Path("/d/REC.mcap"), 0) == Path("/d/REC.mcap")
    assert rotated_path(Path("/d/REC.mcap"), 2) == Path("/d/REC.2.mcap")
    assert rotated_path(Path("/d/run.day1.mcap"), 1) == Path("/d/run.day1.1.mcap")
    assert rotated_path(Path("/d/REC"), 3) == Path("/d/REC.3")


def test_refuses_to_overwrite_or_mix_with_an_earlier_rotation(tmp_path):
    first = tmp_path / "REC.mcap"
    first.write_bytes(b"old")
    with pytest.raises(RecordingError, match="already exists") as refused:
        RotatingRecorder(first, max_bytes=10_000, chunk_bytes=1000, fsync_every_s=1.0)
    assert refused.value.exit_code == EXIT_OUTPUT_EXISTS  # `record` exits 4 (docs/cli.md)
    assert first.read_bytes() == b"old"
    first.unlink()
    (tmp_path / "REC.3.mcap").write_bytes(b"old")
    with pytest.raises(RecordingError, match=r"REC\.3\.mcap of an earlier recording"):
        RotatingRecorder(first, max_bytes=10_000, chunk_bytes=1000, fsync_every_s=1.0)
    assert not first.exists()
    with pytest.raises(RecordingError, match="does not exist"):
        RotatingRecorder(
            tmp_path / "nope" / "REC.mcap", max_bytes=10_000, chunk_bytes=1000, fsync_every_s=1.0
        )
    assert issubclass(RecordingError, TreetraitsError)


def test_closed_recorder_refuses_writes_and_close_is_idempotent(tmp_path):
    recorder = RotatingRecorder(
        tmp_path / "REC.mcap", max_bytes=10_000, chunk_bytes=1000, fsync_every_s=1.0
    )
    recorder.write(GNSS_NMEA, b"$GPZDA*00\r\n", T0, T0)
    recorder.close()
    recorder.close()
    with pytest.raises(RecordingError, match="closed"):
        recorder.write(GNSS_NMEA, b"$GPZDA*00\r\n", T0, T0)
    reader, messages = _read_all(tmp_path / "REC.mcap")
    assert messages == [(GNSS_NMEA, b"$GPZDA*00\r\n", T0)] and not reader.truncated


def test_truncation_at_any_offset_replays_every_complete_chunk(tmp_path):
    path = tmp_path / "REC.mcap"
    written = _messages(600, seed=1)
    with RotatingRecorder(path, max_bytes=10**9, chunk_bytes=16_000, fsync_every_s=60) as rec:
        for topic, data, t in written:
            rec.write(topic, data, t, t)
    blob = path.read_bytes()
    # Independent of our reader: the chunk layout from mcap's own indexed reader.
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) > 30
    rng = random.Random(2)
    offsets = [rng.randrange(len(blob)) for _ in range(40)]
    offsets += [c.chunk_start_offset + c.chunk_length for c in chunks[::7]]  # exact ends
    offsets += [c.chunk_start_offset + c.chunk_length - 1 for c in chunks[::9]]  # one short
    cut = tmp_path / "cut.mcap"
    for offset in offsets:
        cut.write_bytes(blob[:offset])
        complete = [c for c in chunks if c.chunk_start_offset + c.chunk_length <= offset]
        last_time = complete[-1].message_end_time if complete else -1
        expected = [m for m in written if m[2] <= last_time]
        reader, messages = _read_all(cut)
        assert messages == expected, offset
        assert reader.metadata is not None and reader.metadata.calibration == {}
        assert reader.truncated


_KILLED_WRITER = """
import sys, time
from pathlib import Path
from treetraits.drivers.recording.rotation import RotatingRecorder
rec = RotatingRecorder(Path(sys.argv[1]), max_bytes=10**9, chunk_bytes=10**8,
                       fsync_every_s=float(sys.argv[2]), calibration={"k": 1})
i = 0
while True:
    t = time.time_ns()
    rec.write("/gnss/nmea", b"$GPGGA,%d*00\\r\\n" % i, t, t)
    print(i, t, flush=True)
    i += 1
    time.sleep(0.01)
"""


def test_kill_9_loses_about_the_open_chunk_only(tmp_path):
    """GNSS alone (slow, tiny messages): the chunk never fills, the age limit writes it."""
    path = tmp_path / "REC.mcap"
    age = 0.5
    child = subprocess.Popen(
        [sys.executable, "-c", _KILLED_WRITER, str(path), str(age)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            line = child.stdout.readline()
            assert line, "writer died"
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
        lines = [line, *child.stdout.read().splitlines()]
    finally:
        child.kill()
        child.stdout.close()
    last_seq, last_time = (int(x) for x in lines[-1].split())
    reader, messages = _read_all(path)
    assert reader.truncated and reader.metadata.calibration == {"k": 1}
    assert [data for _, data, _ in messages] == [
        b"$GPGGA,%d*00\r\n" % i for i in range(len(messages))
    ]
    assert len(messages) > 50  # ~3 s at 100 Hz, all but the open chunk
    lost_s = (last_time - messages[-1][2]) / 1e9
    # The open chunk is at most `age` old, plus scheduling noise on a busy machine.
    assert 0 <= lost_s < age + 0.75, (lost_s, last_seq, len(messages))


def test_streaming_writer_hands_old_chunks_to_the_os_while_open(tmp_path):
    """A reader of the file being written sees everything but the last `age` seconds."""
    path = tmp_path / "REC.mcap"
    writer = RecordingWriter(path, chunk_size=10**8, max_chunk_age_s=0.2, fsync_every_s=1.0)
    start = time.monotonic()
    i = 0
    while time.monotonic() - start < 1.0:
        writer.write(GNSS_NMEA, b"$%d\r\n" % i, T0 + i)
        i += 1
        time.sleep(0.01)
    seen = [m.data for m in read_recording(path)]
    assert 0 < len(seen) < i
    assert seen == [b"$%d\r\n" % k for k in range(len(seen))]
    # a chunk is closed at the first write after it is 0.2 s old: ~20 writes at 100 Hz
    assert i - len(seen) <= 60
    writer.flush()
    assert [m.data for m in read_recording(path)] == [b"$%d\r\n" % k for k in range(i)]
    writer.close()
    assert writer.bytes_written == path.stat().st_size


def test_default_writer_keeps_small_chunks_in_memory(tmp_path):
    """Backward compatibility: without the streaming options nothing is flushed early."""
    path = tmp_path / "REC.mcap"
    writer = RecordingWriter(path)
    for i in range(100):
        writer.write(GNSS_NMEA, b"$%d\r\n" % i, T0 + i)
    assert list(read_recording(path)) == []
    writer.close()
    assert len(list(read_recording(path))) == 100


_DISK_FULL_WRITER = """
import os, random, resource, signal, sys
from pathlib import Path
from treetraits.drivers.recording.rotation import RecordingError, RotatingRecorder
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit -> EFBIG, not death
rng = random.Random(0)
rec = RotatingRecorder(Path(sys.argv[1]), max_bytes=200_000, chunk_bytes=20_000,
                       fsync_every_s=60.0, calibration={"cal": "x"})
i = 0
limited = False
try:
    while i < 100_000:  # ~120 MB: a bound in case the limit never bites
        if len(rec.files) == 3 and not limited:
            limited = True
            # the disk "fills" during the third file: no write may pass 100 kB more
            size = rec.files[-1].stat().st_size
            resource.setrlimit(resource.RLIMIT_FSIZE, (size + 100_000, resource.RLIM_INFINITY))
        rec.write("/lidar/packets", rng.randbytes(1206), 10**18 + i, 10**18 + i)
        i += 1
except RecordingError as error:
    print("ERROR", error)
    try:
        rec.write("/lidar/packets", b"x", 1, 1)
    except RecordingError as again:
        print("AGAIN", again)
    rec.close()
    print("WRITTEN", i)
    print("FILES", *rec.files)
"""


def test_disk_full_raises_recording_error_and_keeps_files_readable(tmp_path):
    first = tmp_path / "REC.mcap"
    result = subprocess.run(
        [sys.executable, "-c", _DISK_FULL_WRITER, str(first)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    out = dict(line.split(" ", 1) for line in result.stdout.splitlines())
    assert "REC.2.mcap" in out["ERROR"] and "File too large" in out["ERROR"]
    assert out["AGAIN"] == out["ERROR"]
    files = [Path(p) for p in out["FILES"].split()]
    assert files == [first, tmp_path / "REC.1.mcap", tmp_path / "REC.2.mcap"]
    written = int(out["WRITTEN"])
    times = []
    for path in files:
        reader, messages = _read_all(path)
        assert reader.metadata.calibration == {"cal": "x"}
        assert reader.truncated == (path == files[-1])
        times += [t for _, _, t in messages]
    # every message up to the last complete chunk of the last file, in order, no gap
    assert times == [10**18 + k for k in range(len(times))]
    # lost: only the chunk whose write failed (at most ~20 kB of 1.2 kB packets)
    assert 0 <= written - len(times) <= 2 * (20_000 // 1206 + 2)


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="positive"):
        RotatingRecorder(tmp_path / "a.mcap", max_bytes=0, chunk_bytes=1, fsync_every_s=1)
    with pytest.raises(ValueError, match="fsync_every_s"):
        RotatingRecorder(tmp_path / "a.mcap", max_bytes=10, chunk_bytes=1, fsync_every_s=0)
    with pytest.raises(ValueError, match="max_chunk_age_s"):
        RecordingWriter(tmp_path / "b.mcap", max_chunk_age_s=-1)
    assert not (tmp_path / "b.mcap").exists()
    assert os.listdir(tmp_path) == []
