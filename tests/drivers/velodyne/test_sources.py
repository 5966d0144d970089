"""Offline LiDAR sources (pcap, pcapng, raw payloads, MCAP) on real captures.

Each test rewrites a real capture in another container or link layer (pcapng, VLAN-tagged
Ethernet, Linux cooked, raw IP, an MCAP recording), or mixes in other traffic, or cuts it
short, then decodes it through `open_source` and compares with the original capture decoded
as it is. The original is anchored to its reference JSON, and the packets and timestamps are
read from the pcap records here with `struct`, not through the code under test.
"""

from __future__ import annotations

import dataclasses
import shutil
import socket
import struct
from decimal import Decimal
from pathlib import Path
from typing import NamedTuple

import dpkt
import numpy as np
import pytest

from tests.helpers.captures import VLP16_DIR, decode_file, reference
from treetraits.drivers import recording
from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne.sources import (
    McapSource,
    PcapSource,
    RawPayloadSource,
    open_source,
)
from treetraits.errors import SourceError

CAPTURE = "veloview_vlp16_20hz_strongest.pcap"  # Ethernet, data (2368) and position (8308)
RAW_CAPTURE = "einride_vlp16_strongest_1000pkts.bin"

ETH_HEADER = 14
IP_UDP_HEADERS = 28  # IPv4 without options + UDP
LINKTYPE_ETHERNET = 1
LINKTYPE_NULL = 0  # BSD loopback: 4-byte address family in host byte order
LINKTYPE_RAW = 101  # raw IP as libpcap writes it in files (DLT_RAW is 12 or 14 in memory)
LINKTYPE_LINUX_SLL = 113
LINKTYPE_IEEE802_11 = 105
LINKTYPE_IPV4 = 228
LINKTYPE_LINUX_SLL2 = 276


class Record(NamedTuple):
    """One libpcap record: capture time in ns (exact) and the frame."""

    ts_ns: int
    frame: bytes


def pcap_records(path: Path) -> list[Record]:
    """The records of a little-endian microsecond libpcap file, parsed with `struct`."""
    data = path.read_bytes()
    assert data[:4] == b"\xd4\xc3\xb2\xa1", "expected a little-endian microsecond pcap"
    records, offset = [], 24
    while offset < len(data):
        sec, usec, caplen, _ = struct.unpack_from("<IIII", data, offset)
        frame = data[offset + 16 : offset + 16 + caplen]
        records.append(Record(sec * 1_000_000_000 + usec * 1000, frame))
        offset += 16 + caplen
    return records


def udp_payload(frame: bytes) -> bytes:
    """The UDP payload of one of the original Ethernet/IPv4/UDP frames."""
    assert frame[12:14] == b"\x08\x00" and frame[14] == 0x45 and frame[23] == 17
    return frame[ETH_HEADER + IP_UDP_HEADERS :]


def write_pcap(path: Path, records, linktype: int = LINKTYPE_ETHERNET, nano=False) -> Path:
    """A libpcap file through dpkt's writer, times passed exactly (as Decimal seconds)."""
    with open(path, "wb") as f:
        writer = dpkt.pcap.Writer(f, snaplen=65535, linktype=linktype, nano=nano)
        for ts_ns, frame in records:
            writer.writepkt(frame, Decimal(ts_ns) / 10**9)
    return path


def write_pcapng(path: Path, records) -> Path:
    """A pcapng file through dpkt's writer, microsecond times set exactly on each block."""
    with open(path, "wb") as f:
        writer = dpkt.pcapng.Writer(f, snaplen=65535, linktype=LINKTYPE_ETHERNET)
        for ts_ns, frame in records:
            assert ts_ns % 1000 == 0
            us = ts_ns // 1000
            writer.writepkt(
                dpkt.pcapng.EnhancedPacketBlockLE(
                    ts_high=us >> 32,
                    ts_low=us & 0xFFFFFFFF,
                    caplen=len(frame),
                    pkt_len=len(frame),
                    pkt_data=frame,
                )
            )
    return path


def read_packets(path) -> tuple[list[tuple[bytes, int]], dict]:
    """Every packet a source yields, as (payload, t_host), and its counters."""
    source = open_source(path)
    packets = [(p.payload, p.t_host) for p in source]
    source.close()
    return packets, source.stats.as_dict()


