"""Decode speed: our VLP-16 decoder against velodyne_decoder, same packets, same process.

Both decoders get every data packet of a real capture from memory, one push per packet,
and return every scan (ours: `ScanBatcher.push`, compiled passes per scan; theirs:
`StreamDecoder.decode`, C++ behind pybind11). Several interleaved rounds; medians.

Last line, exactly: `decode_vs_velodyne_decoder=R realtime=X`, where R = our throughput /
the peer's (higher is better) and X = our packets per second / the sensor's packet rate
(754 /s in single-return mode, 1508 /s in dual).

    .venv/bin/python bench/decode.py [--rounds 9] [CAPTURE ...]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import velodyne_decoder as vd

from treetraits.drivers.velodyne import models as m
from treetraits.drivers.velodyne.batcher import ScanBatcher
from treetraits.drivers.velodyne.sources import open_source

FIXTURES = Path(__file__).resolve().parent.parent / "tests" / "fixtures" / "vlp16"
DEFAULT_CAPTURES = [
    "veloview_vlp16_20hz_strongest.pcap",
    "einride_vlp16_strongest_1000pkts.bin",
    "nebula_vlp16_dual_10hz.pcap",
]
SENSOR_PACKET_RATE = {"single": 1e9 / m.PACKET_NS_SINGLE, "dual": 1e9 / m.PACKET_NS_DUAL}


def load(path: Path) -> list[tuple[bytes, int]]:
    source = open_source(path)
    packets = [(p.payload, p.t_host) for p in source if p.is_data]
    source.close()
    # The peer refuses the 0x21 byte of early VLP-16 firmware; give both the same bytes.
    return [
        (p[:1205] + bytes([m.PRODUCT_VLP16]) if p[1205] == m.PRODUCT_HDL32E else p, t)
        for p, t in packets
    ]


def run_ours(packets) -> int:
    batcher = ScanBatcher()
    points = 0
    for payload, t_host in packets:
        scan = batcher.push(payload, t_host)
        if scan is not None:
            points += len(scan.points)
    last = batcher.flush()
    return points + (len(last.points) if last is not None else 0)


def run_peer(packets) -> int:
    decoder = vd.StreamDecoder(
        vd.Config(model=vd.Model.VLP16, cut_angle=0, min_range=0, max_range=500)
    )
    points = 0
    for payload, t_host in packets:
        result = decoder.decode(t_host / 1e9, payload)
        if result is not None:
            points += len(result[1])
    result = decoder.finish()
    return points + (len(result[1]) if result is not None else 0)


def timed(function, packets) -> float:
    start = time.perf_counter()
    function(packets)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("captures", nargs="*", default=DEFAULT_CAPTURES)
    parser.add_argument("--rounds", type=int, default=9)
    args = parser.parse_args()

    ratios, realtimes = [], []
    print(
        f"{'capture':40s} {'packets':>7s} {'ours ms':>8s} {'peer ms':>8s} "
        f"{'us/pkt':>7s} {'ratio':>6s} {'x realtime':>10s}"
    )
    for name in args.captures:
        packets = load(FIXTURES / name if not Path(name).exists() else Path(name))
        mode = "dual" if packets[0][0][1204] == m.RETURN_DUAL else "single"
        run_ours(packets), run_peer(packets)  # warm up caches and imports
        ours, peer = [], []
        for _ in range(args.rounds):  # interleaved so machine noise hits both alike
            ours.append(timed(run_ours, packets))
            peer.append(timed(run_peer, packets))
        ours_s, peer_s = statistics.median(ours), statistics.median(peer)
        ratio = peer_s / ours_s
        realtime = len(packets) / ours_s / SENSOR_PACKET_RATE[mode]
        ratios.append(ratio)
        realtimes.append(realtime)
        print(
            f"{name:40s} {len(packets):7d} {ours_s * 1e3:8.1f} {peer_s * 1e3:8.1f} "
            f"{ours_s / len(packets) * 1e6:7.2f} {ratio:6.2f} {realtime:10.0f}"
        )
    # The headline is the worst capture, not the best.
    print(f"decode_vs_velodyne_decoder={min(ratios):.2f} realtime={min(realtimes):.0f}")


if __name__ == "__main__":
    main()
