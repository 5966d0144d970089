"""`treetraits report`: one self-contained HTML page of a run or a season, for a grower
to open offline (docs/season.md, "Report").

The page holds everything: the figures are SVG drawn by matplotlib and put inline
(treetraits/season/figures.py), the style is inline, there is no script and no link to
fetch. Reading the inputs (`load_report_data`) is apart from drawing (`write_report`), so
a bad input fails before an output is touched.

Trees are named as the grower's field map names them (`T17`) wherever the run matched
them to it; a tree it did not match keeps the run's own id, marked `#` (`#4`), so the two
are never confused.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import html
import itertools
import json
import math
import re
import sqlite3
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from treetraits.errors import SourceError
from treetraits.files import iso_utc, write_atomically
from treetraits.pipeline import classify
from treetraits.pipeline.trees import (
    LOWER_BOUND,
    TREE_FIELD,
    height_bounded,
    marked,
    width_bounded,
)

if TYPE_CHECKING:
    from treetraits.season.store import SeasonTree, Survey

# Trees whose histories the season page plots (the ones found in the most surveys).
HISTORY_TREES = 4
# Surveys closer together than this: the page says growth per 30 days is mostly noise.
GROWTH_MIN_DAYS = 30
# A tree the run did not match to the field map: its run id, marked so.
RUN_ID_MARK = "#"

# What each rejection reason (pipeline/classify.py) means to someone in the grove: the
# rule the object failed and what usually fails it (docs/pipeline.md, "What a tree is").
REASON_TEXT = {
    classify.LOW: "too low for a tree: weeds, cover crop, a drip line",
    classify.TALL: "too tall for a tree: a building, a mast",
    classify.FLOATING: "nothing under it near the ground: a roof edge, a piece of a crown",
    classify.THIN: "too narrow for a crown: a post, a pole, a trunk without its crown",
    classify.SLENDER: "too narrow for its height: a person, a pole",
    classify.WIDE: "wider than any crown: a wall, a building",
    classify.SMOOTH: "its surface is not foliage: a wall, a shed, a vehicle",
    classify.NOT_GREEN: "the camera saw no vegetation on it",
}


@dataclass(frozen=True)
class MapTree:
    """A tree as the page shows it: its name, position (UTM m, None when the run had no
    UTM position for it), traits, found or missing."""

    tree_id: str  # the store's: a run's own id (`missing:<field id>`), a season's
    label: str  # the page's name for it: field id, else the run's id marked "#"
    row: str | None
    easting: float | None
    northing: float | None
    width_m: float | None
    height_m: float | None
    ndvi: float | None
    status: str  # found or missing
    width_change: float | None = None  # m per 30 days (season)
    # False: the crown's top was never bracketed within 5 % by the LiDAR's beams, so the
    # height is a lower bound; None where the store does not say (an older run or season
    # survey).
    height_top_seen: bool | None = None
    # 1: the crown was seen from one side only, so the width is a lower bound; 2: both
    # sides; None where the store does not say.
    width_sides_seen: int | None = None
    # The season's width change has a first or last width seen from one side only.
    width_change_one_sided: bool | None = None
    run_id: str | None = None  # the run's id (a run's page; None for a missing tree)
    field_id: str | None = None  # the field-map tree it was matched to


@dataclass(frozen=True)
class RejectedObject:
    """An object the run saw as often as a tree and judged not one, with why."""

    object_id: str
    reason: str
    easting: float | None
    northing: float | None
    width_m: float | None
    height_m: float | None
    ndvi: float | None
    observations: int | None
    # Its vegetation cues (pipeline/vegetation.py); None in a store older than them.
    evidence: float | None = None
    texture_m: float | None = None
    planar_share: float | None = None
    intensity: float | None = None


@dataclass(frozen=True)
class History:
    tree_id: str
    label: str
    dates: list[str]  # ISO UTC
    times_ns: list[int]
    width_m: list[float | None]
    height_m: list[float | None]
    ndvi: list[float | None]
    # Each survey's flags (None: not known): a lower bound is marked on the plot.
    height_top_seen: list[bool | None] = field(default_factory=list)
    width_sides_seen: list[int | None] = field(default_factory=list)

    def bounded(self, name: str) -> list[bool]:
        """Which of the trait's values are lower bounds (`width_m`, `height_m`; none of
        NDVI's, nor where the flags were not given)."""
        if name == "width_m" and self.width_sides_seen:
            return [width_bounded(s) for s in self.width_sides_seen]
        if name == "height_m" and self.height_top_seen:
            return [height_bounded(s) for s in self.height_top_seen]
        return [False] * len(self.times_ns)


