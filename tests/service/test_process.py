"""`treetraits run` as a subprocess on loopback, the way systemd runs it.

A simulated survey is streamed live at its real rate by `sim.player.RecordingPlayer`:
LiDAR over UDP to 127.0.0.1, GNSS and the Jackal MCU over pseudo-terminals, the camera
as an MJPG video file. A bound AF_UNIX datagram socket stands in for systemd's
NOTIFY_SOCKET and receives READY, STATUS, WATCHDOG and STOPPING. Checked: the outputs,
SIGTERM within 5 s, a GNSS pty closed mid-run, a wheel port that appears mid-survey, a
loop behind its sensors, kill -9 and a restart, a foreign sender, a full disk
(RLIMIT_FSIZE) and a config error.
"""

from __future__ import annotations

import csv
import json
import re
import resource
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.helpers.net import free_udp_port
from tests.helpers.paths import REPO
from tests.helpers.service import START_S, Service
from tests.helpers.surveys import twin_survey
from treetraits.drivers import recording as rec
from treetraits.sim.player import RecordingPlayer, write_camera_video
from treetraits.sim.run import LATENCY_NS, SurveySettings


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    """A 10 s drive past the paper's 2x3 grid, its calibration, field map and video."""
    folder = tmp_path_factory.mktemp("service-survey")
    result = twin_survey(SurveySettings(seed=0, goal=5.0), into=folder)
    with rec.read_recording(result.recording) as recording:
        calibration = recording.metadata.calibration
    (folder / "calibration.json").write_text(json.dumps(calibration))
    write_camera_video(result.recording, folder / "camera.avi")
    return result


def write_config(folder: Path, survey, player: RecordingPlayer | None, **extra: str) -> Path:
    sections = {
        "output": f'dir = "{folder / "out"}"\nexport_every_s = 1.0',
        "pipeline": (
            f'calibration = "{survey.recording.parent / "calibration.json"}"\n'
            f'field_map = "{survey.field_map}"'
        ),
        "lidar": (
            f'bind = "127.0.0.1"\ndata_port = {player.data_port if player else free_udp_port()}'
            f'\ntelemetry_port = 0\nsensor_ip = "127.0.0.1"'
        ),
        "camera": f'device = "{survey.recording.parent / "camera.avi"}"',
        "gnss": f'port = "{player.gnss_device if player else "/dev/null-gnss"}"',
        "wheels": f'port = "{player.wheels_device if player else "/dev/null-wheels"}"',
        "record": f'dir = "{folder / "recordings"}"',
        "service": "status_every_s = 0.5",
    }
    sections.update(extra)
    path = folder / "config.toml"
    path.write_text("\n".join(f"[{k}]\n{v}\n" for k, v in sections.items()))
    return path


def scans_in(status: str) -> int:
    match = re.search(r"\bscans=(\d+)", status)
    return int(match.group(1)) if match else -1


def counter(status: str, name: str) -> int:
    match = re.search(rf"\b{name}=(\d+)", status)
    return int(match.group(1)) if match else -1


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def open_db(path: Path) -> sqlite3.Connection:
    db = sqlite3.connect(path)
    assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    return db


def blast_foreign(port: int, count: int) -> None:
    """Datagrams shaped like LiDAR data, from an address that is not the sensor's."""
    payload = bytes(1200) + b"\0\0\0\0\x37\x22"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.2", 0))
        for i in range(count):
            s.sendto(payload, ("127.0.0.1", port))
            if i % 200 == 199:
                time.sleep(0.005)


