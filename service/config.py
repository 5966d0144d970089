"""The service's configuration: a TOML file, validated at start, every key optional.

`load_config(path)` reads the file (None: the defaults) and returns a frozen
`ServiceConfig`; a bad value, a wrong type or an unknown key raises `ConfigError` naming
`section.key` (and the nearest known key for a typo). Relative paths are taken from the
config file's directory, so `dump_config` always prints absolute ones and reading its
output back gives an equal config.

The pipeline's sections ([detection], [tracking], [traits], [localization]) are the very
dataclasses the algorithms take (`pipeline.config`, `pipeline.localization.config`):
a key is a field, its default the field's default, its help the comment above the field,
and the dataclass checks its own values. `treetraits replay --config` and `eval --config`
read the same file.
"""

from __future__ import annotations

import ast
import difflib
import functools
import inspect
import ipaddress
import json
import math
import sys
import textwrap
from dataclasses import MISSING, Field, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any

from treetraits.drivers.velodyne.models import model_by_name
from treetraits.errors import ConfigError
from treetraits.pipeline.config import (
    METHODS,
    TRAIT_METHODS,
    DetectionConfig,
    MapperConfig,
    TrackingConfig,
    TraitsConfig,
)
from treetraits.pipeline.georef import DEFAULT_GATE_M
from treetraits.pipeline.localization.config import LocalizationConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

WHEEL_KINDS = ("jackal", "bridge")
LOG_LEVELS = ("debug", "info", "warning", "error")


# --- per-field checks (metadata of the dataclass fields) -------------------------------


def _key(help_text: str, *, check=None, path: bool = False) -> dict[str, Any]:
    return {"help": help_text, "check": check, "path": path}


def _positive(value: float) -> str | None:
    return None if value > 0 else "must be > 0"


def _between(low: float, high: float):
    """Within a physical range (closed), named in the message: a finite number that no
    robot can mean (an hour's timeout, a 10^18-item queue) is a typo, not a setting."""

    def check(value: float) -> str | None:
        return None if low <= value <= high else f"must be in [{_plain(low)}, {_plain(high)}]"

    return check


def _plain(number: float) -> str:
    """1000000, not 1e+06; 0.01 as it is."""
    return str(int(number)) if float(number).is_integer() else f"{number:g}"


# Upper bounds of the service's numbers, and why (docs/service.md).
MAX_PERIOD_S = 3600.0  # a timeout, period or status interval over an hour is no setting
MAX_SOCKET_BUFFER = 2**31 - 1  # SO_RCVBUF is a C int in the kernel
MAX_BAUD = 4_000_000  # the fastest rate Linux's termios offers (B4000000)
MAX_QUEUE = 1_000_000  # a million LiDAR packets is 1.2 GB of memory, 22 min of data
MAX_FILE_MB = 1024 * 1024  # 1 TiB: beyond any disk the robot carries
MAX_GATE_M = 100.0  # a field-map match or "passed by" 100 m away is another block


def _at_least(minimum: int):
    return lambda value: None if value >= minimum else f"must be >= {minimum}"


def _port(allow_zero: bool):
    low = 0 if allow_zero else 1
    return lambda value: None if low <= value <= 65535 else f"must be a port in {low}..65535"


def _one_of(choices: tuple[str, ...]):
    return lambda value: None if value in choices else f"must be one of {', '.join(choices)}"


def _ip(value: str) -> str | None:
    try:
        ipaddress.ip_address(value)
    except ValueError:
        return "must be an IPv4 or IPv6 address"
    return None


def _optional_ip(value: str) -> str | None:
    return None if value == "" else _ip(value)


def _lidar_model(value: str) -> str | None:
    try:
        model_by_name(value)
    except ValueError as exc:
        return str(exc)
    return None


def _nonempty(value: str) -> str | None:
    return None if value.strip() else "must not be empty"


# --- the schema ------------------------------------------------------------------------