@dataclass(frozen=True)
class SurveyRow:
    """One survey of a season, as its table lists it."""

    date: str  # ISO UTC
    block: str
    recording: str
    found: int | None
    missing: int | None
    rejected: dict[str, int]  # reason -> objects
    damaged: bool


@dataclass(frozen=True)
class ReportData:
    title: str
    source: str
    kind: str  # run or season
    trees: list[MapTree]
    path: list[tuple[float, float]] = field(default_factory=list)  # the robot's, UTM m
    facts: list[tuple[str, str]] = field(default_factory=list)
    histories: list[History] = field(default_factory=list)
    surveys: list[SurveyRow] = field(default_factory=list)
    survey_times: list[int] = field(default_factory=list)  # ns, the season's surveys
    # What the reader must know to read the page right (no GNSS fix, trees off the map).
    notes: list[str] = field(default_factory=list)
    rejected: list[RejectedObject] = field(default_factory=list)
    rejected_counts: dict[str, int] = field(default_factory=dict)  # reason -> objects


def tree_label(run_id: str, field_id: str | None) -> str:
    """The field map's id where the run matched the tree, else the run's id marked."""
    return field_id if field_id else f"{RUN_ID_MARK}{run_id}"


def page_title(kind: str, name: str, dates: Sequence[str]) -> str:
    """The page's title: the kind, then the season's or the run's name, the kind's word
    not said twice when the name holds it, then the survey dates (YYYY-MM-DD): "Season
    north, 2026-05-11 to 2026-05-12"; for season.sqlite "Season, 2026-05-12"."""
    words = set(re.split(r"[^a-z0-9]+", name.lower()))
    head = name if kind.lower() in words else f"{kind} {name}"
    head = head[:1].upper() + head[1:]
    span = sorted(set(dates))
    if not span:
        return head
    when = span[0] if len(span) == 1 else f"{span[0]} to {span[-1]}"
    return f"{head}, {when}"


def load_report_data(source: Path) -> ReportData:
    """A run directory (its traits.sqlite) or a season store, read without writing."""
    source = Path(source)
    if source.is_dir():
        store = source / "traits.sqlite"
        if not store.is_file():
            raise SourceError(f"{source}: no traits.sqlite in it (not a run directory)")
        return _run_data(store, source)
    if not source.is_file():
        raise SourceError(f"{source}: no such run directory or season store")
    if source.name == "traits.sqlite":
        return _run_data(source, source.parent)
    return _season_data(source)


# --- a run ---------------------------------------------------------------------------


def _run_data(store: Path, run_dir: Path) -> ReportData:
    from treetraits.readonly import connect_read_only, sqlite_errors

    db = connect_read_only(store)  # read-only: no -wal/-shm left in the run directory
    try:
        with sqlite_errors(store):
            tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master")}
            if not {"run", "trees"} <= tables:
                raise SourceError(f"{store}: not a run's store (no run or trees table)")
            facts = {k: _fact(v) for k, v in db.execute("SELECT key, value FROM run")}
            trees, seen = _run_trees(db)
            rejected = _rejected(db) if "rejected" in tables else []
    finally:
        db.close()
    path = [(float(e), float(n)) for e, n in _list(facts.get("path"))]
    counts = _rejected_counts(rejected, facts.get("rejected"))
    name = Path(str(facts.get("input") or run_dir)).stem
    dates = [iso_utc(seen)[:10]] if seen is not None else []
    return ReportData(
        title=page_title("Survey", name, dates),
        source=str(run_dir),
        kind="run",
        trees=trees,
        path=path,
        facts=_run_facts(facts, trees, path, counts, seen),
        notes=_run_notes(facts, trees),
        rejected=rejected,
        rejected_counts=counts,
    )


def _fact(text: str) -> Any:
    """A run fact as stored: JSON for what is not a plain string (replay's summary)."""
    try:
        return json.loads(text)
    except ValueError:
        return text