def test_live_survey_end_to_end(survey, tmp_path):
    player = RecordingPlayer(survey.recording, data_port=free_udp_port(), telemetry_port=None)
    config = write_config(tmp_path, survey, player)
    service = Service(tmp_path, config, "--record")
    try:
        service.wait_ready()
        player.start()
        blaster = threading.Thread(target=blast_foreign, args=(player.data_port, 5000))
        blaster.start()
        assert player.wait(timeout=survey.duration_s + 30)
        blaster.join()
        last = service.wait_for(lambda s: counter(s, "foreign") >= 4000, 10, "with foreign")
        # Stop once every packet played is read or counted dropped: a datagram still in the
        # socket's buffer when the stop comes is not read (on a loaded machine the last one
        # can be), and that is a stop, not a loss.
        played = player.counters["lidar_sent"]
        last = service.wait_for(
            lambda s: counter(s, "lidar_packets") + max(counter(s, "kernel_drops"), 0) >= played,
            10,
            "with every played packet taken",
        )
        rss = rss_kib(service.proc.pid)
        code, took = service.terminate()
    finally:
        player.close()
        service.close()
    assert code == 0, service.stderr()
    assert took < 5.0
    assert rss < 2_000_000  # kiB: bounded despite the flood (the queues are)

    sent = service.sent()
    assert sent[0].startswith("READY=1\nSTATUS=OK")  # once every source was open
    assert sum(m == "WATCHDOG=1" for m in sent) >= 3
    assert sent[-1].startswith("STOPPING=1\nSTATUS=")
    statuses = service.statuses()
    playing = [s for s in statuses if scans_in(s) > 0 and "silent" not in s]
    assert playing and all(s.startswith("OK ") for s in playing)
    assert "lidar=ok camera=ok gnss=ok wheels=ok" in playing[-1]
    assert counter(last, "dropped_lidar") == 0
    assert "dropped=" not in last  # each drop is named by its queue
    # Every packet played was taken from the socket, but for what the kernel dropped
    # during the foreign flood (its count takes in foreign datagrams too).
    final = statuses[-1]  # sent with STOPPING=1, the receive threads closed
    sent_packets = player.counters["lidar_sent"]
    taken = counter(final, "lidar_packets")
    assert sent_packets - counter(final, "kernel_drops") <= taken <= sent_packets
    assert counter(final, "dropped_lidar") == 0

    run = (tmp_path / "out" / "runs" / "latest").resolve()
    db = open_db(run / "traits.sqlite")
    scans = db.execute("SELECT COUNT(DISTINCT scan_t) FROM observations").fetchone()[0]
    assert scans >= 0.8 * survey.duration_s * 10  # 10 Hz, the first and last ones aside
    facts = dict(db.execute("SELECT key, value FROM run"))
    assert facts["input"] == "live" and facts["world_frame"] == "utm"
    assert facts["end"] == "interrupted (SIGTERM)"
    assert facts["exports"] == "level with the store"
    unprocessed = int(facts["unprocessed_at_stop"])
    assert f'"unprocessed_at_stop": {unprocessed}' in service.stderr()
    assert_exports_level(run)
    rows = (run / "trees.csv").read_text().splitlines()
    assert rows[0].startswith("tree_id,field_id,row,easting,northing")
    matched = [r.split(",")[1] for r in rows[1:] if r.split(",")[1]]
    assert len(matched) >= 4 and len(set(matched)) == len(matched)
    geojson = json.loads((run / "trees.geojson").read_text())
    assert len(geojson["features"]) == len(rows) - 1
    assert any(f["properties"]["ndvi"] for f in geojson["features"])  # the camera was used

    recordings = sorted((tmp_path / "recordings").glob("*.mcap"))
    assert len(recordings) == 1
    with rec.read_recording(recordings[0]) as recording:
        recorded = [(m.topic, m.data, m.publish_time) for m in recording]
        assert not recording.truncated
    topics = [topic for topic, _, _ in recorded]
    # Every packet played is recorded, but those the drain limit left queued at the stop
    # (a loop behind its sensors on a loaded machine: 747 items once here), now counted.
    recorded_lidar = topics.count(rec.LIDAR_PACKETS)
    assert player.counters["lidar_sent"] - unprocessed <= recorded_lidar
    assert recorded_lidar <= player.counters["lidar_sent"]
    assert {rec.CAMERA_JPEG, rec.GNSS_NMEA, rec.WHEELS_JACKAL} <= set(topics)
    # GNSS publish_time is the epoch's UTC from the sentences, as the simulator wrote it
    # (the service's clock is hours off the simulated survey's: receive times would show).
    with rec.read_recording(survey.recording) as source:
        played = [(m.data, m.publish_time) for m in source if m.topic == rec.GNSS_NMEA]
    gnss = [(bytes(data), t) for topic, data, t in recorded if topic == rec.GNSS_NMEA]
    assert len(gnss) > 50 and [d for d, _ in gnss] == [d for d, _ in played[: len(gnss)]]
    # Before the stream's first date (RMC, after GGA in a burst) the host's date is used.
    dated = next(i for i, (data, _) in enumerate(gnss) if data.startswith(b"$GNRMC"))
    assert dated < 4
    day = 86_400 * 10**9
    assert [t % day for _, t in gnss[:dated]] == [t % day for _, t in played[:dated]]
    assert gnss[dated:] == played[dated : len(gnss)]


