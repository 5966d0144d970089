"""`treetraits sim`: write a simulated survey of the orchard twin as a recording."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from treetraits.errors import ConfigError
from treetraits.files import check_output_file
from treetraits.service.outdir import OutputDir

QUALITIES = {"rtk": 4, "float": 5, "dgps": 2, "autonomous": 1}


def register(commands: argparse._SubParsersAction) -> None:
    from treetraits.sim import PATHS

    sim = commands.add_parser(
        "sim",
        help="simulate a survey of the orchard twin into a recording",
        description=(
            "Simulate the paper's 2x3 citrus grid and a robot driving it at 0.5 m/s, and "
            "write what its VLP-16, Survey3N, GNSS receiver and Jackal MCU would send, as a "
            "recording (format v1). Beside it: <out>.truth.csv (each tree's position, width "
            "and height by the traits' definitions, and kind: tree or missing), "
            "<out>.objects.csv (every object that is not a tree) and "
            "<out>.field_map.geojson. The options below grow a real grove's conditions; "
            "without them the twin is the paper's flat, bare, uniform grid."
        ),
    )
    sim.add_argument(
        "--grid",
        default="5x5",
        metavar="WxL",
        help="tree spacing in metres across x along the path, as the paper names "
        "its grids (default 5x5; the paper also uses 4x4 and 6x6)",
    )
    sim.add_argument(
        "--layout",
        default="2x3",
        metavar="CxR",
        help="trees: columns across x rows along the path (default 2x3)",
    )
    sim.add_argument("--path", choices=PATHS, default="straight", help="default straight")
    sim.add_argument(
        "--seed", type=int, default=0, help="random seed, a non-negative integer (default 0)"
    )
    sim.add_argument("--out", required=True, type=Path, help="recording to write (.mcap)")
    sim.add_argument(
        "--force",
        action="store_true",
        help="replace an existing recording at --out and its truth, objects and field-map "
        "files (without it the simulation is refused, exit 4: a field recording is never "
        "overwritten by a simulation by mistake)",
    )
    sim.add_argument(
        "--gnss",
        choices=sorted(QUALITIES),
        default="rtk",
        help="receiver fix quality (default rtk)",
    )
    sim.add_argument(
        "--gnss-converge",
        type=float,
        metavar="SECONDS",
        help="the receiver is in RTK float for this long from the start, then reaches "
        "--gnss (a receiver converging: typically 30-120 s)",
    )
    sim.add_argument(
        "--dual-antenna", action="store_true", help="the receiver also sends a true heading (HDT)"
    )
    sim.add_argument(
        "--outage",
        action="append",
        default=[],
        metavar="START:END",
        help="seconds from the start without GNSS (repeatable)",
    )
    sim.add_argument(
        "--slope",
        type=float,
        default=0.0,
        help="ground slope along the rows (the path), rise over run, within +-0.15 "
        "(default 0); the robot pitches with the ground under its wheels",
    )
    sim.add_argument(
        "--goal", type=float, default=23.0, help="metres to drive, 0.1-1000 (default 23)"
    )
    sim.add_argument(
        "--wind",
        type=float,
        default=0.0,
        metavar="M/S",
        help="wind speed: crowns lean downwind and sway (default 0, still air; the "
        "paper's field day: 4.4 m/s)",
    )
    sim.add_argument(
        "--wind-direction",
        type=float,
        default=90.0,
        metavar="DEG",
        help="where the wind blows towards, degrees counter-clockwise from the path's "
        "direction (default 90: across the path, to the left)",
    )
    sim.add_argument(
        "--field-heading",
        type=float,
        default=0.0,
        metavar="DEG",
        help="where the rows point in the world, degrees counter-clockwise from east "
        "(default 0); the truth, field map and GNSS turn with the block",
    )
    sim.add_argument(
        "--antenna",
        metavar="X,Y,Z",
        help="the GNSS antenna's position on the robot in metres (x forward, y left, z up "
        "from base_link), written into the recording's calibration (default: the "
        "calibration's)",
    )
    sim.add_argument(
        "--lidar-height",
        type=float,
        metavar="M",
        help="the LiDAR's height above base_link in metres, 0.2-5, written into the "
        "recording's calibration (default: the calibration's; a Jackal's 0.38 m): a "
        "tractor's bonnet (~1.7) or cab (~2.6) sees the crowns' tops",
    )
    sim.add_argument(
        "--lidar-gps",
        action="store_true",
        help="the receiver also feeds the VLP-16's GPS input: its ToH counts on UTC and it "
        "sends position packets (PPS locked, $GPRMC); default: no GPS input, its ToH counts "
        "from power-on",
    )
    sim.add_argument(
        "--host-clock-offset",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="the host clock minus UTC, for a robot without NTP (default 0); every receive "
        "time carries it",
    )
    ground = sim.add_argument_group("terrain (default: flat)")
    ground.add_argument(
        "--slope-across",
        type=float,
        default=0.0,
        help="ground slope across the rows, rise over run, within +-0.08 (default 0)",
    )
    ground.add_argument(
        "--undulation",
        type=float,
        default=0.0,
        metavar="M",
        help="rolling ground: +-M metres of 4.6-11.9 m waves, 0-0.10 (default 0)",
    )
    ground.add_argument(
        "--furrows",
        type=float,
        default=0.0,
        metavar="M",
        help="furrows along the rows 1 m apart, +-M metres, 0-0.10 (default 0)",
    )
    ground.add_argument(
        "--beds", action="store_true", help="raised beds (0.25 m berms) under the tree rows"
    )
    trees = sim.add_argument_group("trees (default: the paper's uniform 2.6-2.8 m citrus)")
    trees.add_argument(
        "--young",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="fraction of young trees (1.0-1.5 m tall, 0.8-1.2 m crowns), 0-1",
    )
    trees.add_argument(
        "--old",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="fraction of old trees (~5 m tall, 4-5 m crowns), 0-1",
    )
    trees.add_argument(
        "--irregular",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="fraction of trees with lobed, lopsided crowns, 0-1",
    )
    trees.add_argument(
        "--hedgerow",
        action="store_true",
        help="3.0-3.3 m crowns: with --grid Wx2.75 (2.5-3 m in-row) they touch and overlap",
    )
    trees.add_argument(
        "--foliage",
        default="scattered",
        metavar="MODEL[,MODEL...]",
        help="how leaves fill the crowns (docs/sim_replay.md): scattered (default, the "
        "paper's twin), dense, broadleaf, clumped, sparse; several: each tree draws one",
    )
    trees.add_argument(
        "--missing",
        type=int,
        default=0,
        metavar="N",
        help="N field-map positions with no tree planted (kind=missing in the truth)",
    )
    clutter = sim.add_argument_group("objects that are not trees (default: none)")
    clutter.add_argument(
        "--weeds",
        type=int,
        default=0,
        metavar="N",
        help="N clumps of weeds / cover crop (0.1-0.6 m) in the inter-row and under trees",
    )
    clutter.add_argument(
        "--drip-lines",
        choices=("none", "ground", "hung"),
        default="none",
        help="a 2 cm drip line along each tree row, on the ground or hung at 0.35 m",
    )
    clutter.add_argument(
        "--posts", action="store_true", help="end posts (0.1 m, 1.5-2.2 m) at every row's ends"
    )
    clutter.add_argument(
        "--wires", action="store_true", help="a trellis wire at 1 m between the posts"
    )
    clutter.add_argument(
        "--people",
        action="store_true",
        help="a person standing in a tree row and one walking across the rows",
    )
    clutter.add_argument(
        "--vehicle", action="store_true", help="a pickup parked at the far headland"
    )
    clutter.add_argument(
        "--wall", action="store_true", help="a wall (8 m long, 2.5 m high) beside the grove"
    )
    sim.add_argument(
        "--no-imu",
        action="store_true",
        help="the wheel controller has no IMU (a retrofit tractor): no imu/data_raw",
    )
    sim.add_argument(
        "--calibration",
        type=Path,
        help="calibration v1 JSON (default: the bundled CitrusFarm calibration)",
    )
    sim.set_defaults(run=run_sim)


# Physical ranges of the twin's options, and why (docs/sim_replay.md).
# Orchards plant 1-12 m apart (high-density apples to old walnuts); 30 m is no orchard.
GRID_M = (0.5, 30.0)
# Trees per row and rows in the block: the twin is meant for blocks of tens of trees; a
# 10 000-tree block takes hours to simulate and is a typo.
LAYOUT = (1, 50)
# A LiDAR's height on the robot: from a small robot's deck to a mast over a tractor's cab.
LIDAR_HEIGHT_M = (0.2, 5.0)
# A survey lasts at most a day of recorded time (GNSS outages, convergence, clock offset).
DAY_S = 86400.0


def _pair(text: str, what: str, kind=float, limits: tuple = GRID_M) -> tuple:
    try:
        a, b = (kind(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"{what} must look like 5x5, got {text!r}") from None
    low, high = limits
    if not all(math.isfinite(v) and low <= v <= high for v in (a, b)):
        raise ConfigError(f"{what} values must be finite and in [{low:g}, {high:g}], got {text!r}")
    return a, b


def _outage(text: str) -> tuple[float, float]:
    """START:END seconds from the start, START before END, within a day."""
    try:
        start, end = (float(v) for v in text.split(":"))
    except ValueError:
        raise ConfigError(f"--outage must look like 10:25, got {text!r}") from None
    _within("--outage START", start, 0, DAY_S)
    _within("--outage END", end, 0, DAY_S)
    if not start < end:
        raise ConfigError(f"--outage START must come before END, got {text!r}")
    return start, end


def _antenna(text: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--antenna must look like -0.18,0,0.53, got {text!r}") from None
    for axis, value in zip("xyz", (x, y, z), strict=True):
        _within(f"--antenna {axis}", value, -5, 5)
    return x, y, z


def _foliage(text: str) -> dict:
    """TreeSettings' foliage fields from `--foliage`: one model, or a mix to draw from."""
    from treetraits.sim import FOLIAGE_MODELS as MODELS

    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in MODELS]
    if not names or unknown:
        raise ConfigError(
            f"--foliage: unknown {', '.join(map(repr, unknown)) or 'empty list'}; "
            f"choose from {', '.join(MODELS)}"
        )
    return {"foliage": names[0]} if len(names) == 1 else {"foliage_mix": names}