def _list(value: Any) -> list:
    return value if isinstance(value, list) else []


def _run_trees(db: sqlite3.Connection) -> tuple[list[MapTree], int | None]:
    """Every tree of the run, found and missing, with a UTM position or not; and when
    the run first saw one (ns, the host clock), its date."""
    columns = {r[1] for r in db.execute("PRAGMA table_info(trees)")}
    # A store older than a flag has no column for it: NULL (not known).
    flags = [c if c in columns else "NULL" for c in ("height_top_seen", "width_sides_seen")]
    rows = db.execute(
        "SELECT tree_id, field_id, row, easting, northing, width_m, height_m, ndvi, status, "
        f"{', '.join(flags)}, first_seen FROM trees"
    ).fetchall()
    top, sides = TREE_FIELD["height_top_seen"], TREE_FIELD["width_sides_seen"]
    trees = []
    for tree_id, field_id, row, e, n, width, height, ndvi, status, seen_top, seen_sides, _ in rows:
        run_id = None if status == "missing" else str(tree_id)
        trees.append(
            MapTree(
                str(tree_id),
                tree_label(str(tree_id), field_id),
                row,
                e,
                n,
                width,
                height,
                ndvi,
                status,
                height_top_seen=top.from_sql(seen_top),
                width_sides_seen=sides.from_sql(seen_sides),
                run_id=run_id,
                field_id=field_id,
            )
        )
    trees.sort(key=lambda t: (t.status != "found", _natural(t.label)))
    first = [r[11] for r in rows if r[11] is not None]
    return trees, min(first) if first else None


def _natural(text: str) -> list:
    """T2 before T10."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", text)]


def _rejected(db: sqlite3.Connection) -> list[RejectedObject]:
    columns = {r[1] for r in db.execute("PRAGMA table_info(rejected)")}
    # A store older than the vegetation cues has no columns for them: NULL.
    cues = ("evidence", "texture_m", "planar_share", "intensity")
    cues = [c if c in columns else "NULL" for c in cues]
    rows = db.execute(
        "SELECT tree_id, reason, easting, northing, width_m, height_m, ndvi, observations, "
        f"{', '.join(cues)} FROM rejected"
    ).fetchall()
    objects = [RejectedObject(str(r[0]), *r[1:]) for r in rows]
    return sorted(objects, key=lambda o: (o.reason, _natural(o.object_id)))


def _rejected_counts(rejected: Sequence[RejectedObject], fact: Any) -> dict[str, int]:
    """Objects per reason: the store's `rejected` table, else the run's summary."""
    if rejected:
        counts = Counter(o.reason for o in rejected)
    elif isinstance(fact, dict):
        counts = Counter({str(k): int(v) for k, v in fact.items() if int(v) > 0})
    else:
        return {}
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def _run_facts(
    facts: dict[str, Any],
    trees: Sequence[MapTree],
    path: Sequence[tuple[float, float]],
    rejected: dict[str, int],
    seen: int | None,
) -> list[tuple[str, str]]:
    found = [t for t in trees if t.status == "found"]
    shown: list[tuple[str, str]] = []

    def add(label: str, value: Any) -> None:
        if value is not None and value != "":
            shown.append((label, str(value)))

    add("recording", facts.get("input"))
    add("surveyed (UTC)", _when(seen))
    add("software", facts.get("software"))
    add("trait method", facts.get("traits") or facts.get("method"))
    add("LiDAR scans", facts.get("scans"))
    add("trees found", len(found))
    field_map = facts.get("field_map")
    on_map = field_map.get("trees") if isinstance(field_map, dict) else None
    matched = sum(t.field_id is not None for t in found)
    add("matched to the field map", f"{matched} of {on_map}" if on_map else matched)
    add("missing (field-map trees passed, not found)", sum(t.status == "missing" for t in trees))
    add("objects rejected (not trees)", sum(rejected.values()))
    add("positions", _position_fact(facts))
    add("GNSS fixes", facts.get("fixes"))
    if path:
        add("path driven (m)", f"{_path_length(path):.0f}")
    if "data_loss" in facts:
        damaged = "damaged or cut: read as far as it went"
        add("recording read", damaged if facts["data_loss"] else "whole")
    return shown


def _when(ns: int | None) -> str | None:
    if ns is None:
        return None
    return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.timezone.utc).strftime("%Y-%m-%d %H:%M")


def _position_fact(facts: dict[str, Any]) -> str:
    """Where the run's positions are: a UTM zone, else the local frame and why."""
    if zone := facts.get("utm_zone"):
        return f"UTM zone {zone} (m)"
    frame = facts.get("world_frame") or "odom"
    local = "local frame only (wheel odometry)" if frame == "odom" else f"{frame} frame only"
    return f"{local}: no GNSS fix" if not facts.get("fixes") else local


