"""`treetraits import`: ROS bags to recordings v1, on the real nebula ROS 2 bag and on bags
this file writes with rosbags' own writers from real data (the nebula packets, gpsd's NMEA
logs). Each import is checked against its source byte for byte or fix for fix, and the
recordings go through `treetraits replay` and the NMEA decoders."""

from __future__ import annotations

import csv
import itertools
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin

from tests.helpers.captures import VLP16_DIR, decode_file
from tests.helpers.paths import FIXTURES
from tests.helpers.rosbag import (
    cli,
    header,
    imu_row,
    odometry_row,
    recorded,
    recording_fixes,
    replay,
    stamp,
    typestore,
    write_ros1,
    write_ros2,
)
from tests.helpers.surveys import twin_survey
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import load_calibration
from treetraits.drivers.gnss.epochs import EpochAssembler
from treetraits.drivers.gnss.sentences import decode
from treetraits.drivers.gnss.sources import LogSource, open_gnss_source
from treetraits.drivers.gnss.summary import summarise
from treetraits.drivers.gnss.times import sentence_time
from treetraits.drivers.records import Fix, WheelSample
from treetraits.drivers.rosbag.convert import ImportOptions, import_bags
from treetraits.drivers.rosbag.topics import CITRUSFARM_T_BASE_IMU
from treetraits.drivers.velodyne.sources import open_source
from treetraits.errors import SourceError
from treetraits.firmware_bridge.jackal.records import JackalImu
from treetraits.firmware_bridge.jackal.session import JackalProtocol
from treetraits.sim.run import SurveySettings

NEBULA_BAG = VLP16_DIR / "nebula_vlp16_dual_10hz_bag"
NEBULA_PCAP = VLP16_DIR / "nebula_vlp16_dual_10hz.pcap"
NMEA = FIXTURES / "nmea"


def pcap_packets() -> list:
    return [p for p in open_source(NEBULA_PCAP) if p.is_data]


def velodyne_rows(store, ros1: bool, per_message: int = 150) -> list[tuple]:
    """The nebula pcap's packets as VelodyneScan messages, received 1 ms after their last
    packet (as the ROS driver publishes a scan once its packets are in)."""
    Scan = store.types["velodyne_msgs/msg/VelodyneScan"]
    Packet = store.types["velodyne_msgs/msg/VelodynePacket"]
    packets = pcap_packets()
    rows = []
    for i in range(0, len(packets), per_message):
        group = packets[i : i + per_message]
        msg = Scan(
            header=header(store, group[0].t_host, "velodyne", ros1),
            packets=[
                Packet(
                    stamp=stamp(store, p.t_host),
                    data=np.frombuffer(p.payload, dtype=np.uint8).copy(),
                )
                for p in group
            ],
        )
        rows.append((group[-1].t_host + 1_000_000, "/velodyne_packets", Scan.__msgtype__, msg))
    return rows


def log_sentences(name: str) -> list:
    """Every framed sentence of a real NMEA log, as the splitter finds it."""
    source = LogSource(NMEA / name)
    try:
        return list(source)
    finally:
        source.close()


def log_times(sentences: list, t0: int) -> list[int]:
    """Receive times for a log that has none: each sentence at its epoch's time of day
    past the log's first, from t0, 1 us apart so the order stays."""
    first = last = None
    times = []
    for k, s in enumerate(sentences):
        tod = sentence_time(s.raw).tod_ns
        if tod is not None:
            first = tod if first is None else first
            last = tod
        offset = 0 if last is None else (last - first) % (86_400 * 10**9)
        times.append(t0 + offset + k * 1000)
    return times


def sentence_rows(store, ros1: bool, name: str, t0: int) -> list[tuple]:
    Sentence = store.types["nmea_msgs/msg/Sentence"]
    sentences = log_sentences(name)
    rows = []
    for s, t in zip(sentences, log_times(sentences, t0), strict=True):
        text = s.raw.decode("ascii").rstrip("\r\n")  # as nmea_navsat_driver publishes it
        msg = Sentence(header=header(store, t, "gps", ros1), sentence=text)
        rows.append((t, "/nmea_sentence", Sentence.__msgtype__, msg))
    return rows


