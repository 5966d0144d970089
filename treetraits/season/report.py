"""`treetraits report`: one self-contained HTML page of a run or a season, for a grower
to open offline (docs/season.md, "Report").

The page holds everything: the figures are PNGs drawn with matplotlib's Agg canvas and
embedded as base64 data URIs, the style is inline, there is no script and no link to
fetch. Reading the inputs (`load_report_data`) is apart from drawing (`write_report`), so
a bad input fails before an output is touched.
"""

from __future__ import annotations

import base64
import contextlib
import html
import io
import json
import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from treetraits.errors import SourceError
from treetraits.files import write_atomically
from treetraits.pipeline.trees import TREE_FIELD, iso_utc

# Trees whose histories the season page plots (the ones found in the most surveys).
HISTORY_TREES = 4


@dataclass(frozen=True)
class MapTree:
    """A tree as the page draws it: position (UTM m), traits, found or missing."""

    tree_id: str
    row: str | None
    easting: float
    northing: float
    width_m: float | None
    height_m: float | None
    ndvi: float | None
    status: str  # found or missing
    width_change: float | None = None  # m per 30 days (season)
    # False: the crown's top was above the LiDAR's view in every scan, so the height is a
    # lower bound; None where the store does not say (a season, an older run).
    height_top_seen: bool | None = None


@dataclass(frozen=True)
class History:
    tree_id: str
    dates: list[str]  # ISO UTC
    times_ns: list[int]
    width_m: list[float | None]
    height_m: list[float | None]
    ndvi: list[float | None]


@dataclass(frozen=True)
class ReportData:
    title: str
    source: str
    kind: str  # run or season
    trees: list[MapTree]
    path: list[tuple[float, float]] = field(default_factory=list)  # the robot's, UTM m
    facts: list[tuple[str, str]] = field(default_factory=list)
    histories: list[History] = field(default_factory=list)
    surveys: list[tuple[str, str, str]] = field(default_factory=list)  # date, recording, status


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


def _run_data(store: Path, run_dir: Path) -> ReportData:
    from treetraits.readonly import connect_read_only, sqlite_errors

    db = connect_read_only(store)  # read-only: no -wal/-shm left in the run directory
    try:
        with sqlite_errors(store):
            tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master")}
            if not {"run", "trees"} <= tables:
                raise SourceError(f"{store}: not a run's store (no run or trees table)")
            facts = dict(db.execute("SELECT key, value FROM run").fetchall())
            columns = {r[1] for r in db.execute("PRAGMA table_info(trees)")}
            top_seen = "height_top_seen" if "height_top_seen" in columns else "NULL"  # older
            rows = db.execute(
                "SELECT tree_id, row, easting, northing, width_m, height_m, ndvi, status, "
                f"{top_seen} FROM trees WHERE easting IS NOT NULL ORDER BY tree_id"
            ).fetchall()
    finally:
        db.close()
    top = TREE_FIELD["height_top_seen"]
    trees = [MapTree(*r[:8], height_top_seen=top.from_sql(r[8])) for r in rows]
    path = _json_list(facts.get("path"))
    shown = (
        "input",
        "software",
        "method",
        "traits",
        "scans",
        "trees",
        "matched",
        "missing",
        "utm_zone",
        "data_loss",
    )
    return ReportData(
        title=f"Survey {Path(facts.get('input', str(run_dir))).name}",
        source=str(run_dir),
        kind="run",
        trees=trees,
        path=[(float(e), float(n)) for e, n in path],
        facts=[(k, facts[k]) for k in shown if k in facts],
    )


def _json_list(text: str | None) -> list:
    try:
        value = json.loads(text) if text else []
    except ValueError:
        return []
    return value if isinstance(value, list) else []


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
        if t.easting is None or not t.visits:
            continue
        g = growth(t)
        shown.append(
            MapTree(
                t.tree_id,
                t.row,
                t.easting,
                t.northing,
                g["width_m"],
                g["height_m"],
                g["ndvi"],
                t.visits[-1].status,
                g["width_change_m_per_30d"],
            )
        )
    ranked = sorted(trees, key=lambda t: (-sum(v.status == "found" for v in t.visits), t.tree_id))
    histories = [
        History(
            t.tree_id,
            [iso_utc(v.t_start) for v in t.visits if v.status == "found"],
            [v.t_start for v in t.visits if v.status == "found"],
            [v.width_m for v in t.visits if v.status == "found"],
            [v.height_m for v in t.visits if v.status == "found"],
            [v.ndvi for v in t.visits if v.status == "found"],
        )
        for t in ranked[:HISTORY_TREES]
    ]
    # The robot's paths: every survey's, from its run directory when it is still there.
    paths: list[tuple[float, float]] = []
    for s in surveys:
        store = Path(s.run_dir) / "traits.sqlite"
        if store.is_file():
            with contextlib.suppress(SourceError):
                paths.extend(_run_data(store, store.parent).path)
    blocks = sorted({t.block for t in trees})
    return ReportData(
        title=f"Season {path.stem}",
        source=str(path),
        kind="season",
        trees=shown,
        path=paths,
        facts=[
            ("surveys", str(len(surveys))),
            ("trees", str(len(trees))),
            ("blocks", ", ".join(blocks) or "-"),
            ("missing in their last survey", str(sum(t.status == "missing" for t in shown))),
        ],
        histories=histories,
        surveys=[
            (iso_utc(s.t_start), s.recording, "damaged" if s.data_loss else "ok") for s in surveys
        ],
    )


