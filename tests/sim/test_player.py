"""The recording player against the real receivers: UDP sockets on loopback, pyserial on the
pty slaves (`SerialSource` for GNSS, `JackalSession` for the MCU), OpenCV for the video.

Expected values come from the recording itself, read back with `read_recording` and the
drivers' own decoders (`decode_stream`), never from the player.
"""

from __future__ import annotations

import socket
import threading
import time

import cv2
import numpy as np
import pytest

from tests.helpers.surveys import twin_survey
from treetraits.drivers import recording as rec
from treetraits.drivers.camera.replay import VideoFileSource
from treetraits.drivers.gnss.sources import SerialSource
from treetraits.drivers.records import WheelSample
from treetraits.drivers.velodyne.sources import UdpSource
from treetraits.errors import SourceError
from treetraits.firmware_bridge.jackal import rosserial as rs
from treetraits.firmware_bridge.jackal.session import JackalSession, decode_stream
from treetraits.sim.player import RecordingPlayer, write_camera_video
from treetraits.sim.run import SurveySettings

SPEED = 2.0


@pytest.fixture(scope="session")
def short_survey(tmp_path_factory):
    """A 3 s simulated survey: one tree row, 1.5 m ahead."""
    return twin_survey(SurveySettings(goal=1.5, rows=1, seed=3))


def recorded(path, topic) -> list[rec.RecordedMessage]:
    return sorted(rec.read_recording(path, [topic]), key=lambda m: m.log_time)


def udp_socket(silence_s: float = 1.0) -> socket.socket:
    """A loopback receiver; `receive_all` on it ends after `silence_s` without a datagram."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(silence_s)
    return sock


def collect(target, out: list) -> threading.Thread:
    thread = threading.Thread(target=lambda: out.extend(target()), daemon=True)
    thread.start()
    return thread


def receive_all(sock: socket.socket) -> list[tuple[float, tuple[str, int], bytes]]:
    """Datagrams until the socket's timeout passes in silence: (arrival, sender, payload)."""
    got = []
    while True:
        try:
            data, sender = sock.recvfrom(4096)
        except TimeoutError:
            return got
        got.append((time.monotonic(), sender, data))


@pytest.fixture(scope="module")
def played(short_survey):
    """The short survey played once at 2x to a UDP socket, a GNSS reader and a Jackal
    session, all opened before the player starts."""
    # The project's LiDAR receiver: each packet stamped by the kernel as it arrives
    # (SO_TIMESTAMPNS), so a reading thread held up by the GIL or a loaded machine does
    # not move the times the player is judged by. Only loopback's datagrams are taken.
    lidar = UdpSource("127.0.0.1", 0, telemetry_port=None, sensor_ip="127.0.0.1")
    player = RecordingPlayer(
        short_survey.recording,
        data_port=lidar.ports[0],
        telemetry_port=None,
        speed=SPEED,
    )
    gnss = SerialSource(player.gnss_device)
    session = JackalSession(player.wheels_device).start()
    packets: list = []
    sentences: list = []
    items: list = []
    threads = [
        collect(lambda: iter(lambda: lidar.read(timeout=1.0), None), packets),
        collect(lambda: iter(gnss), sentences),
        collect(lambda: iter(session), items),
    ]
    started = time.monotonic()
    player.start()
    finished = player.wait(timeout=30)
    played_s = time.monotonic() - started
    time.sleep(0.3)  # the last sentences and frames reach their readers
    counters = player.counters
    gnss.close()
    session.close()
    player.close()
    for thread in threads:
        thread.join(timeout=5)
    lidar.close()
    yield {
        "finished": finished,
        "played_s": played_s,
        "started": started,
        "packets": packets,
        "lidar": lidar,
        "sentences": sentences,
        "items": items,
        "counters": counters,
        "session": session.counters(),
        "player": player,
    }


def test_plays_out_at_the_recorded_pace(played, short_survey):
    assert played["finished"]
    expected = short_survey.duration_s / SPEED
    assert played["played_s"] == pytest.approx(expected, abs=0.5)


