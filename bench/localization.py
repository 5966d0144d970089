"""Localisation speed: NMEA sentences parsed per second (against pynmeagps, same bytes, same
process) and pose updates per second, each as a multiple of what the sensors send.

- NMEA: all 13 real receiver logs in tests/fixtures/nmea, concatenated; ours = the
  resyncing splitter + `decode`; peer = pynmeagps' NMEAReader over the same bytes.
  Real rate: a 10 Hz receiver sending ~10 sentences per epoch = 100 sentences/s.
- Pose: the Localizer over a simulated 90 s drive (wheels at 50 Hz, RTK fixes with a true
  heading at 5 Hz: 55 inputs per second of driving). No peer runs here (robot_localization
  needs ROS); the absolute time per input is printed.

Last line, exactly: `nmea_vs_pynmeagps=R nmea_realtime=X pose_realtime=Y`.

    .venv/bin/python bench/localization.py [--rounds 7]
"""

from __future__ import annotations

import argparse
import io
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # for tests.*: the drive

import numpy as np
from pynmeagps import NMEAReader

from tests.helpers.localization import PATH, WHEELS, drive, sensors
from treetraits.drivers.gnss.sentences import decode
from treetraits.drivers.gnss.stream import SentenceSplitter
from treetraits.drivers.records import WheelSample
from treetraits.pipeline.localization import LocalizationConfig, Localizer

NMEA_DIR = Path(__file__).resolve().parent.parent / "tests" / "fixtures" / "nmea"
NMEA_REAL_RATE = 100.0  # sentences per second from a 10 Hz receiver
POSE_REAL_RATE = 55.0  # wheel samples (50 Hz) + fixes (5 Hz) per second


def parse_ours(data: bytes) -> int:
    splitter = SentenceSplitter()
    decoded = 0
    for sentence in splitter.push(data, 0) + splitter.flush():
        if decode(sentence) is not None:
            decoded += 1
    return decoded


def parse_peer(data: bytes) -> int:
    reader = NMEAReader(io.BytesIO(data), quitonerror=0, validate=1)
    return sum(1 for _raw, parsed in reader if parsed is not None)


def run_localizer(events) -> int:
    localizer = Localizer(LocalizationConfig(), WHEELS)
    for event in events:
        if isinstance(event, WheelSample):
            localizer.add_wheels(event)
        else:
            localizer.add_fix(event)
    return len(events)


def median_time(function, argument, rounds: int) -> float:
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        function(argument)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()

    data = b"".join(p.read_bytes() for p in sorted(NMEA_DIR.glob("*.nmea")))
    sentences = parse_ours(data)
    parse_peer(data)  # warm up
    ours, peer = [], []
    for _ in range(args.rounds):  # interleaved so machine noise hits both alike
        ours.append(median_time(parse_ours, data, 1))
        peer.append(median_time(parse_peer, data, 1))
    ours_s, peer_s = statistics.median(ours), statistics.median(peer)
    nmea_rate = sentences / ours_s
    print(
        f"NMEA: {sentences} sentences ({len(data)} bytes): ours {ours_s * 1e3:.1f} ms, "
        f"pynmeagps {peer_s * 1e3:.1f} ms, {nmea_rate:,.0f} sentences/s"
    )

    events = sensors(drive(PATH), np.random.default_rng(0), heading_sigma_deg=0.5)
    pose_s = median_time(run_localizer, events, args.rounds)
    pose_rate = len(events) / pose_s
    print(
        f"pose: {len(events)} inputs (90 s of driving): {pose_s * 1e3:.1f} ms, "
        f"{pose_s / len(events) * 1e6:.1f} us per input, {pose_rate:,.0f} inputs/s"
    )
    print(
        f"nmea_vs_pynmeagps={peer_s / ours_s:.2f} nmea_realtime={nmea_rate / NMEA_REAL_RATE:.0f} "
        f"pose_realtime={pose_rate / POSE_REAL_RATE:.0f}"
    )


if __name__ == "__main__":
    main()
