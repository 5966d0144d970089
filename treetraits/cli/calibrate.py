"""`treetraits calibrate reflectance`: fit per-band gain and offset from a photo of the
MAPIR reflectance target and write them into a calibration file.

`treetraits calibrate classify`: replay a recording of a row whose field map is known and
propose the vegetation evidence's pivots and weights (`[detection.classify]`) that tell
its trees from everything else (statistics in `pipeline.vegetation_fit`)."""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from treetraits.damage import add_allow_damaged, report_damage
from treetraits.drivers.rosbag.detect import refuse_ros_bag
from treetraits.errors import CalibrationError, ConfigError, SourceError
from treetraits.files import check_output_file

if TYPE_CHECKING:
    import numpy as np

    from treetraits.pipeline.ndvi import BandFit, Box

DEFAULT_CHANNELS = {"red": 2, "green": 1, "nir": 0}
REQUIRED_BANDS = ("red", "nir")  # green is optional in calibration v1


def register(commands: argparse._SubParsersAction) -> None:
    calibrate = commands.add_parser(
        "calibrate",
        help="calibrate the camera's reflectance, or the tree evidence to an orchard",
        description=(
            "Calibration helpers: the camera's reflectance (calibration v1, see "
            "docs/ndvi_projection.md) and the tree/not-tree evidence (docs/pipeline.md)."
        ),
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
    _register_classify(sub)


def _register_classify(sub: argparse._SubParsersAction) -> None:
    classify = sub.add_parser(
        "classify",
        help="fit the tree evidence's pivots and weights to a row whose field map is known",
        description=(
            "Calibrate the tree/not-tree evidence (texture, planarity, NDVI, intensity: "
            "[detection.classify]) to your own orchard. Use it for a new orchard, a new crop "
            "or canopy habit (a pruned hedge, a young block), or a different sensor: drive "
            "one row you know, with GNSS, give its field map, and keep the section it "
            "proposes. The recording is replayed as `treetraits replay` does; the objects "
            "the mapper tracked are split into those at a field-map tree and everything "
            "else (posts, people, vehicles, walls, weeds), and for each cue it prints both "
            "groups' distributions (count, 10th/50th/90th percentiles), the margin between "
            "them on the side that says vegetation, and proposes a pivot in its middle (the "
            "geometric mean for the texture) and a weight: 0 where the groups overlap, the "
            "default weight where they are apart. --out writes the [detection.classify] "
            "section, for `treetraits run|replay --config FILE`."
        ),
    )
    classify.add_argument("recording", type=Path, help="a recording (.mcap) with GNSS fixes")
    classify.add_argument(
        "--field-map",
        required=True,
        type=Path,
        help="GeoJSON or CSV (id,lat,lon[,row]) of the trees of the rows driven",
    )
    classify.add_argument(
        "--calibration", type=Path, help="calibration v1 JSON (default: the recording's)"
    )
    classify.add_argument(
        "--config",
        type=Path,
        help="config file (TOML) to replay with, as `treetraits replay --config` takes",
    )
    classify.add_argument(
        "--out",
        type=Path,
        metavar="FILE",
        help="write the proposed [detection.classify] section into this TOML file",
    )
    classify.add_argument(
        "--force", action="store_true", help="replace FILE when it exists (without it: exit 4)"
    )
    classify.add_argument("--json", action="store_true", help="print the result as one JSON object")
    add_allow_damaged(classify, "proposes the section")
    classify.set_defaults(run=run_classify)


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

    for path, option in ((args.write, "--write"), (args.show, "--show")):
        if path is not None:
            check_output_file(path, option)  # --write's file is updated: it may exist
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


# --- calibrate classify --------------------------------------------------------------


def collect_cues(
    recording: Path, field_map: Path, calibration: Path | None, config: Path | None
) -> dict[str, Any]:
    """Replay `recording` (as `treetraits replay`, outputs in a temporary directory) and
    group the mapper's objects: `trees`, those the replay matched to a field-map tree, with
    the rejected objects standing at a field-map tree no found tree matched; `others`,
    those farther than the match gate from every field-map tree; `near`, the rest (pieces
    of a matched tree's crown: neither group). Each object: its cues, kind and field id."""
    import tempfile

    import numpy as np

    from treetraits.pipeline.georef import FieldMapIndex
    from treetraits.service.config import load_config
    from treetraits.service.replay import ReplayOptions, open_replay, run_replay

    cfg = load_config(config)
    options = ReplayOptions(config=cfg, field_map=field_map, calibration=calibration)
    inputs = open_replay(recording, options)
    try:
        with tempfile.TemporaryDirectory(prefix="treetraits-calibrate-") as out:
            report = run_replay(recording, Path(out), options, inputs=inputs)
    finally:
        inputs.source.close()
    gate = cfg.output.match_gate_m
    records = {str(t.tree_id): t for t in report.mapped}
    found = [t for t in report.trees if t.status == "found"]
    matched_ids = {t.field_id for t in found if t.field_id is not None}
    trees = [(t, t.field_id) for t in found if t.field_id is not None]
    others, near = [], []
    unmatched = [f for f in inputs.field_map if f.id not in matched_ids]
    candidates = [t for t in found if t.field_id is None] + list(report.rejected)
    placed = [t for t in candidates if t.easting is not None and t.northing is not None]
    if report.grid is not None and placed:
        xy = np.array([(t.easting, t.northing) for t in placed], dtype=float)
        free = FieldMapIndex(unmatched, report.grid)
        taken = free.match(xy, gate)
        every = FieldMapIndex(inputs.field_map, report.grid)
        for i, (tree, j) in enumerate(zip(placed, taken, strict=True)):
            if j is not None:
                trees.append((tree, free.trees[j].id))
            elif len(every) and np.hypot(*(every.xy - xy[i]).T).min() <= gate:
                near.append(tree)
            else:
                others.append(tree)
    else:
        others = placed

    def entry(tree, field_id=None) -> dict[str, Any]:
        record = records.get(tree.tree_id)
        cues = {
            cue.name: _finite(getattr(record, cue.field, None)) if record else None
            for cue in _cues()
        }
        kind = getattr(record, "kind", tree.reason or "tree") if record else tree.reason
        return {"id": tree.tree_id, "field_id": field_id, "kind": kind, **cues}

    return {
        "summary": report.summary,
        "field_map_trees": len(inputs.field_map),
        "trees": [entry(t, f) for t, f in trees],
        "others": [entry(t) for t in others],
        "near": [entry(t) for t in near],
        "found_matched": len(matched_ids),
        "gate_m": gate,
    }


def _cues():
    from treetraits.pipeline.vegetation_fit import CUES

    return CUES


def _finite(value: Any) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if value == value and abs(value) != float("inf") else None


def classify_toml(section: Mapping[str, float], recording: Path, counts: str) -> str:
    """The `[detection.classify]` section as a config file's text."""
    lines = [
        f"# treetraits calibrate classify: proposed from {recording.name} ({counts}).",
        "# Keep it as a config file, or paste the section into yours: treetraits run|replay "
        "--config FILE",
        "[detection.classify]",
        *(f"{key} = {value!r}" for key, value in section.items()),
    ]
    return "\n".join(lines) + "\n"


def _write_classify(path: Path, text: str) -> None:
    """Write `text` to `path` once the project's config loader accepts it."""
    import tempfile

    from treetraits.files import write_atomically
    from treetraits.service.config import load_config

    with tempfile.TemporaryDirectory() as folder:
        check = Path(folder) / "classify.toml"
        check.write_text(text)
        load_config(check)  # a ConfigError here is a bug of ours: exit 2 with its message
    write_atomically(path, lambda f: f.write(text))


def run_classify(args: argparse.Namespace) -> int:
    from treetraits.pipeline.vegetation_fit import propose_all, section

    if args.out is not None:
        check_output_file(args.out, force=args.force)
    refuse_ros_bag(args.recording, "a recording")  # a bag: the import to run first
    for path, what in ((args.recording, "recording"), (args.field_map, "field map")):
        if not path.is_file():
            raise SourceError(f"{path}: no such {what} file")
    data = collect_cues(args.recording, args.field_map, args.calibration, args.config)
    status = report_damage(
        args.recording, data["summary"], args.allow_damaged, "the cues are of the rest"
    )
    if not data["trees"]:
        fixes = data["summary"].get("fixes")
        raise ConfigError(
            f"{args.recording}: no object stands at a tree of {args.field_map} "
            f"({data['field_map_trees']} trees on it): calibrating needs a recording with "
            "GNSS fixes and a field map covering the rows it drove"
            + (f" (GNSS fixes in the recording: {fixes})" if fixes is not None else "")
        )
    if not data["others"]:
        raise ConfigError(
            f"{args.recording}: every object stands at a field-map tree: nothing else to "
            "tell the trees from (drive past a post, a vehicle, a wall, people)"
        )
    groups = {
        name: {cue.name: [o[cue.name] for o in data[name]] for cue in _cues()}
        for name in ("trees", "others")
    }
    proposals = propose_all(groups["trees"], groups["others"])
    keys = section(proposals)
    counts = (
        f"{len(data['trees'])} objects at field-map trees, {len(data['others'])} others, "
        f"{len(data['near'])} beside a matched tree left out"
    )
    if args.out is not None:
        _write_classify(args.out, classify_toml(keys, args.recording, counts))
    if args.json:
        print(
            json.dumps(
                {
                    "recording": str(args.recording),
                    "field_map": str(args.field_map),
                    "field_map_trees": data["field_map_trees"],
                    "matched": len(data["trees"]),
                    "matched_as_trees": data["found_matched"],
                    "others": len(data["others"]),
                    "near": len(data["near"]),
                    "gate_m": data["gate_m"],
                    "cues": [
                        {
                            "cue": p.cue,
                            "trees": _dist(p.trees),
                            "others": _dist(p.others),
                            "margin": _finite(p.margin),
                            "pivot": p.pivot,
                            "weight": p.weight,
                            "note": p.note,
                        }
                        for p in proposals
                    ],
                    "section": {"detection": {"classify": keys}},
                    # Each object's cues (None: not measured), for a look of one's own.
                    "objects": {name: data[name] for name in ("trees", "others", "near")},
                    "written": str(args.out) if args.out else None,
                },
                indent=1,
            )
        )
        return status
    print(
        f"{args.recording}: {counts} "
        f"({data['found_matched']} of {data['field_map_trees']} field-map trees found as trees)"
    )
    print(
        f"  {'cue':<10}{'group':<8}{'n':>5}{'p10':>10}{'p50':>10}{'p90':>10}"
        f"{'margin':>10}{'pivot':>10}{'weight':>8}  note"
    )
    for p in proposals:
        for label, dist in (("trees", p.trees), ("others", p.others)):
            row = f"  {p.cue if label == 'trees' else '':<10}{label:<8}{dist.count:>5}"
            row += "".join(f"{_num(v):>10}" for v in (dist.p10, dist.p50, dist.p90))
            if label == "trees":
                pivot = _num(p.pivot) if p.pivot is not None else "keep"
                weight = f"{p.weight:g}" if p.weight is not None else "keep"
                row += f"{_num(p.margin):>10}{pivot:>10}{weight:>8}  {p.note}"
            print(row)
    print("[detection.classify]")
    for key, value in keys.items():
        print(f"{key} = {value!r}")
    if args.out is not None:
        print(f"wrote the [detection.classify] section to {args.out}")
    return status


def _dist(d) -> dict[str, Any]:
    return {"count": d.count, "p10": _finite(d.p10), "p50": _finite(d.p50), "p90": _finite(d.p90)}


def _num(value: float | None) -> str:
    if value is None or value != value:
        return "-"
    return f"{value:.4g}"