@dataclass(frozen=True)
class OutputConfig:
    dir: str = field(
        default="/var/lib/treetraits",
        metadata=_key(
            "each start makes dir/runs/<UTC start>/ (traits.sqlite, trees.geojson, "
            "trees.csv); dir/runs/latest points at it",
            check=_nonempty,
            path=True,
        ),
    )
    export_every_s: float = field(
        default=5.0,
        metadata=_key(
            "trees.geojson / trees.csv rewritten atomically this often, and at exit",
            check=_between(0.01, MAX_PERIOD_S),
        ),
    )
    # Every export rewrites every tree, so its cost grows with the survey (docs/
    # performance.md, "Exports at 50,000 trees"), and more on the robot's slower cores.
    # The store holds every scan as it comes; the files are a view of it, and a view a
    # few seconds older costs the scans nothing.
    export_max_share: float = field(
        default=0.02,
        metadata=_key(
            "exports take at most this share of the time: a slow one (a big survey) "
            "waits longer than export_every_s for the next",
            check=_between(0.001, 1.0),
        ),
    )
    # A stray cluster at the edge of view is seen once; at 10 Hz a real tree in range is
    # seen in dozens of scans.
    min_observations: int = field(
        default=3,
        metadata=_key("a tree seen in fewer scans is not reported", check=_at_least(1)),
    )
    match_gate_m: float = field(
        default=DEFAULT_GATE_M,
        metadata=_key(
            "a tree is matched to the nearest field-map tree within this distance (m)",
            check=_between(0.01, MAX_GATE_M),
        ),
    )
    # The rows either side of the robot's lane: in groves planted 5-7 m between rows they
    # are 2.5-3.5 m away, the rows beyond them 7.5 m and more, hidden behind the first. A
    # tree within 6 m is in full view of tens of scans: not found there means not there.
    missing_range_m: float = field(
        default=6.0,
        metadata=_key(
            "a field-map tree the robot passed within this distance (m) and did not find is "
            "reported missing",
            check=_between(0.01, MAX_GATE_M),
        ),
    )


@dataclass(frozen=True)
class PipelineConfig:
    method: str = field(
        default="paper", metadata=_key("paper | rph | rph-vlp16", check=_one_of(METHODS))
    )
    calibration: str = field(
        default="",
        metadata=_key('calibration v1 JSON; "" = built-in default calibration', path=True),
    )
    field_map: str = field(
        default="", metadata=_key('GeoJSON or CSV field map; "" = none', path=True)
    )
    workers: int = field(
        default=0,
        metadata=_key(
            "threads for the per-scan work: 2 detects each scan beside the tracking of "
            "the one before (same outputs), 1 does both in turn; 0 = 2 in the live service "
            "(its loop thread stays light), 1 in replay and the offline tools (no faster there)",
            check=_between(0, 2),
        ),
    )
    detect_in: str = field(
        default="auto",
        metadata=_key(
            "where workers = 2 detects: thread | process | auto (a thread in the live "
            "service: no second interpreter to start; a process in replay and the offline "
            "tools, where a thread waits on the GIL)",
            check=_one_of(("auto", "thread", "process")),
        ),
    )


@dataclass(frozen=True)
class LidarConfig:
    enabled: bool = field(default=True, metadata=_key("read the VLP-16"))
    bind: str = field(default="0.0.0.0", metadata=_key("address to listen on", check=_ip))
    data_port: int = field(default=2368, metadata=_key("UDP data port", check=_port(False)))
    telemetry_port: int = field(
        default=8308, metadata=_key("0 = do not listen for telemetry", check=_port(True))
    )
    sensor_ip: str = field(
        default="",
        metadata=_key(
            '"" = accept any sender; else foreign senders are dropped and counted',
            check=_optional_ip,
        ),
    )
    rcvbuf_bytes: int = field(
        default=8388608,
        metadata=_key(
            "SO_RCVBUF asked for (capped at net.core.rmem_max)",
            check=_between(1, MAX_SOCKET_BUFFER),
        ),
    )
    model: str = field(
        default="auto", metadata=_key("auto | vlp16 | puck-lite | puck-hires", check=_lidar_model)
    )
    silence_s: float = field(
        default=1.0,
        metadata=_key(
            "no packet for this long -> lidar DEGRADED", check=_between(0.01, MAX_PERIOD_S)
        ),
    )


@dataclass(frozen=True)
class CameraConfig:
    enabled: bool = field(default=True, metadata=_key("read the Survey3N"))
    device: str = field(
        default="auto",
        metadata=_key(
            "auto | usb:VID:PID | /dev/videoN | /dev/survey3n | a video file (played at its "
            "frame rate, stamped on read; for tests)",
            check=_nonempty,
        ),
    )
    silence_s: float = field(
        default=2.0,
        metadata=_key(
            "no frame for this long -> camera DEGRADED", check=_between(0.01, MAX_PERIOD_S)
        ),
    )