def _within(option: str, value: float, low: float, high: float) -> None:
    if not (math.isfinite(value) and low <= value <= high):
        raise ConfigError(f"{option} must be a finite number in [{low:g}, {high:g}], got {value}")


def _output(out: Path, force: bool, calibration: Path | None) -> OutputDir:
    """The recording and the files `simulate_survey` writes beside it, under the output
    rules (docs/cli.md); locked per recording, so several can be simulated into one
    directory at once."""
    check_output_file(out)  # a directory; an earlier recording is OutputDir's (exit 4)
    beside = (".truth.csv", ".objects.csv", ".field_map.geojson")
    owned = [out.name] + [out.with_suffix(suffix).name for suffix in beside]
    return OutputDir(
        out.parent,
        owned,
        force=force,
        inputs=[calibration],
        tag=out.name,
        what="a recording",
        target=out,
    )


def _beside(out: Path, staged: Path) -> Path:
    return out.parent / staged.name


def run_sim(args: argparse.Namespace) -> int:
    import dataclasses

    from tqdm import tqdm

    from treetraits.drivers.calibration import load_calibration
    from treetraits.sim.clutter import ClutterSettings
    from treetraits.sim.gnss import GnssSettings
    from treetraits.sim.lidar import LidarSettings
    from treetraits.sim.orchard import TerrainSettings, TreeSettings, WindSettings
    from treetraits.sim.run import SurveySettings, simulate_survey
    from treetraits.sim.wheels import WheelSettings

    width, length = _pair(args.grid, "--grid")
    columns, rows = _pair(args.layout, "--layout", int, LAYOUT)
    outages = [_outage(text) for text in args.outage]
    if not 0 <= args.wind < 60:
        raise ConfigError(f"--wind is a speed in m/s in [0, 60), got {args.wind:g}")
    _within("--wind-direction", args.wind_direction, -360, 360)
    _within("--slope", args.slope, -0.15, 0.15)
    _within("--slope-across", args.slope_across, -0.08, 0.08)
    _within("--undulation", args.undulation, 0, 0.10)
    _within("--furrows", args.furrows, 0, 0.10)
    _within("--young", args.young, 0, 1)
    _within("--old", args.old, 0, 1)
    _within("--irregular", args.irregular, 0, 1)
    _within("--goal", args.goal, 0.1, 1000)
    if args.seed < 0:  # NumPy's generators take non-negative seeds only
        raise ConfigError(f"--seed must be a non-negative integer, got {args.seed}")
    if args.young + args.old > 1:
        raise ConfigError(f"--young + --old must be <= 1, got {args.young + args.old:g}")
    if not 0 <= args.missing <= columns * rows:
        raise ConfigError(f"--missing must be in [0, {columns * rows}] trees, got {args.missing}")
    if not 0 <= args.weeds <= 5000:
        raise ConfigError(f"--weeds is a number of clumps in [0, 5000], got {args.weeds}")
    _within("--field-heading", args.field_heading, -360, 360)
    _within("--host-clock-offset", args.host_clock_offset, -DAY_S, DAY_S)
    if args.gnss_converge is not None:
        _within("--gnss-converge", args.gnss_converge, 0, DAY_S)
    if args.lidar_height is not None:
        _within("--lidar-height", args.lidar_height, *LIDAR_HEIGHT_M)
    _foliage(args.foliage)  # a ConfigError before any work
    if args.wires and not args.posts:
        raise ConfigError("--wires hang between posts: add --posts")
    settings = SurveySettings(
        path=args.path,
        width=width,
        length=length,
        columns=columns,
        rows=rows,
        seed=args.seed,
        slope=args.slope,
        goal=args.goal,
        field_heading_deg=args.field_heading,
        antenna=_antenna(args.antenna) if args.antenna else None,
        lidar_height=args.lidar_height,
        host_clock_offset_s=args.host_clock_offset,
        lidar=dataclasses.replace(LidarSettings(), gps_sync=args.lidar_gps),
        gnss=dataclasses.replace(
            GnssSettings(),
            quality=QUALITIES[args.gnss],
            dual_antenna=args.dual_antenna,
            outages=tuple(outages),
            converge_s=args.gnss_converge,
        ),
        wind=WindSettings(speed_mps=args.wind, direction_deg=args.wind_direction),
        terrain=TerrainSettings(
            slope_across=args.slope_across,
            undulation_m=args.undulation,
            furrow_m=args.furrows,
            raised_beds=args.beds,
        ),
        trees=TreeSettings(
            young_fraction=args.young,
            old_fraction=args.old,
            irregular_fraction=args.irregular,
            missing=args.missing,
            hedgerow=args.hedgerow,
            **_foliage(args.foliage),
        ),
        clutter=ClutterSettings(
            weeds=args.weeds,
            drip_lines=args.drip_lines,
            posts=args.posts,
            wires=args.wires,
            standing_people=int(args.people),
            walking_people=int(args.people),
            vehicle=args.vehicle,
            wall=args.wall,
        ),
        wheels=dataclasses.replace(WheelSettings(), imu=not args.no_imu),
    )
    output = _output(args.out, args.force, args.calibration)
    calibration = load_calibration(args.calibration) if args.calibration else None
    with (
        output as staging,
        tqdm(total=100, desc="sim", unit="%", leave=False, disable=None) as bar,
    ):

        def progress(fraction: float) -> None:
            bar.update(round(fraction * 100) - bar.n)

        # Built aside (the recording and its companions), moved into place when complete.
        result = simulate_survey(staging / args.out.name, settings, calibration, progress)
    result = dataclasses.replace(
        result,
        recording=args.out,
        truth_csv=_beside(args.out, result.truth_csv),
        field_map=_beside(args.out, result.field_map),
        objects_csv=_beside(args.out, result.objects_csv),
    )
    print(
        f"wrote {result.recording} ({result.duration_s:.1f} s of driving, "
        + ", ".join(f"{n} {topic}" for topic, n in sorted(result.counts.items()))
        + ")"
    )
    print(
        f"truth: {result.truth_csv}  objects: {result.objects_csv}  field map: {result.field_map}"
    )
    return 0