def _path_length(path: Sequence[tuple[float, float]]) -> float:
    return sum(math.dist(a, b) for a, b in itertools.pairwise(path))


def _run_notes(facts: dict[str, Any], trees: Sequence[MapTree]) -> list[str]:
    """What the page must say for its map and names to be read right."""
    notes = []
    found = [t for t in trees if t.status == "found"]
    unplaced = [t for t in found if t.easting is None]
    if not facts.get("utm_zone") and facts.get("world_frame") != "utm":
        fixes = facts.get("fixes")
        why = f"This run never placed itself in UTM ({fixes} GNSS fixes)" if fixes else ""
        frame = facts.get("world_frame") or "odom"
        local = "wheel odometry from where the robot started" if frame == "odom" else frame
        notes.append(
            f"{why or 'This run had no GNSS fix'}: its trees were mapped in the robot's local "
            f"frame ({local}) and have no UTM position, so no map of the block is drawn and "
            "none could be matched to the field map. They are listed below under the run's "
            "ids, with their traits."
        )
    elif unplaced:
        notes.append(
            f"{len(unplaced)} of {len(found)} trees have no UTM position (seen only while the "
            "run had no GNSS fix): they are listed below but not on the map."
        )
    if any(t.field_id is None for t in found):
        notes.append(
            f"Names starting with {RUN_ID_MARK} ({RUN_ID_MARK}4) are the run's own ids, for "
            "trees not matched to a field-map tree; the others are the field map's ids."
        )
    return notes


# --- a season ------------------------------------------------------------------------


def _season_data(path: Path) -> ReportData:
    from treetraits.readonly import sqlite_errors
    from treetraits.season.export import growth
    from treetraits.season.store import SeasonError, SeasonStore

    try:
        with SeasonStore(path, create=False) as season, sqlite_errors(path, "a season store"):
            trees = season.trees()
            surveys = season.surveys()
    except SeasonError as exc:
        raise SourceError(str(exc)) from None
    shown: list[MapTree] = []
    for t in trees:
        if not t.visits:
            continue
        g = growth(t)
        shown.append(
            MapTree(
                t.tree_id,
                t.tree_id,
                t.row,
                t.easting,
                t.northing,
                g["width_m"],
                g["height_m"],
                g["ndvi"],
                t.visits[-1].status,
                g["width_change_m_per_30d"],
                height_top_seen=g["height_top_seen"],
                width_sides_seen=g["width_sides_seen"],
                width_change_one_sided=g["width_change_one_sided"],
            )
        )
    ranked = sorted(trees, key=lambda t: (-sum(v.status == "found" for v in t.visits), t.tree_id))
    histories = [_history(t) for t in ranked[:HISTORY_TREES]]
    # The robot's paths: every survey's, from its run directory when it is still there.
    paths: list[tuple[float, float]] = []
    for s in surveys:
        store = Path(s.run_dir) / "traits.sqlite"
        if store.is_file():
            with contextlib.suppress(SourceError):
                paths.extend(_run_data(store, store.parent).path)
    blocks = sorted({t.block for t in trees})
    dates = [iso_utc(s.t_start)[:10] for s in surveys]
    rows = [_survey_row(s) for s in surveys]
    rejected: Counter = Counter()
    for row in rows:
        rejected.update(row.rejected)
    found = [v for t in trees for v in t.visits if v.status == "found"]
    notes = []
    if any(v.height_top_seen is None or v.width_sides_seen is None for v in found):
        notes.append(UNKNOWN_FLAGS_NOTE)
    return ReportData(
        title=page_title("Season", path.stem, dates),
        source=str(path),
        kind="season",
        trees=shown,
        path=paths,
        facts=[
            ("surveys", str(len(surveys))),
            ("survey dates (UTC)", ", ".join(sorted(set(dates))) or "-"),
            ("trees", str(len(trees))),
            ("blocks", ", ".join(blocks) or "-"),
            ("missing in their last survey", str(sum(t.status == "missing" for t in shown))),
            ("objects rejected (not trees), all surveys", str(sum(rejected.values()))),
        ],
        histories=histories,
        surveys=rows,
        survey_times=[s.t_start for s in surveys],
        notes=notes,
        rejected_counts=dict(sorted(rejected.items(), key=lambda kv: (-kv[1], kv[0]))),
    )


