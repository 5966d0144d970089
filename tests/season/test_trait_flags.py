"""Every trait says how it was measured, from the run's outputs to the season's report.

Two twin drives of one 2x2 block (trees in two rows along the path), batched into a
season a day apart: a straight pass down the lane between the rows, which sees each row
from that lane only (every width one-sided), and an S path through the lanes on both
sides of each row (every width seen from both). Their heights are whatever the LiDAR's
top beam allowed on each drive; the tests read each flag from the run's store and check
that every output marks it the same way: trees.csv, trees.geojson, traits.sqlite,
`replay`'s table, `season trees` (text and JSON), season.csv and season.geojson, and the
report's pages."""

from __future__ import annotations

import contextlib
import csv
import html
import io
import json
import sqlite3
from pathlib import Path

import pytest

from tests.helpers.report_page import SVG, Page, by_id
from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.pipeline.trees import HEIGHT_BOUND_LEGEND, WIDTH_BOUND_LEGEND
from treetraits.season.store import SeasonStore
from treetraits.service.replay import format_table
from treetraits.service.store import TraitStore
from treetraits.sim.paths import DriveSettings
from treetraits.sim.run import SurveySettings

DAY_S = 86400.0
# The straight drive is the one tests/season/test_report.py batches first (its host clock a
# day behind: the season's first survey); the S path drives the same block the next day.
STRAIGHT = SurveySettings(columns=2, rows=2, goal=10.0, seed=4, host_clock_offset_s=-DAY_S)
# At 1 m/s (a tractor's walking pace): the lanes on both sides of each row in half the scans.
S_PATH = SurveySettings(
    path="s", columns=2, rows=2, goal=10.0, seed=2, drive=DriveSettings(speed=1.0)
)


def _quiet(argv: list[str]) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = main(argv)
    return status, out.getvalue()


@pytest.fixture(scope="module")
def season(tmp_path_factory) -> Path:
    recordings = [twin_survey(s).recording for s in (STRAIGHT, S_PATH)]
    path = tmp_path_factory.mktemp("season") / "north.sqlite"
    status, _ = _quiet(["batch", *map(str, recordings), "--season", str(path), "--workers", "2"])
    assert status == 0
    return path


@pytest.fixture(scope="module")
def runs(season) -> dict[str, Path]:
    """The run directories by drive: the straight one is the earlier survey."""
    with SeasonStore(season, create=False) as store:
        straight, s_path = (Path(s.run_dir) for s in store.surveys())
    return {"straight": straight, "s": s_path}


def _stored_flags(run_dir: Path) -> dict[str, tuple[int | None, int | None]]:
    """Each found tree's (height_top_seen, width_sides_seen) by field id, from the store."""
    with sqlite3.connect(run_dir / "traits.sqlite") as db:
        rows = db.execute(
            "SELECT field_id, height_top_seen, width_sides_seen FROM trees WHERE status = 'found'"
        ).fetchall()
    return {field_id: (top, sides) for field_id, top, sides in rows}


# --- a run's outputs -------------------------------------------------------------------