def scan_metadata(scan: Scan) -> dict:
    return {f.name: getattr(scan, f.name) for f in dataclasses.fields(scan) if f.name != "points"}


def assert_same_scans(actual: list[Scan], expected: list[Scan]) -> None:
    assert len(actual) == len(expected)
    for i, (a, e) in enumerate(zip(actual, expected, strict=True)):
        assert scan_metadata(a) == scan_metadata(e), f"scan {i}"
        assert a.points.dtype == e.points.dtype
        np.testing.assert_array_equal(a.points, e.points, err_msg=f"scan {i}")


class Original(NamedTuple):
    path: Path
    records: list[Record]
    packets: list[tuple[bytes, int]]
    counters: dict
    scans: list[Scan]
    batcher: dict


@pytest.fixture(scope="module")
def original() -> Original:
    """The capture as it is, checked against its reference facts and its own records."""
    path = VLP16_DIR / CAPTURE
    ref = reference(CAPTURE)
    records = pcap_records(path)
    packets, counters = read_packets(path)
    scans, reader = decode_file(path)

    assert packets == [(udp_payload(r.frame), r.ts_ns) for r in records]
    assert counters["data_packets"] == ref["raw"]["data_packets"] == 1902
    assert counters["position_packets"] == ref["raw"]["position_packets"] == 367
    assert counters["malformed"] == counters["foreign"] == 0
    assert counters["truncated"] is False
    cut0 = ref["velodyne_decoder"]["cut_angle_0"]
    assert [len(s.distinct) for s in scans] == cut0["points_per_scan_all"]
    return Original(path, records, packets, counters, scans, reader.batcher.stats.as_dict())


def assert_same_as_original(path: Path, original: Original) -> None:
    packets, counters = read_packets(path)
    assert packets == original.packets
    assert counters == original.counters
    scans, reader = decode_file(path)
    assert_same_scans(scans, original.scans)
    assert reader.batcher.stats.as_dict() == original.batcher


# --- containers and link layers ---------------------------------------------------------


def test_pcapng_rewrite_decodes_identically(original, tmp_path):
    path = write_pcapng(tmp_path / "capture.pcapng", original.records)
    assert isinstance(open_source(path), PcapSource)
    assert_same_as_original(path, original)


def test_nanosecond_pcap_decodes_identically(original, tmp_path):
    """tcpdump --time-stamp-precision=nano writes this magic (a1 b2 3c 4d)."""
    path = write_pcap(tmp_path / "nano.pcap", original.records, nano=True)
    assert path.read_bytes()[:4] == b"\x4d\x3c\xb2\xa1"
    assert_same_as_original(path, original)


def _vlan(frame: bytes) -> bytes:
    """One 802.1Q tag (VLAN 42, priority 5) between the MAC addresses and the EtherType."""
    return frame[:12] + b"\x81\x00" + struct.pack(">H", 5 << 13 | 42) + frame[12:]


def _qinq(frame: bytes) -> bytes:
    """802.1ad outer tag (service VLAN 7) and 802.1Q inner tag (VLAN 42)."""
    tags = b"\x88\xa8" + struct.pack(">H", 7) + b"\x81\x00" + struct.pack(">H", 42)
    return frame[:12] + tags + frame[12:]


def _sll(frame: bytes) -> bytes:
    """Linux cooked v1: packet type 1 (broadcast), ARPHRD_ETHER, source MAC, EtherType."""
    return struct.pack(">HHH8s", 1, 1, 6, frame[6:12]) + frame[12:]


def _sll2(frame: bytes) -> bytes:
    """Linux cooked v2: EtherType, reserved, ifindex, ARPHRD_ETHER, type, addr len, addr."""
    return frame[12:14] + struct.pack(">HiHBB8s", 0, 3, 1, 1, 6, frame[6:12]) + frame[14:]


def _raw_ip(frame: bytes) -> bytes:
    return frame[ETH_HEADER:]


def _bsd_loopback(frame: bytes) -> bytes:
    return struct.pack("=I", 2) + frame[ETH_HEADER:]  # AF_INET