@dataclass(frozen=True)
class GnssConfig:
    enabled: bool = field(default=True, metadata=_key("read the GNSS receiver"))
    port: str = field(default="/dev/gnss", metadata=_key("serial device", check=_nonempty))
    baudrate: int = field(
        default=115200, metadata=_key("serial speed", check=_between(50, MAX_BAUD))
    )
    silence_s: float = field(
        default=3.0,
        metadata=_key(
            "no sentence for this long -> gnss DEGRADED", check=_between(0.01, MAX_PERIOD_S)
        ),
    )


@dataclass(frozen=True)
class WheelsConfig:
    enabled: bool = field(default=True, metadata=_key("read wheel odometry"))
    kind: str = field(
        default="jackal",
        metadata=_key(
            "jackal (rosserial MCU) | bridge (retrofit encoder board)",
            check=_one_of(WHEEL_KINDS),
        ),
    )
    port: str = field(default="/dev/jackal", metadata=_key("serial device", check=_nonempty))
    baudrate: int = field(
        default=115200, metadata=_key("serial speed", check=_between(50, MAX_BAUD))
    )
    silence_s: float = field(
        default=2.0,
        metadata=_key(
            "no bytes for this long -> wheels DEGRADED", check=_between(0.01, MAX_PERIOD_S)
        ),
    )


@dataclass(frozen=True)
class RecordConfig:
    enabled: bool = field(default=False, metadata=_key("`treetraits run --record` turns it on"))
    dir: str = field(
        default="/var/lib/treetraits/recordings",
        metadata=_key("recordings go here, one per start", check=_nonempty, path=True),
    )
    max_file_mb: int = field(
        default=1024,
        metadata=_key("rotate to a new file past this size", check=_between(1, MAX_FILE_MB)),
    )
    chunk_kb: int = field(
        default=512,
        metadata=_key(
            "MCAP chunk size: about one second of all sensors", check=_between(1, MAX_FILE_MB)
        ),
    )
    fsync_every_s: float = field(
        default=1.0,
        metadata=_key("longest time between two fsyncs", check=_between(0.01, MAX_PERIOD_S)),
    )


@dataclass(frozen=True)
class QueuesConfig:
    lidar_packets: int = field(
        default=8000, metadata=_key("~10 s at 754 packets/s", check=_between(1, MAX_QUEUE))
    )
    camera_frames: int = field(
        default=16, metadata=_key("JPEG frames", check=_between(1, MAX_QUEUE))
    )
    gnss_sentences: int = field(
        default=2000, metadata=_key("NMEA sentences", check=_between(1, MAX_QUEUE))
    )
    wheel_chunks: int = field(
        default=2000, metadata=_key("serial reads from the wheels", check=_between(1, MAX_QUEUE))
    )


@dataclass(frozen=True)
class ServiceSection:
    status_every_s: float = field(
        default=2.0,
        metadata=_key("STATUS= line to systemd and a log line", check=_between(0.01, MAX_PERIOD_S)),
    )
    log_level: str = field(
        default="info", metadata=_key("debug | info | warning | error", check=_one_of(LOG_LEVELS))
    )
    max_backlog_s: float = field(
        default=0.5,
        metadata=_key(
            "a scan ready while the loop is this far behind its sensors is not mapped "
            "(counted, scans_shed): a host too slow for every scan maps some, and loses no "
            "packet or frame from a full queue; 0: never",
            check=_between(0.0, MAX_PERIOD_S),
        ),
    )


SECTION_HELP = {
    "queues": "bounded; a receiver never blocks: when full the NEWEST item is dropped and counted",
    "detection": "per scan: crop box, ground, clusters (reasons: docs/pipeline.md)",
    "tracking": "one Kalman filter per tree, the paper's gates (docs/pipeline.md)",
    "traits": "width and height per tree: paper | robust (docs/pipeline.md)",
    "localization": "wheels + GNSS filter (reasons: docs/localization.md)",
    "localization.sigma_per_hdop": "metres of 1-sigma per unit of HDOP, by GGA quality",
}