def _history(tree: SeasonTree) -> History:
    found = [v for v in tree.visits if v.status == "found"]
    return History(
        tree.tree_id,
        tree.tree_id,
        [iso_utc(v.t_start) for v in found],
        [v.t_start for v in found],
        [v.width_m for v in found],
        [v.height_m for v in found],
        [v.ndvi for v in found],
        [v.height_top_seen for v in found],
        [v.width_sides_seen for v in found],
    )


def _survey_row(survey: Survey) -> SurveyRow:
    summary = survey.summary
    rejected = summary.get("rejected")
    return SurveyRow(
        iso_utc(survey.t_start),
        survey.block,
        survey.recording,
        summary.get("trees"),
        summary.get("missing"),
        {str(k): int(v) for k, v in rejected.items()} if isinstance(rejected, dict) else {},
        survey.data_loss,
    )


# --- the page ------------------------------------------------------------------------


def row_table(trees: Sequence[MapTree]) -> list[dict]:
    """Per row (the field map's; "-" for trees off the map): trees found, missing, and
    the mean width, height and NDVI of the found ones; `width_bound`, `height_bound`: the
    mean takes in a lower bound, so it is one too."""
    rows: dict[str, list[MapTree]] = defaultdict(list)
    for t in trees:
        rows[t.row or "-"].append(t)

    def mean(values) -> float | None:
        values = [v for v in values if v is not None]
        return sum(values) / len(values) if values else None

    table = []
    for row in sorted(rows, key=lambda r: (r == "-", _natural(r))):
        found = [t for t in rows[row] if t.status == "found"]
        table.append(
            {
                "row": row,
                "found": len(found),
                "missing": sum(t.status == "missing" for t in rows[row]),
                "width_m": mean(t.width_m for t in found),
                "height_m": mean(t.height_m for t in found),
                "ndvi": mean(t.ndvi for t in found),
                "width_bound": any(_width_bound(t) for t in found),
                "height_bound": any(_height_bound(t) for t in found),
            }
        )
    return table


STYLE = """
body { font-family: sans-serif; margin: 1.5em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.15em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 0.5em 0; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.7em; text-align: right; }
th { background: #eef3ea; } td:first-child, th:first-child { text-align: left; }
svg.figure { max-width: 100%; height: auto; border: 1px solid #ddd; display: block; }
.facts td { text-align: left; }
.note { background: #fff4d6; border-left: 4px solid #d9a400; padding: 0.5em 0.8em; }
"""


def render_html(data: ReportData, colour: str = "height") -> str:
    """The page as one string."""
    from treetraits.season import figures

    e = html.escape
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{e(data.title)}</title><style>{STYLE}</style></head><body>",
        f"<h1>{e(data.title)}</h1>",
        '<table class="facts">',
        *(f"<tr><th>{e(k)}</th><td>{e(v)}</td></tr>" for k, v in data.facts),
        "</table>",
        *(f'<p class="note">{e(note)}</p>' for note in data.notes),
        "<h2>Map of the block</h2>",
        figures.draw_map(data, colour)
        or "<p>No map: nothing in this run has a UTM position (see the note above).</p>",
        "<h2>Per row</h2>",
        _table(
            ["row", "trees found", "missing", "mean width (m)", "mean height (m)", "mean NDVI"],
            [
                [
                    r["row"],
                    r["found"],
                    r["missing"],
                    marked(r["width_m"], r["width_bound"]),
                    marked(r["height_m"], r["height_bound"]),
                    _f(r["ndvi"]),
                ]
                for r in row_table(data.trees)
            ],
        ),
        *_bound_legend(data.trees, "a row's mean that takes in one is one too"),
        "<h2>Distributions</h2>",
        figures.draw_histograms(data.trees),
    ]
    if data.kind == "season":
        parts += _season_sections(data)
    parts += _rejected_section(data)
    parts += _trees_section(data)
    parts.append(f"<p><small>source: {e(data.source)}</small></p></body></html>")
    return "\n".join(parts) + "\n"