@pytest.mark.parametrize(
    ("linktype", "rewrap"),
    [
        pytest.param(LINKTYPE_ETHERNET, _vlan, id="ethernet-802.1Q"),
        pytest.param(LINKTYPE_ETHERNET, _qinq, id="ethernet-802.1ad-QinQ"),
        pytest.param(LINKTYPE_LINUX_SLL, _sll, id="linux-cooked-sll"),
        pytest.param(LINKTYPE_LINUX_SLL2, _sll2, id="linux-cooked-sll2"),
        pytest.param(LINKTYPE_RAW, _raw_ip, id="raw-ip-101"),
        pytest.param(LINKTYPE_IPV4, _raw_ip, id="raw-ipv4-228"),
        pytest.param(LINKTYPE_NULL, _bsd_loopback, id="bsd-loopback"),
    ],
)
def test_link_layers_decode_identically(original, tmp_path, linktype, rewrap):
    records = [Record(r.ts_ns, rewrap(r.frame)) for r in original.records]
    path = write_pcap(tmp_path / "relinked.pcap", records, linktype=linktype)
    assert_same_as_original(path, original)


# --- other traffic ----------------------------------------------------------------------

SENSOR_MAC, HOST_MAC = b"\x60\x76\x88\x00\x00\x01", b"\x00\x1b\x21\x00\x00\x02"
SENSOR_IP, HOST_IP = bytes([192, 168, 1, 201]), bytes([192, 168, 1, 77])


def _ethernet(payload, ethertype: int) -> bytes:
    return bytes(dpkt.ethernet.Ethernet(dst=HOST_MAC, src=SENSOR_MAC, type=ethertype, data=payload))


def _ipv4(transport, proto: int) -> bytes:
    ip = dpkt.ip.IP(src=SENSOR_IP, dst=HOST_IP, p=proto, ttl=64, data=transport)
    ip.len = len(ip)
    return _ethernet(ip, dpkt.ethernet.ETH_TYPE_IP)


def _udp4(dport: int, length: int) -> bytes:
    udp = dpkt.udp.UDP(sport=2368, dport=dport, data=bytes(range(256)) * 16)
    udp.data = udp.data[:length]
    udp.ulen = len(udp)
    return _ipv4(udp, dpkt.ip.IP_PROTO_UDP)


def _udp6(dport: int, length: int) -> bytes:
    udp = dpkt.udp.UDP(sport=40000, dport=dport, data=b"\x5a" * length)
    udp.ulen = len(udp)
    ip6 = dpkt.ip6.IP6(
        src=b"\xfe\x80" + b"\x00" * 13 + b"\x01",
        dst=b"\xff\x02" + b"\x00" * 13 + b"\x01",
        nxt=dpkt.ip.IP_PROTO_UDP,
        hlim=1,
        plen=len(udp),
        data=udp,
    )
    return _ethernet(ip6, dpkt.ethernet.ETH_TYPE_IP6)


def _arp() -> bytes:
    arp = dpkt.arp.ARP(sha=HOST_MAC, spa=HOST_IP, tha=b"\x00" * 6, tpa=SENSOR_IP)
    return bytes(dpkt.ethernet.Ethernet(dst=b"\xff" * 6, src=HOST_MAC, type=0x0806, data=arp))


def _tcp_to_data_port() -> bytes:
    """A TCP segment to port 2368 carrying exactly 1206 bytes: still not a sensor packet."""
    tcp = dpkt.tcp.TCP(sport=50000, dport=2368, flags=dpkt.tcp.TH_ACK, data=b"\xff\xee" * 603)
    return _ipv4(tcp, dpkt.ip.IP_PROTO_TCP)


FOREIGN_FRAMES = {
    "arp": _arp(),
    "tcp to 2368, 1206 bytes": _tcp_to_data_port(),
    "dns, 40 bytes": _udp4(53, 40),
    "mdns, 300 bytes": _udp4(5353, 300),
    "udp 9000, 1248 bytes": _udp4(9000, 1248),
    "ipv6 udp 547, 100 bytes": _udp6(547, 100),
    "lldp": _ethernet(b"\x02\x07\x04" + SENSOR_MAC + b"\x00" * 30, 0x88CC),
}
MALFORMED_FRAMES = {
    "udp 2368, 1205 bytes": _udp4(2368, 1205),
    "udp 2368, 1000 bytes": _udp4(2368, 1000),
    "ipv6 udp 8308, 513 bytes": _udp6(8308, 513),
}


