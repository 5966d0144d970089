"""`treetraits calibrate reflectance`: fit per-band gain and offset from a photo of the
MAPIR reflectance target and write them into a calibration file."""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from treetraits.errors import CalibrationError, ConfigError, SourceError

if TYPE_CHECKING:
    import numpy as np

    from treetraits.pipeline.ndvi import BandFit, Box

DEFAULT_CHANNELS = {"red": 2, "green": 1, "nir": 0}
REQUIRED_BANDS = ("red", "nir")  # green is optional in calibration v1


def register(commands: argparse._SubParsersAction) -> None:
    calibrate = commands.add_parser(
        "calibrate",
        help="calibrate the camera's reflectance from a photo of the MAPIR target",
        description="Calibration helpers (calibration v1, see docs/ndvi_projection.md).",
    )
    sub = calibrate.add_subparsers(dest="calibrate_command", metavar="COMMAND", required=True)
    refl = sub.add_parser(
        "reflectance",
        help="fit reflectance = gain * raw + offset per band from a target photo",
        description=(
            "Fit, per band, reflectance = gain * raw + offset (least squares over the "
            "target's panels) from a photo taken with the same exposure, gain and white "
            "balance as the field run (lock them first). Panels are found through the "
            "target V2's ArUco marker, or given with --box, brightest panel first. "
            "Prints the fit; --write puts the `reflectance` section into a calibration file."
        ),
    )
    refl.add_argument("image", type=Path, help="the target photo (JPEG or PNG, as streamed)")
    refl.add_argument(
        "--box",
        action="append",
        type=_box,
        metavar="X,Y,W,H",
        help="a panel's sample rectangle in pixels; once per panel, brightest first",
    )
    refl.add_argument(
        "--calibration", type=Path, help="calibration v1 JSON whose camera.channels to use"
    )
    refl.add_argument(
        "--target",
        type=Path,
        help="JSON {band: [panel reflectances, brightest first]} (default: MAPIR target V2)",
    )
    refl.add_argument(
        "--write",
        type=Path,
        metavar="FILE",
        help="put the fitted `reflectance` section into this calibration JSON (created if "
        "missing, other sections kept)",
    )
    refl.add_argument("--show", type=Path, metavar="PNG", help="draw the sampled panels here")
    refl.add_argument("--json", action="store_true", help="print the result as JSON")
    refl.set_defaults(run=run_reflectance)