def log_fixes(name: str) -> list[Fix]:
    """The log's epochs as our decoders assemble them."""
    assembler = EpochAssembler()
    fixes = []
    for s in log_sentences(name):
        record = decode(s)
        if record is not None and (fix := assembler.push(record)) is not None:
            fixes.append(fix)
    if (fix := assembler.flush()) is not None:
        fixes.append(fix)
    return fixes


# GGA quality -> NavSatStatus.status as a ROS GNSS driver reports it.
STATUS = {0: -1, 1: 0, 2: 1, 4: 2, 5: 2}


def navsatfix_rows(store, ros1: bool, name: str, t0: int) -> tuple[list[tuple], list[Fix]]:
    """A real log's fixes as NavSatFix: ellipsoidal altitude, the GST sigmas as the ENU
    covariance's diagonal (unknown without GST), received 60 ms after the epoch."""
    NavSatFix = store.types["sensor_msgs/msg/NavSatFix"]
    Status = store.types["sensor_msgs/msg/NavSatStatus"]
    fixes = [f for f in log_fixes(name) if f.lat is not None and f.utc_ns is not None]
    first = fixes[0].utc_ns
    rows = []
    for f in fixes:
        known = f.std_lat_m is not None and f.std_lon_m is not None
        diagonal = [f.std_lon_m, f.std_lat_m, f.std_alt_m] if known else [0.0, 0.0, 0.0]
        covariance = np.diag([(v or 0.0) ** 2 for v in diagonal]).ravel()
        msg = NavSatFix(
            header=header(store, f.utc_ns, "gps", ros1),
            status=Status(status=STATUS[f.quality], service=1),
            latitude=f.lat,
            longitude=f.lon,
            altitude=f.altitude_msl_m + (f.geoid_separation_m or 0.0),
            position_covariance=covariance,
            position_covariance_type=2 if known else 0,
        )
        rows.append((t0 + f.utc_ns - first + 60_000_000, "/fix", NavSatFix.__msgtype__, msg))
    return rows, fixes


# --- the real ROS 2 bag ---------------------------------------------------------------


def test_nebula_bag_gives_the_pcaps_603_packets_byte_for_byte(tmp_path):
    out = tmp_path / "nebula.mcap"
    report = import_bags([NEBULA_BAG], out)
    packets = recorded(out, rec.LIDAR_PACKETS)
    source = pcap_packets()
    assert report.channels == {rec.LIDAR_PACKETS: 603}
    assert len(packets) == len(source) == 603
    assert [m.data for m in packets] == [p.payload for p in source]
    # log_time is each packet's own stamp; the pcap holds the same stamps rounded to the us.
    assert all(abs(m.log_time - p.t_host) < 1000 for m, p in zip(packets, source, strict=True))
    assert all(a.log_time <= b.log_time for a, b in itertools.pairwise(packets))
    # publish_time: the packet's ToH (bytes 1200-1203) on the hour of log_time.
    toh_us = int.from_bytes(packets[0].data[1200:1204], "little")
    assert packets[0].publish_time % 3_600_000_000_000 == toh_us * 1000


def test_nebula_bag_decodes_to_the_pcaps_scans(tmp_path):
    out = tmp_path / "nebula.mcap"
    import_bags([NEBULA_BAG], out)
    ours, _ = decode_file(out)
    theirs, _ = decode_file(NEBULA_PCAP)
    assert len(ours) == len(theirs) == 4
    for a, b in zip(ours, theirs, strict=True):
        assert np.array_equal(a.points, b.points)
        assert (a.t_start, a.t_end, a.packets, a.complete, a.lost_packets) == (
            b.t_start,
            b.t_end,
            b.packets,
            b.complete,
            b.lost_packets,
        )
        assert (a.model, a.return_mode) == (b.model, b.return_mode)
        assert abs(a.t_host - b.t_host) < 1000