def assert_exports_level(run: Path) -> None:
    """trees.csv and trees.geojson hold exactly the store's trees: the same found trees
    with the same observation counts, the same number of missing ones."""
    with sqlite3.connect(run / "traits.sqlite") as db:
        stored = db.execute("SELECT tree_id, observations, status FROM trees").fetchall()
    found = sorted((t, n) for t, n, status in stored if status == "found")
    missing = sum(status == "missing" for _, _, status in stored)
    with open(run / "trees.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert (
        sorted((r["tree_id"], int(r["observations"])) for r in rows if r["status"] == "found")
        == found
    )
    assert sum(r["status"] == "missing" for r in rows) == missing
    features = json.loads((run / "trees.geojson").read_text())["features"]
    assert (
        sorted(
            (f["properties"]["tree_id"], f["properties"]["observations"])
            for f in features
            if f["properties"]["status"] == "found"
        )
        == found
    )


def test_ctrl_c_mid_run_exports_the_store_and_marks_the_run_interrupted(survey, tmp_path):
    """Issue 14, case 8: SIGINT while the trees come in. The exports are rewritten from
    the store after the last scan, and the store and the summary say the run was
    interrupted."""
    player = RecordingPlayer(survey.recording, data_port=free_udp_port(), telemetry_port=None)
    config = write_config(tmp_path, survey, player, camera="enabled = false")
    service = Service(tmp_path, config)
    try:
        service.wait_ready()
        player.start()
        service.wait_for(lambda s: counter(s, "trees") >= 2, 60, "with 2 trees")
        service.proc.send_signal(signal.SIGINT)
        code = service.proc.wait(timeout=30)
    finally:
        player.close()
        service.close()
    assert code == 0, service.stderr()
    run = (tmp_path / "out" / "runs" / "latest").resolve()
    facts = dict(open_db(run / "traits.sqlite").execute("SELECT key, value FROM run"))
    assert facts["end"] == "interrupted (SIGINT)"
    assert facts["exports"] == "level with the store"
    assert int(facts["scans"]) > 0
    assert_exports_level(run)
    assert '"end": "interrupted (SIGINT)"' in service.stderr()  # the summary line


def _trees_by_field_id(store: Path) -> dict[str, tuple]:
    with sqlite3.connect(store) as db:
        rows = db.execute(
            "SELECT field_id, tree_id, width_m, height_m, ndvi FROM trees "
            "WHERE status = 'found' AND field_id IS NOT NULL"
        ).fetchall()
    return {field_id: rest for field_id, *rest in rows}


def _within(a: float | None, b: float | None, rel: float) -> bool:
    if a is None or b is None:
        return a is b
    return abs(a - b) <= rel * max(abs(a), abs(b))