def _box(text: str) -> Box:
    from treetraits.pipeline.ndvi import Box

    try:
        return Box.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _read_json(path: Path, what: str) -> Any:
    from treetraits.drivers.jsontext import JsonTooDeepError, loads_limited

    try:
        return loads_limited(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such {what} file") from None
    except JsonTooDeepError as exc:
        raise ConfigError(f"{path}: {exc}: not a {what} file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: {what} file is not valid JSON ({exc})") from exc


def _channels(args: argparse.Namespace) -> dict[str, int]:
    from treetraits.drivers.calibration import load_calibration

    for path in (args.calibration, args.write):
        if path is not None and (path == args.calibration or path.exists()):
            calibration = load_calibration(path)
            if calibration.camera is not None:
                return dict(calibration.camera.channels)
    return dict(DEFAULT_CHANNELS)


def _target(path: Path | None) -> dict[str, tuple[float, ...]]:
    from treetraits.pipeline.ndvi import MAPIR_TARGET_V2

    if path is None:
        return dict(MAPIR_TARGET_V2)
    data = _read_json(path, "target")
    if not isinstance(data, Mapping) or not all(
        isinstance(v, list) and all(isinstance(x, int | float) for x in v) for v in data.values()
    ):
        raise ConfigError(f"{path}: expected {{band: [reflectance, ...]}} with numbers")
    missing = [b for b in REQUIRED_BANDS if b not in data]
    if missing:
        raise ConfigError(f"{path}: no panel reflectances for {missing}")
    return {band: tuple(float(x) for x in values) for band, values in data.items()}


def run_reflectance(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from treetraits.pipeline.ndvi import find_target_v2, fit_reflectance, sample_panels

    if not args.image.is_file():
        raise SourceError(f"{args.image}: no such file (expected a JPEG or PNG of the target)")
    image = cv2.imread(str(args.image), cv2.IMREAD_COLOR)
    if image is None:
        raise SourceError(f"{args.image}: not a readable image (expected a JPEG or PNG)")
    channels = _channels(args)
    target = _target(args.target)
    panels = len(next(iter(target.values())))
    if args.box:
        if len(args.box) != panels:
            raise ConfigError(f"{len(args.box)} --box given, the target has {panels} panels")
        boxes, how = list(args.box), "boxes given"
    else:
        boxes, corners = find_target_v2(image)
        how = f"target V2 marker at {np.round(corners.mean(axis=0)).astype(int).tolist()}"
    sample = sample_panels(image, boxes, {b: c for b, c in channels.items() if b in target})
    fits: dict[str, BandFit] = {}
    problems: list[str] = []
    for band in target:
        if band not in sample.mean:
            continue
        try:
            fits[band] = fit_reflectance(sample, {band: target[band]})[band]
        except CalibrationError as exc:
            if band in REQUIRED_BANDS:
                raise
            problems.append(f"{band} left out: {exc}")  # green is optional
    section = {band: [fit.gain, fit.offset] for band, fit in fits.items()}

    if args.show is not None:
        _show(args.show, image, boxes)
    if args.write is not None:
        _write_reflectance(args.write, section)

    if args.json:
        print(
            json.dumps(
                {
                    "image": str(args.image),
                    "panels": how,
                    "boxes": [str(b) for b in boxes],
                    "channels": channels,
                    "fits": {
                        b: {
                            "gain": f.gain,
                            "offset": f.offset,
                            "r2": f.r2,
                            "max_residual": f.max_residual,
                            "panels_used": [i + 1 for i in f.used],
                            "panel_means": f.raw,
                            "panel_reflectance": f.target,
                            "notes": list(f.notes),
                        }
                        for b, f in fits.items()
                    },
                    "problems": problems,
                    "reflectance": section,
                    "written": str(args.write) if args.write else None,
                },
                indent=1,
            )
        )
        return 0
    print(f"{args.image}: {how}; channels {channels}")
    print(f"  {'panel':<6}{'box':<20}" + "".join(f"{b:>9}" for b in sample.mean))
    for i, box in enumerate(boxes):
        means = "".join(f"{sample.mean[b][i]:9.1f}" for b in sample.mean)
        print(f"  {i + 1:<6}{box!s:<20}{means}")
    print(f"  {'band':<6}{'gain':>12}{'offset':>12}{'R²':>9}{'max resid':>11}  panels")
    for band, fit in fits.items():
        used = ",".join(str(i + 1) for i in fit.used)
        print(
            f"  {band:<6}{fit.gain:12.6g}{fit.offset:12.5f}{fit.r2:9.5f}"
            f"{fit.max_residual:11.4f}  {used}"
        )
        for note in fit.notes:
            print(f"    {band}: {note}")
    for problem in problems:
        print(f"  {problem}")
    print(json.dumps({"reflectance": section}))
    if args.write is not None:
        print(f"wrote the reflectance section to {args.write}")
    return 0


def _write_reflectance(path: Path, section: dict[str, list[float]]) -> None:
    """Replace the `reflectance` section of `path` (other sections kept), checked by the
    calibration loader before the file is atomically replaced."""
    from treetraits.drivers.calibration import Calibration, load_calibration

    data: dict[str, Any] = {}
    if path.exists():
        data = _read_json(path, "calibration")
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a JSON object (calibration v1)")
    data["reflectance"] = section
    try:
        # A new file holds only the reflectance: checked on the defaults' geometry, it
        # still needs the robot's own (T_base_lidar...) before a command takes it.
        load_calibration(data if path.exists() else {**Calibration().to_json(), **data})
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: not written: {exc}") from exc
    text = json.dumps(data, indent=2) + "\n"
    from treetraits.files import write_atomically

    # Owner-only (0600), the mode mkstemp gave the file here: opening it to all readers
    # is a decision of its own, not a side effect of sharing the writer.
    write_atomically(path, lambda f: f.write(text), permissions=0o600)


def _show(path: Path, image: np.ndarray, boxes: list[Box]) -> None:
    import cv2

    picture = image.copy()
    for i, box in enumerate(boxes):
        cv2.rectangle(
            picture, (box.x, box.y), (box.x + box.w - 1, box.y + box.h - 1), (0, 0, 255), 2
        )
        cv2.putText(
            picture,
            str(i + 1),
            (box.x, max(box.y - 4, 10)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.6,
            (0, 0, 255),
            2,
        )
    if not cv2.imwrite(str(path), picture):
        raise SourceError(f"{path}: could not write the picture")