@dataclass(frozen=True)
class ServiceConfig:
    output: OutputConfig = field(default_factory=OutputConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    detection: DetectionConfig = field(default_factory=DetectionConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    traits: TraitsConfig = field(default_factory=TraitsConfig)
    localization: LocalizationConfig = field(default_factory=LocalizationConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    wheels: WheelsConfig = field(default_factory=WheelsConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    queues: QueuesConfig = field(default_factory=QueuesConfig)
    service: ServiceSection = field(default_factory=ServiceSection)

    def mapper(self) -> MapperConfig:
        """The tree pipeline's settings (method `paper`)."""
        return MapperConfig(self.detection, self.tracking, self.traits)


# --- reading ---------------------------------------------------------------------------


def load_config(path: Path | None) -> ServiceConfig:
    """The config in `path` (None: every default). ConfigError names the file and the key."""
    if path is None:
        return ServiceConfig()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(
            f"{path}: no such config file; write one (`treetraits config dump > {path}` "
            "prints the defaults) or point --config at it"
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the config file ({exc})") from None
    try:
        document = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{path}: TOML nested too deeply to be a config") from None
    return parse_config(document, base=path.resolve().parent, source=str(path))


def parse_config(document: dict[str, Any], base: Path, source: str = "config") -> ServiceConfig:
    """A parsed TOML document to a checked config; relative paths resolved against `base`."""
    sections = {f.name: f for f in fields(ServiceConfig)}
    for name, content in document.items():
        if name not in sections:
            raise ConfigError(f"{source}: unknown section [{name}]{_nearest(name, sections)}")
        if not isinstance(content, dict):
            raise ConfigError(f"{source}: {name} must be a [{name}] table of keys")
    return _parse_table(ServiceConfig, document, "", base, source)


def _parse_table(table_type, content: dict, where: str, base: Path, source: str):
    """One TOML table into the dataclass `table_type` (sub-tables into nested dataclasses);
    the dataclass's own checks run on construction and are reported with `source`."""
    known = {f.name: f for f in fields(table_type)}
    values = {}
    for key, raw in content.items():
        name = f"{where}.{key}" if where else key
        if key not in known:
            raise ConfigError(f"{source}: unknown key {name}{_nearest(key, known, where)}")
        spec = known[key]
        default = _default(spec)
        if is_dataclass(default):
            if not isinstance(raw, dict):
                raise ConfigError(f"{source}: {name} must be a [{name}] table of keys")
            values[key] = _parse_table(type(default), raw, name, base, source)
            continue
        value = _typed(raw, default, name, source)
        check = spec.metadata.get("check")
        problem = check(value) if check else None
        if problem:
            raise ConfigError(f"{source}: {name} {problem}, got {_show(raw)}")
        if spec.metadata.get("path") and value and not Path(value).is_absolute():
            value = str((base / value).resolve())
        if name == "camera.device":
            value = _camera_device(value, base)
        values[key] = value
    try:
        return table_type(**values)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _default(spec: Field) -> Any:
    if spec.default_factory is not MISSING:
        return spec.default_factory()
    return spec.default


_TYPE_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def _typed(raw: Any, default: Any, where: str, source: str) -> Any:
    """`raw` as the type of the key's default: bool, int, float (an int is fine), str, a
    fixed-length array (tuple) or a table of numbers keyed by integers (dict)."""
    if isinstance(default, tuple):
        if not isinstance(raw, list) or len(raw) != len(default):
            raise ConfigError(
                f"{source}: {where} must be an array of {len(default)} values, got {_show(raw)}"
            )
        return tuple(
            _typed(item, d, f"{where}[{i}]", source)
            for i, (item, d) in enumerate(zip(raw, default, strict=True))
        )
    if isinstance(default, dict):
        if not isinstance(raw, dict):
            raise ConfigError(f"{source}: {where} must be a table, got {_show(raw)}")
        sample = next(iter(default.values()))
        typed = {}
        for key, value in raw.items():
            try:
                number = int(key)
            except ValueError:
                raise ConfigError(
                    f"{source}: {where}: keys must be integers, got {key!r}"
                ) from None
            typed[number] = _typed(value, sample, f"{where}.{key}", source)
        return typed
    kind = type(default)
    if kind is bool:
        ok = isinstance(raw, bool)
    elif kind is int:
        ok = isinstance(raw, int) and not isinstance(raw, bool)
    elif kind is float:
        ok = isinstance(raw, int | float) and not isinstance(raw, bool)
        if ok and not math.isfinite(raw):
            raise ConfigError(f"{source}: {where} must be a finite number, got {_show(raw)}")
    else:
        ok = isinstance(raw, str)
    if not ok:
        raise ConfigError(f"{source}: {where} must be {_TYPE_NAMES[kind]}, got {_show(raw)}")
    return kind(raw)


def _camera_device(value: str, base: Path) -> str:
    """A video-file device relative to the config file; device specs are left alone."""
    if value == "auto" or value.startswith(("usb:", "/")) or value.isdigit():
        return value
    return str((base / value).resolve())


def _nearest(word: str, known, section: str | None = None) -> str:
    close = difflib.get_close_matches(word, list(known), n=1, cutoff=0.6)
    if not close:
        listed = ", ".join(known)
        return f"; known: {listed}"
    return f"; did you mean {section + '.' if section else ''}{close[0]}?"


def _show(value: Any) -> str:
    return json.dumps(value) if isinstance(value, str) else repr(value)


# --- writing ---------------------------------------------------------------------------


def dump_config(cfg: ServiceConfig, comments: bool = True) -> str:
    """`cfg` as TOML that `load_config` reads back to an equal config; with `comments`,
    each key is followed by what it does (and its default where the value differs)."""
    lines: list[str] = []
    for section in fields(ServiceConfig):
        _dump_table(section.name, getattr(cfg, section.name), comments, lines)
    return "\n".join(lines)


def _dump_table(name: str, content: Any, comments: bool, lines: list[str]) -> None:
    header = f"[{name}]"
    if comments and name in SECTION_HELP:
        header = f"{header:<34} # {SECTION_HELP[name]}"
    lines.append(header)
    helps = field_help(type(content))
    nested = []
    for spec in fields(content):
        value = getattr(content, spec.name)
        if is_dataclass(value):
            nested.append((f"{name}.{spec.name}", value))
            continue
        assignment = f"{spec.name} = {_toml_value(value)}"
        if comments:
            note = helps.get(spec.name, "")
            default = _default(spec)
            if value != default:
                note = f"{note} [default {_toml_value(default)}]".strip()
            assignment = f"{assignment:<34} # {note}" if note else assignment
        lines.append(assignment.rstrip())
    lines.append("")
    for sub_name, sub_content in nested:  # TOML: a table's keys before its sub-tables
        _dump_table(sub_name, sub_content, comments, lines)


@functools.cache
def field_help(table_type: type) -> dict[str, str]:
    """The help `config dump` gives each key of a section: the field's `_key` help where it
    has one (the service's own sections, written as help), else the first sentence of
    the comment above the field (the pipeline's sections: the reasons for their values
    live there, once, and the help is taken from them)."""
    helps = _comment_help(table_type)
    for spec in fields(table_type):
        if spec.metadata.get("help"):
            helps[spec.name] = spec.metadata["help"]
    return helps


def _comment_help(table_type: type) -> dict[str, str]:
    """The first sentence of the comment above each field of a dataclass (or of the comment
    beside it, when there is none above)."""
    try:
        source = textwrap.dedent(inspect.getsource(table_type))
    except (OSError, TypeError):
        return {}
    lines = source.splitlines()
    helps = {}
    for node in ast.parse(source).body[0].body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        row, comment = node.lineno - 2, []
        while row >= 0 and lines[row].strip().startswith("#"):
            comment.insert(0, lines[row].strip().lstrip("#").strip())
            row -= 1
        inline = lines[node.lineno - 1].partition("  # ")[2].strip()
        text = " ".join(comment) or inline
        if text:
            helps[node.target.id] = _first_sentence(text)
    return helps


def _first_sentence(text: str, limit: int = 110) -> str:
    cut = text.find(". ")
    if 0 < cut < limit:
        return text[:cut]
    return text if len(text) <= limit else text[: limit - 3].rstrip() + "..."


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    # A TOML basic string takes JSON's escapes (ASCII only, so none is ambiguous).
    return json.dumps(value, ensure_ascii=True)


def with_method(
    cfg: ServiceConfig, method: str | None = None, traits: str | None = None
) -> ServiceConfig:
    """`cfg` with another `pipeline.method` and `traits.method` (None: keep), checked as
    the file's values are (the command line's --method and --traits)."""
    if method is not None and method not in METHODS:
        raise ConfigError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if traits is not None and traits not in TRAIT_METHODS:
        raise ConfigError(f"traits must be one of {', '.join(TRAIT_METHODS)}, got {traits!r}")
    return with_overrides(
        cfg,
        pipeline={"method": method or cfg.pipeline.method},
        traits={"method": traits or cfg.traits.method},
    )


def with_overrides(cfg: ServiceConfig, **sections: dict[str, Any]) -> ServiceConfig:
    """`cfg` with some keys replaced, e.g. `with_overrides(cfg, record={"enabled": True})`
    (command-line options that override the file)."""
    return replace(cfg, **{name: replace(getattr(cfg, name), **v) for name, v in sections.items()})
