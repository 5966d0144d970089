"""`treetraits sim`: write a simulated survey of the orchard twin as a recording."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from tqdm import tqdm

from treetraits.drivers.calibration import load_calibration
from treetraits.errors import ConfigError
from treetraits.sim.gnss import GnssSettings
from treetraits.sim.orchard import WindSettings
from treetraits.sim.paths import PATHS
from treetraits.sim.run import SurveySettings, simulate_survey

QUALITIES = {"rtk": 4, "float": 5, "dgps": 2, "autonomous": 1}


def register(commands: argparse._SubParsersAction) -> None:
    sim = commands.add_parser(
        "sim",
        help="simulate a survey of the orchard twin into a recording",
        description=(
            "Simulate the paper's 2x3 citrus grid and a robot driving it at 0.5 m/s, and "
            "write what its VLP-16, Survey3N, GNSS receiver and Jackal MCU would send, as a "
            "recording (format v1). Beside it: <out>.truth.csv (each tree's position, width "
            "and height by the traits' definitions) and <out>.field_map.geojson."
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
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--out", required=True, type=Path, help="recording to write (.mcap)")
    sim.add_argument(
        "--gnss",
        choices=sorted(QUALITIES),
        default="rtk",
        help="receiver fix quality (default rtk)",
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
    sim.add_argument("--slope", type=float, default=0.0, help="ground slope along the path")
    sim.add_argument("--goal", type=float, default=23.0, help="metres to drive (default 23)")
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
        "--calibration",
        type=Path,
        help="calibration v1 JSON (default: the bundled CitrusFarm calibration)",
    )
    sim.set_defaults(run=run_sim)


def _pair(text: str, what: str, kind=float) -> tuple:
    try:
        a, b = (kind(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"{what} must look like 5x5, got {text!r}") from None
    if a <= 0 or b <= 0:
        raise ConfigError(f"{what} must be positive, got {text!r}")
    return a, b


def run_sim(args: argparse.Namespace) -> int:
    width, length = _pair(args.grid, "--grid")
    columns, rows = _pair(args.layout, "--layout", int)
    outages = []
    for text in args.outage:
        try:
            start, end = (float(v) for v in text.split(":"))
        except ValueError:
            raise ConfigError(f"--outage must look like 10:25, got {text!r}") from None
        outages.append((start, end))
    if not 0 <= args.wind < 60:
        raise ConfigError(f"--wind is a speed in m/s in [0, 60), got {args.wind:g}")
    settings = SurveySettings(
        path=args.path,
        width=width,
        length=length,
        columns=columns,
        rows=rows,
        seed=args.seed,
        slope=args.slope,
        goal=args.goal,
        gnss=dataclasses.replace(
            GnssSettings(),
            quality=QUALITIES[args.gnss],
            dual_antenna=args.dual_antenna,
            outages=tuple(outages),
        ),
        wind=WindSettings(speed_mps=args.wind, direction_deg=args.wind_direction),
    )
    calibration = load_calibration(args.calibration) if args.calibration else None
    with tqdm(total=100, desc="sim", unit="%", leave=False, disable=None) as bar:

        def progress(fraction: float) -> None:
            bar.update(round(fraction * 100) - bar.n)

        result = simulate_survey(args.out, settings, calibration, progress)
    print(
        f"wrote {result.recording} ({result.duration_s:.1f} s of driving, "
        + ", ".join(f"{n} {topic}" for topic, n in sorted(result.counts.items()))
        + ")"
    )
    print(f"truth: {result.truth_csv}  field map: {result.field_map}")
    return 0