def test_other_traffic_is_skipped_and_counted(original, tmp_path):
    extra = [*FOREIGN_FRAMES.values(), *MALFORMED_FRAMES.values()]
    records, inserted = [], []
    for i, (ts_ns, frame) in enumerate(original.records):
        records.append(Record(ts_ns, frame))
        if i % 97 == 0:  # every kind of extra frame, several times, all through the capture
            inserted.append(extra[len(inserted) % len(extra)])
            records.append(Record(ts_ns + 1000, inserted[-1]))
    path = write_pcap(tmp_path / "mixed.pcap", records)

    packets, counters = read_packets(path)
    assert packets == original.packets
    assert counters["foreign"] == sum(f in FOREIGN_FRAMES.values() for f in inserted)
    assert counters["malformed"] == sum(f in MALFORMED_FRAMES.values() for f in inserted)
    assert counters["foreign"] >= 2 * len(FOREIGN_FRAMES)
    assert counters["malformed"] >= 2 * len(MALFORMED_FRAMES)
    assert counters["truncated"] is False
    scans, _ = decode_file(path)
    assert_same_scans(scans, original.scans)


# --- truncated captures -----------------------------------------------------------------


@pytest.mark.parametrize(("where", "into_record"), [("in a record header", 7), ("in a frame", 600)])
def test_truncated_pcap_decodes_the_whole_records(original, tmp_path, where, into_record):
    """A capture cut by a full disk or a power cut: every whole record before the cut."""
    whole = 1000  # records before the cut
    offset = 24 + sum(16 + len(r.frame) for r in original.records[:whole])
    path = tmp_path / "cut.pcap"
    path.write_bytes(original.path.read_bytes()[: offset + into_record])

    packets, counters = read_packets(path)
    assert packets == original.packets[:whole]
    before_cut = [udp_payload(r.frame) for r in original.records[:whole]]
    assert counters["data_packets"] == sum(len(p) == 1206 for p in before_cut)
    assert counters["position_packets"] == sum(len(p) == 512 for p in before_cut)
    assert counters["truncated"] is True
    assert counters["malformed"] == counters["foreign"] == 0  # a cut is not bad traffic

    scans, _ = decode_file(path)
    assert 0 < len(scans) < len(original.scans)
    assert_same_scans(scans[:-1], original.scans[: len(scans) - 1])
    last, same = scans[-1], original.scans[len(scans) - 1]
    np.testing.assert_array_equal(last.points, same.points[: len(last.points)])


# --- raw payload files ------------------------------------------------------------------


def test_raw_payload_file_gives_the_reference_counts():
    ref = reference(RAW_CAPTURE)
    source = open_source(VLP16_DIR / RAW_CAPTURE)
    assert isinstance(source, RawPayloadSource)
    packets = list(source)
    source.close()
    raw = (VLP16_DIR / RAW_CAPTURE).read_bytes()
    assert [p.payload for p in packets] == [raw[i : i + 1206] for i in range(0, len(raw), 1206)]
    assert source.stats.data_packets == ref["raw"]["data_packets"] == 1000
    assert source.stats.position_packets == ref["raw"]["position_packets"] == 0
    assert source.stats.malformed == 0
    assert source.stats.truncated is False
    # No capture clock in the file: t_host is rebuilt from the ToH (device microseconds).
    assert packets[-1].t_host - packets[0].t_host == round(ref["raw"]["toh_span_s"] * 1e9)


def test_raw_payload_file_with_a_partial_last_payload(tmp_path):
    whole = VLP16_DIR / RAW_CAPTURE
    path = tmp_path / "cut.bin"
    shutil.copy(whole, path)
    with open(path, "ab") as f:
        f.write(whole.read_bytes()[:500])  # a payload cut short by the end of the file

    packets, counters = read_packets(path)
    assert packets == read_packets(whole)[0]
    assert counters["data_packets"] == reference(RAW_CAPTURE)["raw"]["data_packets"]
    assert counters["malformed"] == 1
    assert counters["truncated"] is True
    assert_same_scans(decode_file(path)[0], decode_file(whole)[0])