def _play_through(service: Service, player: RecordingPlayer, survey, count: str) -> int:
    """The survey played into the service until it has taken every packet played and
    caught up (`_wait_caught_up` by `count`), then SIGTERM: the exit code."""
    service.wait_ready()
    player.start()
    assert player.wait(timeout=survey.duration_s + 30)
    played = player.counters["lidar_sent"]
    service.wait_for(
        lambda s: counter(s, "lidar_packets") + max(counter(s, "kernel_drops"), 0) >= played,
        20,
        "with every played packet taken",
    )
    _wait_caught_up(service, 60, count)
    code, _ = service.terminate()
    return code


def _wait_caught_up(service: Service, timeout: float, count: str) -> None:
    """The loop has handled what its queues held: two new STATUS lines in a row with
    nothing more `count`ed (recorded messages, or committed scans). A loaded machine's
    loop falls seconds behind the packets it took; a SIGTERM then leaves the end of the
    survey unprocessed (the drain limit)."""
    seen = len(service.statuses())
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        counts = [counter(s, count) for s in service.statuses()[seen:]]
        if len(counts) >= 2 and counts[-1] == counts[-2]:
            return
        time.sleep(0.1)
    raise AssertionError(f"the loop did not catch up: {service.statuses()[-3:]}")


def test_live_and_replay_write_the_same_trees(survey, tmp_path):
    """Issue 14, case 9: the twin recording played into `treetraits run --record` (LiDAR
    over UDP, GNSS and wheels over ptys, the camera from a video), then replayed. The
    replay of what the service recorded writes the service's trees (same ids, traits
    within 1 %: they come out equal). The replay of the twin recording itself finds the
    same field-map trees with widths, heights and NDVI within 1 %: serial data is timed
    by the devices' own clocks (the MCU's stamps, the epochs' UTC), not by when a loaded
    host read it, and the video's frames start at the first LiDAR packet's first firing
    (docs/service.md, "Live against replay").

    The player sends the twin's old UTC, so the live host is not on the receiver's UTC
    and places epochs at their arrival less `gnss_latency_s`: set to the twin receiver's
    latency, as docs/localization.md asks of a real one (the default 50 ms put every fix
    10 ms, 5 mm, off the twin's)."""
    player = RecordingPlayer(survey.recording, data_port=free_udp_port(), telemetry_port=None)
    latency = f"gnss_latency_s = {LATENCY_NS['gnss'] / 1e9}"
    # Every scan mapped, however far a loaded machine's loop falls behind: a shed scan
    # is a difference from the replay by design (docs/service.md).
    never_shed = "status_every_s = 0.5\nmax_backlog_s = 0"
    config = write_config(tmp_path, survey, player, localization=latency, service=never_shed)
    service = Service(tmp_path, config, "--record")
    try:
        code = _play_through(service, player, survey, "recorded")
    finally:
        player.close()
        service.close()
    assert code == 0, service.stderr()
    live = _trees_by_field_id((tmp_path / "out" / "runs" / "latest" / "traits.sqlite").resolve())
    assert len(live) >= 4

    (recording,) = sorted((tmp_path / "recordings").glob("*.mcap"))
    for name, source in (("of-the-live-run", recording), ("of-the-twin", survey.recording)):
        out = tmp_path / f"replay-{name}"
        result = subprocess.run(
            [
                sys.executable,
                "-m",
                "treetraits",
                "replay",
                str(source),
                "--out",
                str(out),
                "--config",
                str(config),
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert result.returncode == 0, result.stderr
        replayed = _trees_by_field_id(out / "traits.sqlite")
        assert set(replayed) == set(live), name
        if name != "of-the-live-run":
            for field_id, (_, width, height, ndvi) in replayed.items():
                _, live_width, live_height, live_ndvi = live[field_id]
                assert _within(width, live_width, 0.01), (field_id, width, live_width)
                assert _within(height, live_height, 0.01), (field_id, height, live_height)
                assert _within(ndvi, live_ndvi, 0.01), (field_id, ndvi, live_ndvi)
            continue
        # The very messages the service processed, in its order: the same trees.
        for field_id, (tree_id, width, height, ndvi) in replayed.items():
            live_id, live_width, live_height, live_ndvi = live[field_id]
            assert tree_id == live_id
            assert _within(width, live_width, 0.01), (field_id, width, live_width)
            assert _within(height, live_height, 0.01), (field_id, height, live_height)
            assert _within(ndvi, live_ndvi, 0.01), (field_id, ndvi, live_ndvi)


def test_a_wheel_link_that_comes_late_maps_every_scan(survey, tmp_path):
    """The survey starts before the Jackal MCU's port exists: the service starts with the
    wheels reopening, the port appears 3 s into the survey (its first MCU frames unheard,
    as in the slow bench run of docs/performance.md), and every scan is still mapped and
    committed, in UTM, with the field-map trees found."""
    player = RecordingPlayer(survey.recording, data_port=free_udp_port(), telemetry_port=None)
    late_port = tmp_path / "jackal-late"
    config = write_config(tmp_path, survey, player, wheels=f'port = "{late_port}"')
    service = Service(tmp_path, config)
    appear = threading.Timer(3.0, lambda: late_port.symlink_to(player.wheels_device))
    try:
        service.wait_ready()
        appear.start()  # as the survey starts
        code = _play_through(service, player, survey, "scans")
        appear.join()
    finally:
        player.close()
        service.close()
    assert code == 0, service.stderr()
    assert player.counters["wheels_unheard"] > 0  # the MCU's first frames went unheard
    statuses = service.statuses()
    assert any("wheels=disconnected" in s and scans_in(s) > 0 for s in statuses), statuses[:5]
    assert "wheels=ok" in statuses[-1]
    run = (tmp_path / "out" / "runs" / "latest").resolve()
    db = open_db(run / "traits.sqlite")
    scans = db.execute("SELECT COUNT(DISTINCT scan_t) FROM observations").fetchone()[0]
    assert scans >= 0.8 * survey.duration_s * 10  # 10 Hz, the first and last ones aside
    assert dict(db.execute("SELECT key, value FROM run"))["world_frame"] == "utm"
    assert len(_trees_by_field_id(run / "traits.sqlite")) >= 4


def test_a_loop_behind_its_sensors_sheds_scans_not_packets(survey, tmp_path):
    """`service.max_backlog_s` far below what a loop can hold to (1 ms: it gathers 10 ms
    of items per wake-up) stands for a computer too slow for every scan: the scans ready
    while it is behind are not mapped, counted in STATUS (`scans_shed`, DEGRADED) and in
    the store's run facts, and no packet is dropped."""
    player = RecordingPlayer(survey.recording, data_port=free_udp_port(), telemetry_port=None)
    config = write_config(
        tmp_path, survey, player, service="status_every_s = 0.5\nmax_backlog_s = 0.001"
    )
    service = Service(tmp_path, config)
    try:
        code = _play_through(service, player, survey, "scans")
    finally:
        player.close()
        service.close()
    assert code == 0, service.stderr()
    statuses = service.statuses()
    assert any(s.startswith("DEGRADED behind its sensors: ") for s in statuses), statuses[-3:]
    final = statuses[-1]
    assert counter(final, "scans_shed") > 0.5 * survey.duration_s * 10
    assert counter(final, "dropped_lidar") == 0
    run = (tmp_path / "out" / "runs" / "latest").resolve()
    facts = dict(open_db(run / "traits.sqlite").execute("SELECT key, value FROM run"))
    # The shutdown's last scans come after the STOPPING status; its summary has them all.
    assert int(facts["scans_shed"]) >= counter(final, "scans_shed")
    assert f'"scans_shed": {facts["scans_shed"]}' in service.stderr()


def test_gnss_unplugged_then_kill_9_and_restart(survey, tmp_path):
    player = RecordingPlayer(survey.recording, data_port=free_udp_port(), telemetry_port=None)
    config = write_config(tmp_path, survey, player, camera="enabled = false")
    service = Service(tmp_path, config)
    try:
        service.wait_ready()
        player.start()
        before = service.wait_for(lambda s: scans_in(s) >= 20, 30, "with 20 scans")
        assert "camera" not in before  # disabled: not reported
        player.close_gnss()
        degraded = service.wait_for(
            lambda s: s.startswith("DEGRADED") and "gnss disconnected" in s, 10, "gnss gone"
        )
        assert "lidar=ok" in degraded and "gnss=disconnected" in degraded
        # The rest goes on: LiDAR scans are still processed without the receiver.
        service.wait_for(
            lambda s: "gnss disconnected" in s and scans_in(s) >= scans_in(degraded) + 10,
            10,
            "with scans going on",
        )
        killed_run = (tmp_path / "out" / "runs" / "latest").resolve()
        service.proc.send_signal(signal.SIGKILL)
        assert service.proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        player.close()
        service.close()

    db = open_db(killed_run / "traits.sqlite")  # opens clean: WAL recovered
    scans = db.execute("SELECT COUNT(DISTINCT scan_t) FROM observations").fetchone()[0]
    assert scans >= 20
    # Killed outright: it never said how it ended, so it does not look complete.
    assert dict(db.execute("SELECT key, value FROM run"))["end"] == "running"
    db.close()

    # The closed pty's /dev/pts number may already belong to another program's pty: the
    # restart names a receiver port that is surely not there.
    gone = tmp_path / "unplugged-gnss"
    config.write_text(config.read_text().replace(player.gnss_device, str(gone)))
    restarted = Service(tmp_path, config)
    try:
        restarted.wait_ready()
        restarted.wait_for(lambda s: "gnss disconnected" in s, 10, "naming the missing gnss")
        code, took = restarted.terminate()
    finally:
        restarted.close()
    assert code == 0 and took < 5.0, restarted.stderr()
    new_run = (tmp_path / "out" / "runs" / "latest").resolve()
    assert new_run != killed_run and new_run.parent == killed_run.parent
    open_db(killed_run / "traits.sqlite")
    open_db(new_run / "traits.sqlite")


def test_a_full_disk_degrades_without_corrupting_the_store(survey, tmp_path):
    """A tiny file size limit stands in for a full disk: with SIGXFSZ ignored, a write past
    RLIMIT_FSIZE fails with EFBIG, as a write to a full disk fails with ENOSPC."""
    limit = 256 * 1024

    def small_files() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    player = RecordingPlayer(survey.recording, data_port=free_udp_port(), telemetry_port=None)
    config = write_config(tmp_path, survey, player, camera="enabled = false")
    service = Service(tmp_path, config, preexec_fn=small_files)
    try:
        service.wait_ready()
        player.start()
        full = service.wait_for(
            lambda s: "traits.sqlite: scan not committed" in s, survey.duration_s + 20, "full"
        )
        assert full.startswith("DEGRADED") and "lidar=ok" in full
        code, took = service.terminate()
    finally:
        player.close()
        service.close()
    assert code == 0 and took < 5.0, service.stderr()
    assert "scan not committed" in service.stderr()  # the log names the file and the error
    run = (tmp_path / "out" / "runs" / "latest").resolve()
    db = open_db(run / "traits.sqlite")
    assert db.execute("SELECT COUNT(DISTINCT scan_t) FROM observations").fetchone()[0] > 0
    assert all(p.stat().st_size <= limit for p in run.iterdir())


def test_a_config_error_names_the_key_and_exits_2(survey, tmp_path):
    config = write_config(tmp_path, survey, None, lidar="data_port = 70000")
    result = subprocess.run(
        [sys.executable, "-m", "treetraits", "run", "--config", str(config)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=START_S,
    )
    assert result.returncode == 2
    assert "lidar.data_port must be a port in 1..65535, got 70000" in result.stderr
    assert "Traceback" not in result.stderr