def _season_sections(data: ReportData) -> list[str]:
    from treetraits.season import figures

    if not data.survey_times:  # every recording failed: nothing to draw over time
        return ["<h2>Surveys</h2>", "<p>No survey in this season yet.</p>"]
    return [
        "<h2>Growth</h2>",
        *(f'<p class="note">{html.escape(n)}</p>' for n in _growth_notes(data.survey_times)),
        figures.draw_map(data, growth=True) or "",
        "<h2>A few trees over the season</h2>",
        figures.draw_histories(data.histories, data.survey_times),
        *_history_legend(data.histories),
        "<h2>Surveys</h2>",
        _table(
            ["date (UTC)", "block", "recording", "trees found", "missing", "rejected", "read"],
            [
                [
                    _when_iso(s.date),
                    s.block,
                    s.recording,
                    _count(s.found),
                    _count(s.missing),
                    _reasons(s.rejected) or "0",
                    "damaged or cut" if s.damaged else "whole",
                ]
                for s in data.surveys
            ],
        ),
    ]


def _growth_notes(times_ns: Sequence[int]) -> list[str]:
    """Why the growth map may say little: growth per 30 days from surveys days apart is
    the drives' own scatter scaled up (a 3 cm difference a day apart is 0.9 m / 30 days)."""
    days = (max(times_ns) - min(times_ns)) / 86400e9
    if days < 0.5:
        return ["All the surveys are on one day: no change can be measured yet."]
    if days < GROWTH_MIN_DAYS:
        return [
            f"The surveys span {days:.1f} days: a change per 30 days over so short a span is "
            "mostly the measurement's scatter from one drive to the next, scaled up."
        ]
    return []


def _rejected_section(data: ReportData) -> list[str]:
    """How many objects were taken for trees at first and rejected, and why."""
    total = sum(data.rejected_counts.values())
    if not total:
        return []
    e = html.escape
    where = "over the season's surveys " if data.kind == "season" else ""
    parts = [
        "<h2>Objects that are not trees</h2>",
        f'<p class="note">{total} object{"s" if total != 1 else ""} '
        f"seen {where}as often as a tree {'were' if total != 1 else 'was'} rejected: "
        f"{e(_reasons(data.rejected_counts))}.</p>",
        "<ul>",
        *(
            f"<li><b>{e(_reason_name(r))}</b>: {e(REASON_TEXT.get(r, r))}</li>"
            for r in data.rejected_counts
        ),
        "</ul>",
    ]
    if data.rejected:  # a run's: each object from its store, with its cues
        parts.append(_rejected_table(data.rejected))
    return parts


def _rejected_table(rejected: Sequence[RejectedObject]) -> str:
    header = ["object (run id)", "reason", "width (m)", "height (m)", "NDVI", "scans"]
    header += ["vegetation evidence", "texture (m)", "planar share", "intensity"]
    return _table(header, [_rejected_row(o) for o in rejected])


def _rejected_row(o: RejectedObject) -> list[str]:
    return [
        o.object_id,
        _reason_name(o.reason),
        _f(o.width_m),
        _f(o.height_m),
        _f(o.ndvi),
        _count(o.observations),
        _f(o.evidence),
        _f(o.texture_m, 3),
        _f(o.planar_share),
        _f(o.intensity, 0),
    ]


def _trees_section(data: ReportData) -> list[str]:
    if data.kind == "season":
        header = ["tree", "row", "last status", "width (m)", "height (m)", "NDVI"]
        header.append("width change (m / 30 days)")
        rows = [
            [t.label, t.row or "-", t.status, *_traits(t), _width_change(t)] for t in data.trees
        ]
    else:
        header = ["tree", "run id", "row", "status", "width (m)", "height (m)", "NDVI"]
        rows = [[t.label, t.run_id or "-", t.row or "-", t.status, *_traits(t)] for t in data.trees]
    parts = ["<h2>Trees</h2>", _table(header, rows), *_bound_legend(data.trees)]
    if any(t.width_change_one_sided for t in data.trees):
        parts.append(f"<p><small>{html.escape(ONE_SIDED_CHANGE)}</small></p>")
    return parts