def test_nebula_bag_through_the_cli_and_replay(tmp_path):
    out = tmp_path / "nebula.mcap"
    result = cli("import", str(NEBULA_BAG), "--out", str(out), "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["channels"] == {rec.LIDAR_PACKETS: 603}
    assert summary["imported"] == ["/velodyne_packets"]
    assert replay(out, tmp_path / "run")["scans"] == 4


# --- bags written here from real data ---------------------------------------------------


def test_ros1_bag_of_packets_and_nmea_sentences(tmp_path):
    store = typestore(ros1=True)
    lidar = velodyne_rows(store, ros1=True)
    t0 = lidar[0][0] - 200_000_000
    gnss = sentence_rows(store, ros1=True, name="ublox-zed-f9p-nmea.nmea", t0=t0)
    bag = write_ros1(tmp_path / "survey.bag", store, lidar + gnss)
    out = tmp_path / "survey.mcap"

    report = import_bags([bag], out)

    assert report.channels == {rec.LIDAR_PACKETS: 603, rec.GNSS_NMEA: len(gnss)}
    assert [m.data for m in recorded(out, rec.LIDAR_PACKETS)] == [p.payload for p in pcap_packets()]
    # Every sentence as the receiver sent it, CRLF included, at the bag's receive time.
    nmea = recorded(out, rec.GNSS_NMEA)
    assert [m.data for m in nmea] == [s.raw for s in log_sentences("ublox-zed-f9p-nmea.nmea")]
    assert [m.log_time for m in nmea] == [row[0] for row in gnss]
    # The recording is in log_time order, as the live recorder writes it.
    times = [m.log_time for m in rec.read_recording(out)]
    assert times == sorted(times)
    # The decoders see the log's epochs: same count, fixes and GGA qualities.
    source = summarise(open_gnss_source(NMEA / "ublox-zed-f9p-nmea.nmea"))
    imported = summarise(open_gnss_source(out))
    assert imported["epochs"] == source["epochs"] == 29
    assert imported["fixes"] == source["fixes"]
    assert imported["gga_quality_histogram"] == source["gga_quality_histogram"]
    # publish_time is each sentence's UTC (the format's GNSS rule), not the bag's clock.
    first_gga = next(m for m in nmea if m.data[3:6] == b"GGA")
    assert first_gga.publish_time == log_fixes("ublox-zed-f9p-nmea.nmea")[0].utc_ns

    # Replay decodes all of it. The log's fixes are of 2019 and the scans of 2023: each
    # epoch is put on the bag's clock by its UTC and the least arrival delay
    # (`serial_clock`), so the fixes come at the scans' times; a single antenna gives no
    # heading in the first 0.4 s, so every scan is counted, none mapped.
    summary = replay(out, tmp_path / "run")
    assert summary["fixes"] == 29
    assert summary["scans"] + summary["scans_without_pose"] + summary["scans_without_heading"] == 4


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_ros2_bag_of_navsatfix_becomes_the_logs_fixes(tmp_path, storage):
    store = typestore(ros1=False)
    lidar = velodyne_rows(store, ros1=False)
    gnss, source = navsatfix_rows(store, False, "ublox-zed-f9r.nmea", lidar[0][0] - 200_000_000)
    bag = write_ros2(tmp_path / "survey", store, lidar + gnss, storage)
    out = tmp_path / "survey.mcap"

    report = import_bags([bag], out)

    assert report.channels[rec.LIDAR_PACKETS] == 603
    fixes = recording_fixes(out)
    assert len(fixes) == len(source) == 30
    for ours, theirs in zip(fixes, source, strict=True):
        assert abs(ours.utc_ns - theirs.utc_ns) <= 500_000  # GGA carries ms
        assert ours.lat == pytest.approx(theirs.lat, abs=1e-9)
        assert ours.lon == pytest.approx(theirs.lon, abs=1e-9)
        assert ours.altitude_ellipsoid_m == pytest.approx(theirs.altitude_ellipsoid_m, abs=1e-3)
        # The localiser's sigmas come through GST.
        assert ours.std_lat_m == pytest.approx(theirs.std_lat_m, abs=5e-4)
        assert ours.std_lon_m == pytest.approx(theirs.std_lon_m, abs=5e-4)
        # GBAS (RTK) is fixed when the horizontal sigma is at most 5 cm, else float.
        sigma = max(theirs.std_lat_m, theirs.std_lon_m)
        assert ours.quality == (4 if sigma <= 0.05 else 5)
    assert {f.quality for f in source} == {5}
    assert {f.quality for f in fixes} == {5}  # the F9R's float sigmas are all above 5 cm

    summary = replay(out, tmp_path / "run")  # fixes of 2025, scans of 2023 (see above)
    assert summary["fixes"] == 30
    assert summary["scans"] + summary["scans_without_pose"] + summary["scans_without_heading"] == 4


def test_navsatfix_without_covariance_cannot_tell_fixed_from_float(tmp_path):
    store = typestore(ros1=True)
    gnss, source = navsatfix_rows(store, True, "nmea-rtk.nmea", 1_700_000_000 * 10**9)
    bag = write_ros1(tmp_path / "rtk.bag", store, gnss)
    assert {f.quality for f in source} == {2, 4} and all(f.std_lat_m is None for f in source)

    import_bags([bag], tmp_path / "auto.mcap")
    auto = recording_fixes(tmp_path / "auto.mcap")
    assert len(auto) == len(source) == 122
    # SBAS stays DGPS (2); GBAS without a covariance is taken as RTK float (5).
    assert [f.quality for f in auto] == [{2: 2, 4: 5}[f.quality] for f in source]

    import_bags([bag], tmp_path / "fixed.mcap", ImportOptions(gnss_quality=4))
    assert {f.quality for f in recording_fixes(tmp_path / "fixed.mcap")} == {4}


def test_bags_split_by_sensor_are_merged_by_time(tmp_path):
    """CitrusFarm ships one bag per modality: LiDAR from a ROS 1 bag, GNSS from a ROS 2 one."""
    store1, store2 = typestore(ros1=True), typestore(ros1=False)
    lidar = velodyne_rows(store1, ros1=True)
    t0 = lidar[0][0] - 200_000_000
    gnss = sentence_rows(store2, ros1=False, name="ublox-zed-f9p-nmea.nmea", t0=t0)
    lidar_bag = write_ros1(tmp_path / "lidar.bag", store1, lidar)
    gnss_bag = write_ros2(tmp_path / "gnss", store2, gnss, StoragePlugin.SQLITE3)
    out = tmp_path / "merged.mcap"

    report = import_bags([gnss_bag, lidar_bag], out)

    messages = list(rec.read_recording(out))
    assert report.channels == {rec.GNSS_NMEA: len(gnss), rec.LIDAR_PACKETS: 603}
    assert [m.log_time for m in messages] == sorted(m.log_time for m in messages)
    # The GNSS log starts before the scans and runs past them: the channels interleave.
    topics = [m.topic for m in messages]
    first_lidar = topics.index(rec.LIDAR_PACKETS)
    assert rec.GNSS_NMEA in topics[:first_lidar] and rec.GNSS_NMEA in topics[first_lidar + 603 :]


def test_image_topics_become_jpeg_frames(tmp_path):
    """A raw rgb8 image becomes a JPEG whose bands decode where they were (no camera
    fixture holds real frames: the pixels are made here, one flat band and one gradient,
    so a swapped band shows)."""
    store = typestore(ros1=True)
    Image = store.types["sensor_msgs/msg/Image"]
    height, width = 72, 128
    rgb = np.zeros((height, width, 3), dtype=np.uint8)
    rgb[..., 0] = 200  # red band high
    rgb[..., 2] = np.linspace(0, 255, width, dtype=np.uint8)  # third band a gradient
    t = 1_673_400_471_000_000_000
    msg = Image(
        header=header(store, t, "cam", True),
        height=height,
        width=width,
        encoding="rgb8",
        is_bigendian=0,
        step=width * 3,
        data=rgb.ravel(),
    )
    bag = write_ros1(tmp_path / "cam.bag", store, [(t + 5_000_000, "/cam", Image.__msgtype__, msg)])
    out = tmp_path / "cam.mcap"
    import_bags([bag], out)
    (frame,) = recorded(out, rec.CAMERA_JPEG)
    assert frame.log_time == t + 5_000_000 and frame.publish_time == t
    bgr = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
    assert bgr.shape == (height, width, 3)
    assert abs(int(bgr[..., 2].mean()) - 200) <= 3  # red is still red
    assert np.abs(bgr[..., 0].astype(int) - rgb[..., 2].astype(int)).mean() < 3


def test_unknown_and_missing_topics_are_listed_not_fatal(tmp_path):
    store = typestore(ros1=True)
    String = store.types["std_msgs/msg/String"]
    rows = velodyne_rows(store, ros1=True)
    rows.append((rows[0][0], "/notes", String.__msgtype__, String(data="run 3, row 12")))
    bag = write_ros1(tmp_path / "survey.bag", store, rows)
    out = tmp_path / "survey.mcap"
    result = cli(
        "import", str(bag), "--out", str(out), "--topics", "camera=/cam", "lidar=/velodyne_packets",
        "--json",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    status = {t["topic"]: t["status"] for t in summary["topics"]}
    assert status == {
        "/velodyne_packets": "imported",
        "/notes": "unknown type",
        "/cam": "missing",
    }
    assert summary["missing"] == ["/cam"]
    assert summary["channels"] == {rec.LIDAR_PACKETS: 603}
    text = cli("import", str(bag), "--out", str(tmp_path / "b.mcap"), "--preset", "citrusfarm")
    assert text.returncode == 0, text.stderr
    assert "/piksi/navsatfix_best_fix" in text.stdout and "missing" in text.stdout
    assert "nothing" in text.stdout  # no CitrusFarm topic in this bag: an empty recording
    # The preset's calibration is the recording's, with the MicroStrain's mounting.
    assert rec.read_recording(tmp_path / "b.mcap").metadata.calibration == {
        **json.loads(
            (FIXTURES / "citrusfarm_calib" / "citrusfarm_calibration_v1.json").read_text()
        ),
        "T_base_imu": list(CITRUSFARM_T_BASE_IMU),
    }


def test_a_damaged_bag_is_one_line_and_exit_2(tmp_path):
    store = typestore(ros1=True)
    bag = write_ros1(tmp_path / "survey.bag", store, velodyne_rows(store, ros1=True))
    data = bag.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) // 2])
    db3 = tmp_path / "cut_ros2"
    db3.mkdir()
    (db3 / "metadata.yaml").write_bytes((NEBULA_BAG / "metadata.yaml").read_bytes())
    name = "1673400471837873222_0.db3"
    (db3 / name).write_bytes((NEBULA_BAG / name).read_bytes()[:300_000])

    for damaged in (cut, db3):
        out = tmp_path / "out.mcap"
        result = cli("import", str(damaged), "--out", str(out))
        assert result.returncode == 2
        assert result.stderr.startswith(f"treetraits: error: {damaged}: ")
        assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr
        assert not out.exists()
    with pytest.raises(SourceError, match="no such bag"):
        import_bags([tmp_path / "nope.bag"], tmp_path / "out.mcap")


# --- the twin as a CitrusFarm-shaped ROS 1 bag, odometry and IMU included (format 1.1) ---


def twin_rows(store, recording: Path) -> list[tuple]:
    """A twin recording as the ROS topics a Jackal survey records: VelodyneScan (a
    message per 76 packets, each packet at its receive time), nmea_msgs/Sentence,
    CompressedImage, and the MCU's wheels and IMU as nav_msgs/Odometry (the twist of each
    wheel step, as jackal_velocity_controller reports it) and sensor_msgs/Imu."""
    calibration = load_calibration(rec.read_recording(recording).metadata.calibration)
    wheels = calibration.wheels
    T = store.types
    rows: list[tuple] = []
    packets: list = []
    mcu = JackalProtocol()
    previous = None
    for m in rec.read_recording(recording):
        if m.topic == rec.LIDAR_PACKETS:
            packets.append(m)
            if len(packets) == 76:
                rows.append(_scan_row(store, packets))
                packets = []
        elif m.topic == rec.GNSS_NMEA:
            msg = T["nmea_msgs/msg/Sentence"](
                header=header(store, m.log_time, "gps", True),
                sentence=m.data.decode("ascii").rstrip("\r\n"),
            )
            rows.append((m.log_time, "/nmea_sentence", msg.__msgtype__, msg))
        elif m.topic == rec.CAMERA_JPEG:
            msg = T["sensor_msgs/msg/CompressedImage"](
                header=header(store, m.publish_time, "mapir", True),
                format="jpeg",
                data=np.frombuffer(m.data, dtype=np.uint8).copy(),
            )
            rows.append((m.log_time, "/mapir_cam/image_raw/compressed", msg.__msgtype__, msg))
        elif m.topic == rec.WHEELS_JACKAL:
            for record in mcu.receive(m.data, m.log_time, m.log_time / 1e9):
                if isinstance(record, WheelSample):
                    speed = turn = 0.0
                    if previous is not None and record.t_host > previous.t_host:
                        dt = (record.t_host - previous.t_host) / 1e9
                        left = wheels.metres(record.left - previous.left, record.unit)
                        right = wheels.metres(record.right - previous.right, record.unit)
                        speed, turn = (left + right) / 2 / dt, (right - left) / wheels.track / dt
                    previous = record
                    rows.append(odometry_row(store, record.t_host, speed, turn))
                elif isinstance(record, JackalImu):
                    rows.append(imu_row(store, record))
            mcu.take_outgoing()
    if packets:
        rows.append(_scan_row(store, packets))
    return rows


def _scan_row(store, packets: list) -> tuple:
    T = store.types
    msg = T["velodyne_msgs/msg/VelodyneScan"](
        header=header(store, packets[0].log_time, "velodyne", True),
        packets=[
            T["velodyne_msgs/msg/VelodynePacket"](
                stamp=stamp(store, p.log_time), data=np.frombuffer(p.data, np.uint8).copy()
            )
            for p in packets
        ],
    )
    return (packets[-1].log_time + 1_000_000, "/velodyne_packets", msg.__msgtype__, msg)


def trees_csv(run: Path) -> list[dict]:
    with open(run / "trees.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_a_twin_survey_as_a_ros1_bag_maps_the_same_trees(tmp_path):
    twin = twin_survey(SurveySettings(seed=2, goal=8.0))  # tests/export/test_foxglove.py's drive
    store = typestore(ros1=True)
    bag = write_ros1(tmp_path / "twin.bag", store, twin_rows(store, twin.recording))
    out = tmp_path / "imported.mcap"
    calibration = tmp_path / "calibration.json"
    calibration.write_text(json.dumps(rec.read_recording(twin.recording).metadata.calibration))

    report = import_bags([bag], out, ImportOptions(calibration=json.loads(calibration.read_text())))

    assert report.format_version == "1.1"
    assert rec.read_recording(out).metadata.format_version == "1.1"
    original = {t: n for t, n in _counts(twin.recording).items() if t != rec.WHEELS_JACKAL}
    imported = _counts(out)
    for topic in (rec.LIDAR_PACKETS, rec.GNSS_NMEA, rec.CAMERA_JPEG):
        assert imported[topic] == original[topic]
    assert imported[rec.WHEELS_ODOMETRY] > 0 and imported[rec.IMU_DATA] > 0
    # The sensors' bytes and times are the twin's own.
    for topic in (rec.LIDAR_PACKETS, rec.GNSS_NMEA, rec.CAMERA_JPEG):
        ours = [(m.data, m.log_time, m.publish_time) for m in recorded(out, topic)]
        theirs = [(m.data, m.log_time, m.publish_time) for m in recorded(twin.recording, topic)]
        assert ours == theirs, topic

    # The field map is an attachment of the twin's recording, not a ROS topic: give both.
    field_map = ("--field-map", str(twin.field_map))
    ours = replay(out, tmp_path / "ours", *field_map)
    theirs = replay(twin.recording, tmp_path / "theirs", *field_map)
    assert ours["trees"] == theirs["trees"] >= 4
    assert ours["scans"] == theirs["scans"]
    for a, b in zip(trees_csv(tmp_path / "ours"), trees_csv(tmp_path / "theirs"), strict=True):
        for key in ("easting", "northing", "width_m", "height_m"):
            assert float(a[key]) == pytest.approx(float(b[key]), abs=0.01), key


def _counts(path: Path) -> dict[str, int]:
    counts: dict[str, int] = {}
    for m in rec.read_recording(path):
        counts[m.topic] = counts.get(m.topic, 0) + 1
    return counts


def test_help_explains_every_option_and_bad_options_are_one_line(tmp_path):
    result = cli("import", "--help")
    assert result.returncode == 0 and result.stdout.startswith("usage: treetraits import")
    for option in (
        "--out", "--topics", "--calibration", "--preset", "--gnss-quality", "--jpeg-quality",
        "--force", "--overwrite", "--json",
    ):  # fmt: skip
        assert option in result.stdout
    text = " ".join(result.stdout.split())  # argparse wraps lines
    for kind in (
        "lidar:",
        "points: sensor_msgs/msg/PointCloud2",
        "gnss:",
        "camera:",
        "odom:",
        "imu:",
    ):
        assert kind in text
    bad = cli("import", str(NEBULA_BAG), "--out", str(tmp_path / "o.mcap"), "--topics", "sonar=/x")
    assert bad.returncode == 2 and "unknown kind 'sonar'" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1


def test_an_existing_output_is_exit_4_and_force_replaces_it_as_every_command(tmp_path):
    """docs/cli.md: an earlier output is refused with exit 4 and replaced with --force, as
    by every command (import used to say exit 2 and --overwrite, still an alias); a
    directory where the recording is wanted is refused before any bag is read."""
    out = tmp_path / "o.mcap"
    out.write_bytes(b"")
    exists = cli("import", str(NEBULA_BAG), "--out", str(out))
    assert exists.returncode == 4, exists.stderr
    assert exists.stderr == (
        f"treetraits: error: {out}: exists; give --force to replace it, or choose another --out\n"
    )
    assert out.read_bytes() == b""
    for option in ("--force", "--overwrite"):
        replaced = cli("import", str(NEBULA_BAG), "--out", str(out), option, "--json")
        assert replaced.returncode == 0, replaced.stderr
        assert json.loads(replaced.stdout)["channels"]["/lidar/packets"] > 0
        assert rec.read_recording(out).metadata is not None
    folder = tmp_path / "folder.mcap"
    folder.mkdir()
    for force in ([], ["--force"]):
        refused = cli("import", str(NEBULA_BAG), "--out", str(folder), *force)
        assert refused.returncode == 2, refused.stderr
        assert refused.stderr.startswith(f"treetraits: error: {folder}: is a directory; ")
        assert list(folder.iterdir()) == []


def test_navsatfix_gets_a_course_made_good_once_the_receiver_moves(tmp_path):
    # NavSatFix has no velocity; the import derives RMC's course and speed from the
    # positions of the last second (tests/drivers/rosbag/test_citrusfarm.py checks them against
    # the twin's receiver). A real log driven at up to 1.7 m/s: every moving fix gets a
    # speed (but the first after a gap in the log), and a course once 0.2 m were travelled
    # within the second.
    store = typestore(ros1=True)
    gnss, source = navsatfix_rows(store, True, "nmea-rtk.nmea", 1_700_000_000 * 10**9)
    bag = write_ros1(tmp_path / "rtk.bag", store, gnss)
    import_bags([bag], tmp_path / "rtk.mcap")
    ours = recording_fixes(tmp_path / "rtk.mcap")
    assert len(ours) == len(source) == 122
    moving = [a for a, b in zip(ours, source, strict=True) if (b.speed_mps or 0) > 0.5]
    assert len(moving) == 44
    assert sum(a.speed_mps is not None for a in moving) >= len(moving) - 3  # gaps reset it
    assert sum(a.course_deg is not None for a in moving) >= len(moving) - 3
    # The first fixes (less than half a second of history): neither.
    assert ours[0].course_deg is None and ours[0].speed_mps is None
    # This log's moving fixes are DGPS (quality 2, decimetres of noise): the course made
    # good from them is off the receiver's Doppler course by 26 deg (median), which is why
    # the localiser's course sigma grows as the speed falls; RTK gives about 2 deg.