def test_lidar_packets_arrive_in_order_from_loopback_at_their_times(played, short_survey):
    messages = recorded(short_survey.recording, rec.LIDAR_PACKETS)
    packets, lidar = played["packets"], played["lidar"]
    assert [p.payload for p in packets] == [m.data for m in messages]
    assert lidar.stats.foreign == 0 and lidar.kernel_timestamps  # loopback's, kernel-stamped
    # Each packet within 0.25 s of its recorded time (scaled by the speed) after the first.
    t0, first = messages[0].log_time, packets[0].t_host
    offsets = [
        (p.t_host - first) / 1e9 - (m.log_time - t0) / 1e9 / SPEED
        for p, m in zip(packets, messages, strict=True)
    ]
    assert max(abs(o) for o in offsets) < 0.25
    # And not all at once: the second half arrives a good while after the first.
    half = (packets[-1].t_host - packets[len(packets) // 2].t_host) / 1e9
    assert half > 0.3 * short_survey.duration_s / SPEED
    counters = played["counters"]
    assert counters["lidar_sent"] == len(messages)
    assert counters["lidar_bytes"] == sum(len(m.data) for m in messages)
    assert counters["lidar_late_median_ms"] < 50


def test_nmea_sentences_arrive_on_the_slave_as_recorded(played, short_survey):
    messages = recorded(short_survey.recording, rec.GNSS_NMEA)
    assert [s.raw for s in played["sentences"]] == [m.data for m in messages]
    assert played["counters"]["gnss_sent"] == len(messages)
    assert played["counters"]["gnss_unheard"] == 0


def test_a_jackal_session_on_the_wheels_slave_gets_every_wheel_sample(played, short_survey):
    messages = recorded(short_survey.recording, rec.WHEELS_JACKAL)
    truth = [
        (r.left, r.right)
        for r in decode_stream((m.log_time, m.data) for m in messages)
        if isinstance(r, WheelSample)
    ]
    samples = [i for i in played["items"] if isinstance(i, WheelSample)]
    assert len(truth) > 100
    assert [(s.left, s.right) for s in samples] == truth
    # Stamped on arrival, spread over the play: not a burst.
    span_s = (samples[-1].t_host - samples[0].t_host) / 1e9
    assert span_s == pytest.approx(short_survey.duration_s / SPEED, abs=0.5)
    session = played["session"]
    assert session["topic_requests"] >= 1 and session["negotiation"] >= 1
    assert session["frame_skipped_bytes"] == 0 and session["malformed"] == 0
    assert played["counters"]["mcu_time_replies"] >= 1  # the host answered our time request


def test_telemetry_goes_to_its_own_port(tmp_path):
    path = tmp_path / "lidar.mcap"
    data_payloads = [bytes([i]) * 1206 for i in range(20)]
    tel_payloads = [bytes([100 + i]) * 512 for i in range(2)]
    with rec.RecordingWriter(path) as writer:
        for i, payload in enumerate(data_payloads):
            writer.write(rec.LIDAR_PACKETS, payload, log_time=10**18 + i * 1_000_000)
            if i % 10 == 5:
                writer.write(
                    rec.LIDAR_TELEMETRY, tel_payloads[i // 10], log_time=10**18 + i * 10**6
                )
    data, tel = udp_socket(0.3), udp_socket(0.3)
    with RecordingPlayer(
        path,
        data_port=data.getsockname()[1],
        telemetry_port=tel.getsockname()[1],
        gnss_pty=False,
        wheels_pty=False,
    ) as player:
        assert player.gnss_device is None and player.wheels_device is None
        player.start()
        assert player.wait(timeout=5)
        got_data = [p for _, _, p in receive_all(data)]
        got_tel = [p for _, _, p in receive_all(tel)]
        counters = player.counters
    data.close()
    tel.close()
    assert got_data == data_payloads and got_tel == tel_payloads
    assert counters["lidar_sent"] == 20 and counters["telemetry_sent"] == 2


def test_close_gnss_is_an_unplug_for_the_reader(short_survey):
    with RecordingPlayer(
        short_survey.recording, data_port=None, telemetry_port=None, wheels_pty=False
    ) as player:
        gnss = SerialSource(player.gnss_device, reconnect=False)
        player.start()
        first = gnss.read(timeout=3)
        assert first is not None
        player.close_gnss()
        deadline = time.monotonic() + 3
        while gnss.read(timeout=0.5) is not None and time.monotonic() < deadline:
            pass  # what was already on the way
        assert gnss.stats.disconnects == 1
        assert gnss.closed  # reconnect=False: the unplug ended the source
        time.sleep(0.3)
        assert player.counters["gnss_unheard"] > 0  # due after the unplug: nobody heard them
        gnss.close()


def test_sentences_due_while_the_port_is_closed_are_lost_not_queued(short_survey):
    messages = recorded(short_survey.recording, rec.GNSS_NMEA)
    with RecordingPlayer(
        short_survey.recording, data_port=None, telemetry_port=None, wheels_pty=False
    ) as player:
        player.start()
        time.sleep(1.0)
        gnss = SerialSource(player.gnss_device)
        first = gnss.read(timeout=2)
        # Counted while the port is still open: once closed, sentences go unheard again.
        unheard = player.counters["gnss_unheard"]
        gnss.close()
    assert first is not None
    index = [m.data for m in messages].index(first.raw)
    assert index == unheard > 10  # the first sentence read is the first one due after open


def test_a_wheels_recording_without_topic_info_is_refused(tmp_path):
    path = tmp_path / "no_handshake.mcap"
    with rec.RecordingWriter(path) as writer:
        writer.write(rec.WHEELS_JACKAL, rs.encode_frame(137, b"\x00" * 40), log_time=10**18)
    with pytest.raises(SourceError, match="TopicInfo"):
        RecordingPlayer(path, data_port=None, telemetry_port=None, gnss_pty=False)


def test_loop_plays_the_recording_again(short_survey):
    count = len(recorded(short_survey.recording, rec.LIDAR_PACKETS))
    sink = udp_socket()
    with RecordingPlayer(
        short_survey.recording,
        data_port=sink.getsockname()[1],
        telemetry_port=None,
        gnss_pty=False,
        wheels_pty=False,
        speed=10.0,
        loop=True,
    ) as player:
        player.start()
        assert not player.wait(timeout=0.9)  # one pass takes 0.3 s at 10x, but it loops
        counters = player.counters
    sink.close()
    assert counters["loops"] >= 2
    assert counters["lidar_sent"] > 2 * count


def test_camera_video_keeps_the_jpeg_bytes_at_the_recorded_rate(short_survey, tmp_path):
    messages = recorded(short_survey.recording, rec.CAMERA_JPEG)
    out = write_camera_video(short_survey.recording, tmp_path / "camera.avi")
    capture = cv2.VideoCapture(str(out))
    assert capture.isOpened()
    decoded = 0
    while True:
        ok, image = capture.read()
        if not ok:
            break
        decoded += 1
        assert isinstance(image, np.ndarray) and image.shape[2] == 3
    fps = capture.get(cv2.CAP_PROP_FPS)
    capture.release()
    assert decoded == len(messages) == 30
    assert fps == pytest.approx(10.0, rel=0.02)
    with VideoFileSource(out) as source:
        assert source.passthrough
        assert [f.jpeg for f in source] == [m.data for m in messages]


def test_camera_video_needs_camera_frames(tmp_path):
    path = tmp_path / "nocam.mcap"
    with rec.RecordingWriter(path) as writer:
        writer.write(rec.GNSS_NMEA, b"$GPGGA,*00\r\n", log_time=10**18)
    with pytest.raises(SourceError, match="/camera/jpeg"):
        write_camera_video(path, tmp_path / "x.avi")


def test_play_command_sends_the_packets(short_survey, capsys):
    import argparse

    from treetraits.cli.play import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    sink = udp_socket(0.3)
    port = sink.getsockname()[1]
    args = parser.parse_args(
        ["play", str(short_survey.recording), "--lidar", f"127.0.0.1:{port}", "--speed", "6"]
    )
    got: list = []
    receiver = collect(lambda: receive_all(sink), got)  # as they come: rmem_max may be small
    assert args.run(args) == 0
    receiver.join(timeout=5)
    sink.close()
    assert len(got) == short_survey.counts[rec.LIDAR_PACKETS]
    out = capsys.readouterr().out
    assert "gnss: /dev/pts/" in out and f"lidar {len(got)}," in out
    with pytest.raises(SystemExit):
        parser.parse_args(["play", str(short_survey.recording), "--lidar", "nowhere"])


def test_stop_silences_the_streams_but_leaves_the_ports_plugged(short_survey):
    with RecordingPlayer(
        short_survey.recording, data_port=None, telemetry_port=None, wheels_pty=False
    ) as player:
        gnss = SerialSource(player.gnss_device, reconnect=False)
        player.start()
        assert gnss.read(timeout=3) is not None
        player.stop()
        sent = player.counters["gnss_sent"]
        while gnss.read(timeout=0.5) is not None:
            pass  # what was on the way
        time.sleep(0.3)
        assert (
            player.counters["gnss_sent"]
            == sent
            < len(recorded(short_survey.recording, rec.GNSS_NMEA))
        )
        assert gnss.stats.disconnects == 0 and not gnss.closed
        gnss.close()
