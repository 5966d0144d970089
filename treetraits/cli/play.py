"""`treetraits play`: play a recording to live interfaces at its recorded pace."""

from __future__ import annotations

import argparse
import ipaddress
import time
from pathlib import Path

from treetraits.damage import add_allow_damaged, report_damage
from treetraits.errors import ConfigError
from treetraits.files import check_output_file


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT (e.g. 127.0.0.1:2368), got {text!r}")
    return host.strip("[]"), int(port)


def _source_for(host: str) -> str:
    """Send from loopback to a loopback host (as the tests and the bench expect), else from
    any address (the route picks the interface)."""
    v6 = ":" in host
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if loopback:
        return "::1" if v6 else "127.0.0.1"
    return "::" if v6 else "0.0.0.0"


def register(commands: argparse._SubParsersAction) -> None:
    play = commands.add_parser(
        "play",
        help="play a recording to UDP and pseudo-terminals at its recorded pace",
        description=(
            "Send a recording's VLP-16 packets over UDP (from 127.0.0.1), its NMEA into a "
            "pseudo-terminal and act as the Jackal MCU on a second one, at the recorded "
            "pace: point `treetraits run` (or any reader) at them as at the robot. The pty "
            "paths are printed at the start."
        ),
    )
    play.add_argument("recording", type=Path, help="a recording (.mcap)")
    play.add_argument(
        "--lidar",
        type=_host_port,
        default=("127.0.0.1", 2368),
        metavar="HOST:PORT",
        help="where the data packets go (default 127.0.0.1:2368)",
    )
    play.add_argument(
        "--telemetry-port",
        type=int,
        default=8308,
        help="where the telemetry datagrams go, on the same host (default 8308; 0: none)",
    )
    play.add_argument("--speed", type=float, default=1.0, help="pace factor (default 1.0)")
    play.add_argument("--loop", action="store_true", help="start again at the end, until ^C")
    play.add_argument(
        "--camera-video",
        type=Path,
        help="also write the camera frames as an MJPG video here first (for camera.device)",
    )
    add_allow_damaged(play, "plays what it read")
    play.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from treetraits.sim.player import RecordingPlayer, write_camera_video

    if not args.speed > 0:
        raise ConfigError(f"--speed must be positive, got {args.speed}")
    if args.camera_video is not None:
        check_output_file(args.camera_video, "--camera-video")
        print(f"camera video: {write_camera_video(args.recording, args.camera_video)}")
    host, port = args.lidar
    with RecordingPlayer(
        args.recording,
        lidar_host=host,
        data_port=port,
        telemetry_port=args.telemetry_port or None,
        speed=args.speed,
        loop=args.loop,
        lidar_source=_source_for(host),
    ) as player:
        print(f"gnss: {player.gnss_device}")
        print(f"wheels: {player.wheels_device}")
        print(f"lidar: udp://{host}:{port} ({player.duration_s:.1f} s at x{args.speed:g})")
        # Read whole before playing: the loss is known, and said, before the first packet.
        status = report_damage(
            args.recording, player.integrity, args.allow_damaged, "only the rest is played"
        )
        player.start()
        try:
            while not player.wait(timeout=1.0):
                pass
        except KeyboardInterrupt:
            pass
        time.sleep(0.2)  # the last bytes reach the readers before the ptys close
        counters = player.counters
    sent = ", ".join(
        f"{name} {counters[f'{name}_sent']}" for name in ("lidar", "telemetry", "gnss", "wheels")
    )
    unheard = counters["gnss_unheard"] + counters["wheels_unheard"]
    print(
        f"sent: {sent} ({unheard} serial messages unheard: no reader had the pty open); "
        f"lateness median {counters['lidar_late_median_ms']:.2f} ms, "
        f"max {counters['lidar_late_max_ms']:.1f} ms"
    )
    return status