# --- MCAP recordings --------------------------------------------------------------------


def write_recording(path: Path, records: list[Record]) -> Path:
    """Every sensor packet of a capture into a recording, log_time = the capture time."""
    with recording.RecordingWriter(path) as writer:
        for ts_ns, frame in records:
            payload = udp_payload(frame)
            topic = recording.LIDAR_PACKETS if len(payload) == 1206 else recording.LIDAR_TELEMETRY
            writer.write(topic, payload, log_time=ts_ns)
    return path


def test_mcap_recording_decodes_like_the_pcap(original, tmp_path):
    path = write_recording(tmp_path / "capture.mcap", original.records)
    source = open_source(path)
    assert isinstance(source, McapSource)
    source.close()
    assert_same_as_original(path, original)


def test_truncated_mcap_recording_yields_a_prefix(original, tmp_path):
    whole = write_recording(tmp_path / "whole.mcap", original.records)
    data = whole.read_bytes()
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[: int(len(data) * 0.7)])

    packets, counters = read_packets(path)
    assert 0 < len(packets) < len(original.packets)
    assert packets == original.packets[: len(packets)]
    assert counters["truncated"] is True
    assert counters["malformed"] == 0

    scans, _ = decode_file(path)
    assert 0 < len(scans) < len(original.scans)
    assert_same_scans(scans[:-1], original.scans[: len(scans) - 1])
    last, same = scans[-1], original.scans[len(scans) - 1]
    np.testing.assert_array_equal(last.points, same.points[: len(last.points)])


# --- open_source errors -----------------------------------------------------------------


def test_missing_file_is_a_source_error(tmp_path):
    missing = tmp_path / "nowhere.pcap"
    with pytest.raises(SourceError, match="no such file") as error:
        open_source(missing)
    assert str(missing) in str(error.value)


@pytest.mark.parametrize(
    "content",
    [
        pytest.param(b"timestamp,x,y,z\n0,1.0,2.0,3.0\n", id="text"),
        pytest.param(b"", id="empty"),
        pytest.param(b"\xff\xee" + b"\x00" * 1000, id="raw-but-not-1206-sized"),
    ],
)
def test_not_a_capture_is_a_source_error(tmp_path, content):
    path = tmp_path / "notes.txt"
    path.write_bytes(content)
    with pytest.raises(SourceError, match="not a pcap, pcapng or MCAP") as error:
        open_source(path)
    assert str(path) in str(error.value)


def test_pcap_with_a_cut_file_header_is_a_source_error(original, tmp_path):
    path = tmp_path / "header.pcap"
    path.write_bytes(original.path.read_bytes()[:10])
    with pytest.raises(SourceError, match="not a readable pcap") as error:
        open_source(path)
    assert str(path) in str(error.value)


def test_unsupported_link_type_is_a_source_error(original, tmp_path):
    path = write_pcap(tmp_path / "wifi.pcap", original.records[:5], linktype=LINKTYPE_IEEE802_11)
    with pytest.raises(SourceError, match="link type 105 is not supported") as error:
        open_source(path)
    assert "Ethernet" in str(error.value)  # says what is supported


@pytest.mark.parametrize(
    ("uri", "message"),
    [
        ("udp://127.0.0.1:0?telemetry=0&bogus=1", r"unknown option\(s\) \['bogus'\]"),
        ("udp://127.0.0.1:0?telemetry=eight", "invalid literal"),
        ("udp://127.0.0.1:0?telemetry=0&rcvbuf=lots", "invalid literal"),
        ("udp://127.0.0.1:70000?telemetry=0", "out of range"),
        ("udp://127.0.0.1:0?telemetry=0&sensor=lidar.local", "lidar.local"),
    ],
)
def test_bad_udp_uri_is_a_source_error(uri, message):
    with pytest.raises(SourceError, match=message):
        open_source(uri)


def test_udp_port_in_use_is_a_source_error():
    """Another program (VeloView, a ROS driver) holds the port without SO_REUSEADDR."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        other.bind(("127.0.0.1", 0))
        port = other.getsockname()[1]
        with pytest.raises(SourceError, match=f"127.0.0.1:{port}.*another program"):
            open_source(f"udp://127.0.0.1:{port}?telemetry=0")