@pytest.mark.parametrize(("drive", "sides"), [("straight", 1), ("s", 2)])
def test_the_run_outputs_carry_the_sides_the_crowns_were_seen_from(runs, drive, sides):
    run_dir = runs[drive]
    stored = _stored_flags(run_dir)
    assert sorted(stored) == ["T1", "T2", "T3", "T4"]
    # One lane between the rows: each crown from one side; the S path: from both.
    assert {s for _, s in stored.values()} == {sides}
    with open(run_dir / "trees.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["status"] == "found"]
    assert {r["field_id"]: r["width_sides_seen"] for r in rows} == {
        f: str(s) for f, (_, s) in stored.items()
    }
    assert {r["field_id"]: r["height_top_seen"] for r in rows} == {
        f: {1: "true", 0: "false"}[top] for f, (top, _) in stored.items()
    }
    features = json.loads((run_dir / "trees.geojson").read_text())["features"]
    properties = [f["properties"] for f in features if f["properties"]["status"] == "found"]
    assert {p["field_id"]: (p["height_top_seen"], p["width_sides_seen"]) for p in properties} == {
        f: (bool(top), s) for f, (top, s) in stored.items()
    }


@pytest.mark.parametrize("drive", ["straight", "s"])
def test_replays_table_marks_each_lower_bound_and_says_what_the_mark_means(runs, drive):
    with TraitStore(runs[drive] / "traits.sqlite") as store:
        trees = [t for t in store.trees() if t.status == "found"]
    table = format_table(trees).splitlines()
    # A tree's cells: tree, field id, row, easting, northing, width, height, NDVI, obs.
    rows = {line.split()[1]: line.split() for line in table[2 : 2 + len(trees)]}
    for t in trees:
        cells = rows[t.field_id]
        assert cells[5].startswith(">") == (t.width_sides_seen == 1), cells
        assert cells[6].startswith(">") == (t.height_top_seen is False), cells
    assert (WIDTH_BOUND_LEGEND in table) == any(t.width_sides_seen == 1 for t in trees)
    assert (HEIGHT_BOUND_LEGEND in table) == any(t.height_top_seen is False for t in trees)
    assert (WIDTH_BOUND_LEGEND in table) == (drive == "straight")


# --- the season -----------------------------------------------------------------------


def _season_flags(season: Path) -> dict[str, list[tuple[bool | None, int | None]]]:
    with SeasonStore(season, create=False) as store:
        return {
            t.tree_id: [(v.height_top_seen, v.width_sides_seen) for v in t.visits]
            for t in store.trees()
        }


def test_the_season_keeps_each_surveys_flags_as_its_run_stored_them(season, runs):
    flags = _season_flags(season)
    straight, s_path = _stored_flags(runs["straight"]), _stored_flags(runs["s"])
    assert sorted(flags) == ["T1", "T2", "T3", "T4"]
    for tree_id, visits in flags.items():
        assert visits == [(bool(run[tree_id][0]), run[tree_id][1]) for run in (straight, s_path)], (
            tree_id
        )


def test_season_trees_text_and_json_mark_the_lower_bounds(season):
    flags = _season_flags(season)
    status, text = _quiet(["season", "trees", "--season", str(season)])
    assert status == 0
    lines = text.splitlines()
    visits = [line for line in lines if "  survey " in line]
    assert len(visits) == 8
    widths = [line.split("width ")[1].split()[0] for line in visits]
    heights = [line.split("height ")[1].split()[0] for line in visits]
    expected = [v for tree_id in sorted(flags) for v in flags[tree_id]]
    assert [w.startswith(">") for w in widths] == [s == 1 for _, s in expected]
    assert [h.startswith(">") for h in heights] == [top is False for top, _ in expected]
    assert WIDTH_BOUND_LEGEND in lines  # the straight drive's widths
    assert (HEIGHT_BOUND_LEGEND in lines) == any(top is False for top, _ in expected)

    status, out = _quiet(["season", "trees", "--season", str(season), "--json"])
    assert status == 0
    document = json.loads(out)["trees"]
    assert {
        t["id"]: [(s["height_top_seen"], s["width_sides_seen"]) for s in t["surveys"]]
        for t in document
    } == flags


def test_season_export_carries_the_flags_and_growth_says_how_it_was_measured(season, tmp_path):
    flags = _season_flags(season)
    out = tmp_path / "export"
    assert _quiet(["season", "export", "--season", str(season), "--out", str(out)])[0] == 0
    with open(out / "season.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {
        t: [(r["height_top_seen"], r["width_sides_seen"]) for r in rows if r["tree_id"] == t]
        for t in flags
    } == {
        t: [({True: "true", False: "false"}[top], str(s)) for top, s in visits]
        for t, visits in flags.items()
    }
    features = json.loads((out / "season.geojson").read_text())["features"]
    for feature in features:
        p = feature["properties"]
        visits = flags[p["tree_id"]]
        # The width change runs from the straight drive's one-sided width.
        assert p["width_change_one_sided"] is True
        # The height change only from heights whose top was in view.
        topped = sum(top is True for top, _ in visits)
        assert (p["height_change_m_per_30d"] is None) == (topped < 2)
        assert p["height_lower_bounds"] == sum(top is False for top, _ in visits)
        assert (p["height_top_seen"], p["width_sides_seen"]) == visits[-1]


# --- the report ----------------------------------------------------------------------


def _report(source: Path, out: Path) -> tuple[Page, str]:
    """The page parsed, and its text as a reader sees it (entities decoded)."""
    assert _quiet(["report", str(source), "--out", str(out)])[0] == 0
    text = out.read_text()
    return Page.read(text), html.unescape(text)


def test_the_season_report_marks_lower_bounds_in_its_tables_and_histories(season, tmp_path):
    flags = _season_flags(season)
    page, text = _report(season, tmp_path / "season.html")
    header, *rows = page.table("tree")
    for row in rows:
        last = flags[row[0]][-1]  # the table shows the last survey's values
        assert row[header.index("width (m)")].startswith(">") == (last[1] == 1), row
        assert row[header.index("height (m)")].startswith(">") == (last[0] is False), row
        # Each tree's width change starts from the straight drive's one-sided width.
        assert row[header.index("width change (m / 30 days)")].endswith("(1 side)"), row
    per_row_header, *per_row = page.table("row")
    for cells in per_row:
        trees = [t for t in rows if t[header.index("row")] == cells[0]]
        marked = any(t[header.index("height (m)")].startswith(">") for t in trees)
        assert cells[per_row_header.index("mean height (m)")].startswith(">") == marked
    assert "Lower bounds: " in text and "(1 side): the change is from" in text

    # The histories: an open triangle over each lower bound, the straight drive's widths
    # among them, with a legend entry and a line under the figure.
    histories = page.figures["histories"]
    for name, bound in (("width_m", lambda v: v[1] == 1), ("height_m", lambda v: v[0] is False)):
        marks = by_id(histories, f"histories-{name}-lower-bounds")
        count = sum(bound(v) for visits in flags.values() for v in visits)
        if count == 0:
            assert marks is None, name
            continue
        assert len(list(marks.iter(f"{SVG}use"))) == count, name
    assert "Open triangles: a survey's width" in text


def test_a_run_report_marks_one_sided_widths(runs, tmp_path):
    stored = _stored_flags(runs["straight"])
    page, text = _report(runs["straight"], tmp_path / "run.html")
    header, *rows = page.table("tree")
    for row in rows:
        top, sides = stored[row[0]]
        assert row[header.index("width (m)")].startswith(">") == (sides == 1), row
        assert row[header.index("height (m)")].startswith(">") == (top == 0), row
    assert "a width marked >: the crown was seen from one side only" in text
    # The S path's run: every crown seen from both sides, no width marked.
    page, _ = _report(runs["s"], tmp_path / "s.html")
    header, *rows = page.table("tree")
    assert not any(row[header.index("width (m)")].startswith(">") for row in rows)