# What the page's marks mean (`_bound_legend`, `_history_legend`).
WIDTH_BOUND_TEXT = (
    "the crown was seen from one side only, its far side hidden: the width is at least that"
)
HEIGHT_BOUND_TEXT = (
    "the crown's top was not measured to 5 % (above the LiDAR's view, or bracketed less "
    "closely by its beams): the height is at least that"
)
ONE_SIDED_CHANGE = (
    "(1 side): the change is from a first or last width seen from one side only; it "
    "compares like with like only where both surveys saw the crown the same way."
)
UNKNOWN_FLAGS_NOTE = (
    "Some surveys do not say how each height and width was measured (added before the "
    "season kept it, or by a method that does not judge it: RPH): their values are not "
    "marked as lower bounds even where they are, and their heights are left out of the "
    "height change. `treetraits batch --force` over their recordings adds them again "
    "with the marks."
)


def _bound_legend(trees: Sequence[MapTree], also: str = "") -> list[str]:
    """The legend line under a table with lower bounds marked `>`; none without any."""
    meanings = []
    if any(_width_bound(t) for t in trees):
        meanings.append(f"a width marked {LOWER_BOUND}: {WIDTH_BOUND_TEXT}")
    if any(_height_bound(t) for t in trees):
        meanings.append(f"a height marked {LOWER_BOUND}: {HEIGHT_BOUND_TEXT}")
    if not meanings:
        return []
    text = "Lower bounds: " + "; ".join(meanings) + (f"; {also}" if also else "") + "."
    return [f'<p class="legend"><small>{html.escape(text)}</small></p>']


def _history_legend(histories: Sequence[History]) -> list[str]:
    """What the open triangles of the histories mean, when there are any."""
    traits = [
        name.split("_")[0]
        for name in ("width_m", "height_m")
        if any(any(h.bounded(name)) for h in histories)
    ]
    if not traits:
        return []
    text = (
        f"Open triangles: a survey's {' or '.join(traits)} that is a lower bound "
        f"({'; '.join(_MEANING[t] for t in traits)})."
    )
    return [f'<p class="legend"><small>{html.escape(text)}</small></p>']


_MEANING = {"width": WIDTH_BOUND_TEXT, "height": HEIGHT_BOUND_TEXT}


def write_report(path: Path, data: ReportData, colour: str = "height") -> None:
    page = render_html(data, colour)
    write_atomically(path, lambda f: f.write(page), permissions=0o644)


def _table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    e = html.escape
    head = "".join(f"<th>{e(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{e(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _f(value: float | None, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    text = f"{value:.{digits}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text  # not "-0.00"


def _count(value: int | None) -> str:
    return "-" if value is None else str(value)


def _when_iso(iso: str) -> str:
    """2026-05-12T17:00:00.000Z as 2026-05-12 17:00."""
    return iso[:16].replace("T", " ")


def _reason_name(reason: str) -> str:
    return reason.replace("_", " ")


def _reasons(counts: dict[str, int]) -> str:
    """ "5 thin, 2 low": objects per reason, the commonest first."""
    return ", ".join(f"{n} {_reason_name(r)}" for r, n in counts.items())


def _traits(tree: MapTree) -> list[str]:
    """Width, height and NDVI; a lower bound marked ">" (as `treetraits replay` prints it)."""
    return [
        marked(tree.width_m, _width_bound(tree)),
        marked(tree.height_m, _height_bound(tree)),
        _f(tree.ndvi),
    ]


def _width_bound(tree: MapTree) -> bool:
    return width_bounded(tree.width_sides_seen) and tree.width_m is not None


def _height_bound(tree: MapTree) -> bool:
    return height_bounded(tree.height_top_seen) and tree.height_m is not None


def _width_change(tree: MapTree) -> str:
    text = _f(tree.width_change)
    return f"{text} (1 side)" if tree.width_change_one_sided and text != "-" else text