# --- drawing -----------------------------------------------------------------------------


def _figure(width: float = 8.0, height: float = 5.5):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _png(fig) -> str:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight")
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def draw_map(data: ReportData, colour: str = "height", growth: bool = False) -> str:
    """The block from above, metres from its south-west corner: each found tree a disc of
    its width coloured by `colour` (or by width change per 30 days with `growth`), missing
    trees as red crosses, the robot's path as a grey line. A base64 PNG."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Circle

    fig = _figure()
    ax = fig.add_subplot()
    points = [(t.easting, t.northing) for t in data.trees] + list(data.path)
    e0 = min((p[0] for p in points), default=0.0)
    n0 = min((p[1] for p in points), default=0.0)
    if data.path:
        ax.plot(
            [p[0] - e0 for p in data.path],
            [p[1] - n0 for p in data.path],
            color="0.6",
            lw=1.2,
            label="robot path",
            zorder=1,
        )
    found = [t for t in data.trees if t.status == "found"]
    if growth:
        values, label, cmap = (
            [t.width_change for t in found],
            "width change (m / 30 days)",
            "RdYlGn",
        )
    elif colour == "ndvi":
        values, label, cmap = [t.ndvi for t in found], "NDVI", "RdYlGn"
    else:
        values, label, cmap = [t.height_m for t in found], "height (m)", "viridis"
    circles = [
        Circle((t.easting - e0, t.northing - n0), max((t.width_m or 0.3) / 2, 0.15)) for t in found
    ]
    if circles:
        known = [v for v in values if v is not None]
        collection = PatchCollection(circles, cmap=cmap, edgecolor="k", linewidth=0.6, zorder=2)
        collection.set_array([math.nan if v is None else v for v in values])
        if known:
            low, high = min(known), max(known)
            if growth:
                bound = max(abs(low), abs(high), 1e-3)
                low, high = -bound, bound
            collection.set_clim(low, high if high > low else low + 1e-3)
        ax.add_collection(collection)
        fig.colorbar(collection, ax=ax, label=label if known else f"{label}: not measured")
        for t in found:
            ax.annotate(
                t.tree_id,
                (t.easting - e0, t.northing - n0),
                fontsize=7,
                ha="center",
                va="center",
                zorder=3,
            )
    missing = [t for t in data.trees if t.status == "missing"]
    if missing:
        ax.scatter(
            [t.easting - e0 for t in missing],
            [t.northing - n0 for t in missing],
            marker="x",
            s=80,
            color="red",
            linewidths=2,
            label="missing",
            zorder=3,
        )
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.margins(0.08)
    ax.set_xlabel(f"easting − {e0:.0f} (m)")
    ax.set_ylabel(f"northing − {n0:.0f} (m)")
    ax.grid(alpha=0.3)
    if data.path or missing:
        ax.legend(loc="best", fontsize=8)
    ax.set_title("Width change per 30 days" if growth else f"Trees by {label}")
    return _png(fig)


def draw_histograms(trees: Sequence[MapTree]) -> str:
    fig = _figure(10, 3.2)
    found = [t for t in trees if t.status == "found"]
    for i, (name, unit) in enumerate((("width_m", "m"), ("height_m", "m"), ("ndvi", ""))):
        ax = fig.add_subplot(1, 3, i + 1)
        values = [getattr(t, name) for t in found if getattr(t, name) is not None]
        title = name.replace("_m", "").upper() if name == "ndvi" else name.replace("_m", "")
        if values:
            ax.hist(values, bins=min(12, max(3, len(values))), color="tab:green", edgecolor="k")
        else:
            ax.text(0.5, 0.5, "not measured", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel(f"{title} ({unit})" if unit else title)
        ax.set_ylabel("trees")
    fig.tight_layout()
    return _png(fig)


def draw_histories(histories: Sequence[History]) -> str:
    import datetime as dt

    fig = _figure(10, 3.2)
    for i, (name, label) in enumerate(
        (("width_m", "width (m)"), ("height_m", "height (m)"), ("ndvi", "NDVI"))
    ):
        ax = fig.add_subplot(1, 3, i + 1)
        for h in histories:
            pairs = [
                (t, v) for t, v in zip(h.times_ns, getattr(h, name), strict=True) if v is not None
            ]
            if pairs:
                days = [dt.datetime.fromtimestamp(t / 1e9, tz=dt.timezone.utc) for t, _ in pairs]
                ax.plot(days, [v for _, v in pairs], marker="o", label=h.tree_id)
        ax.set_ylabel(label)
        ax.tick_params(axis="x", labelrotation=30, labelsize=7)
        if i == 0 and histories:
            ax.legend(fontsize=7)
    fig.tight_layout()
    return _png(fig)


def row_table(trees: Sequence[MapTree]) -> list[dict]:
    """Per row (the field map's; "-" for trees off the map): trees found, missing, and
    the mean width, height and NDVI of the found ones."""
    rows: dict[str, list[MapTree]] = defaultdict(list)
    for t in trees:
        rows[t.row or "-"].append(t)

    def mean(values) -> float | None:
        values = [v for v in values if v is not None]
        return sum(values) / len(values) if values else None

    table = []
    for row in sorted(rows, key=lambda r: (r == "-", r)):
        found = [t for t in rows[row] if t.status == "found"]
        table.append(
            {
                "row": row,
                "found": len(found),
                "missing": sum(t.status == "missing" for t in rows[row]),
                "width_m": mean(t.width_m for t in found),
                "height_m": mean(t.height_m for t in found),
                "ndvi": mean(t.ndvi for t in found),
            }
        )
    return table


STYLE = """
body { font-family: sans-serif; margin: 1.5em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.15em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 0.5em 0; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.7em; text-align: right; }
th { background: #eef3ea; } td:first-child, th:first-child { text-align: left; }
img { max-width: 100%; border: 1px solid #ddd; }
.facts td { text-align: left; }
"""


def render_html(data: ReportData, colour: str = "height") -> str:
    """The page as one string."""
    e = html.escape
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{e(data.title)}</title><style>{STYLE}</style></head><body>",
        f"<h1>{e(data.title)}</h1>",
        '<table class="facts">',
        *(f"<tr><th>{e(k)}</th><td>{e(v)}</td></tr>" for k, v in data.facts),
        "</table>",
        "<h2>Map of the block</h2>",
        _img(draw_map(data, colour), "map of the block"),
        "<h2>Per row</h2>",
        _table(
            ["row", "found", "missing", "mean width (m)", "mean height (m)", "mean NDVI"],
            [
                [
                    r["row"],
                    r["found"],
                    r["missing"],
                    _f(r["width_m"]),
                    _f(r["height_m"]),
                    _f(r["ndvi"]),
                ]
                for r in row_table(data.trees)
            ],
        ),
        "<h2>Distributions</h2>",
        _img(draw_histograms(data.trees), "histograms of width, height and NDVI"),
    ]
    if data.kind == "season":
        parts += [
            "<h2>Growth</h2>",
            _img(draw_map(data, growth=True), "growth map"),
            "<h2>A few trees over the season</h2>",
            _img(draw_histories(data.histories), "time series of trees"),
            "<h2>Surveys</h2>",
            _table(["date", "recording", "read"], [list(s) for s in data.surveys]),
        ]
    parts.append(
        "<h2>Trees</h2>"
        + _table(
            ["tree", "row", "status", "width (m)", "height (m)", "NDVI"],
            [
                [t.tree_id, t.row or "-", t.status, _f(t.width_m), _height(t), _f(t.ndvi)]
                for t in data.trees
            ],
        )
    )
    if any(t.height_top_seen is False for t in data.trees):
        parts.append(
            "<p><small>&gt;2.55: a lower bound; the crown's top was above the LiDAR's "
            "view in every scan.</small></p>"
        )
    parts.append(f"<p><small>source: {e(data.source)}</small></p></body></html>")
    return "\n".join(parts) + "\n"


def write_report(path: Path, data: ReportData, colour: str = "height") -> None:
    page = render_html(data, colour)
    write_atomically(path, lambda f: f.write(page), permissions=0o644)


def _img(png_base64: str, alt: str) -> str:
    return f'<p><img alt="{html.escape(alt)}" src="data:image/png;base64,{png_base64}"></p>'


def _table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    e = html.escape
    head = "".join(f"<th>{e(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{e(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _f(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _height(tree: MapTree) -> str:
    """The height, marked ">" where it is a lower bound (as `treetraits replay` prints it)."""
    text = _f(tree.height_m)
    return f">{text}" if tree.height_top_seen is False and tree.height_m is not None else text
