"""What the grower reads: `treetraits report` on real stores, read back off the page.

A season of two twin drives of a 2x2 block, the robot's host clock a day apart (`sim
--host-clock-offset`: the survey date is the recording's), batched into
`season.sqlite`; one of its runs; and a drive among posts, a person, a vehicle and a
wall with no GNSS fix at all. The figures are inline SVG with their text kept as text,
so the tests read the labels, ticks and units the reader sees."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import re
import sqlite3
from collections import Counter
from pathlib import Path

import pytest

from tests.helpers.report_page import Page, by_id, contrast, fill, texts
from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.pipeline import classify
from treetraits.season.report import REASON_TEXT, page_title
from treetraits.season.store import SeasonStore
from treetraits.sim.clutter import ClutterSettings
from treetraits.sim.gnss import GnssSettings
from treetraits.sim.run import SurveySettings

DAY_S = 86400.0
# The twin drives on 2026-05-12 at 17:00 UTC; the first drive's host clock a day behind.
DRIVES = (
    SurveySettings(columns=2, rows=2, goal=10.0, seed=4, host_clock_offset_s=-DAY_S),
    SurveySettings(columns=2, rows=2, goal=10.0, seed=2),
)
WITHOUT_GNSS = SurveySettings(
    rows=2,
    goal=11.0,
    gnss=GnssSettings(outages=((0.0, 1e6),)),
    clutter=ClutterSettings(posts=True, standing_people=1, vehicle=True, wall=True),
)
LEGIBLE = 4.5  # WCAG 2 AA contrast for normal text


def _report(source: Path | str, out: Path, *extra: str) -> Page:
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["report", str(source), "--out", str(out), *extra]) == 0
    return Page.read(out.read_text())


@pytest.fixture(scope="module")
def season(tmp_path_factory) -> Path:
    """`season.sqlite` (the name that made "Season season"), batched from the drives."""
    recordings = [twin_survey(s).recording for s in DRIVES]
    path = tmp_path_factory.mktemp("season") / "season.sqlite"
    argv = ["batch", *map(str, recordings), "--season", str(path), "--workers", "2"]
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(argv) == 0
    return path


@pytest.fixture(scope="module")
def season_page(season, tmp_path_factory) -> Page:
    return _report(season, tmp_path_factory.mktemp("pages") / "season.html")


@pytest.fixture(scope="module")
def run_dir(season) -> Path:
    with SeasonStore(season, create=False) as store:
        return Path(store.surveys()[-1].run_dir)


@pytest.fixture(scope="module")
def run_page(run_dir, tmp_path_factory) -> Page:
    return _report(run_dir, tmp_path_factory.mktemp("pages") / "run.html")


@pytest.fixture(scope="module")
def without_gnss(tmp_path_factory) -> tuple[Path, Page]:
    """The cluttered drive with no fix, replayed; its run directory and page."""
    recording = twin_survey(WITHOUT_GNSS).recording
    out = tmp_path_factory.mktemp("no-gnss") / "run"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["replay", str(recording), "--out", str(out)]) == 0
    return out, _report(out, out.parent / "run.html")


def _store_trees(run_dir: Path) -> list[tuple[str, str | None]]:
    with sqlite3.connect(run_dir / "traits.sqlite") as db:
        return db.execute("SELECT tree_id, field_id FROM trees WHERE status = 'found'").fetchall()


def _map_labels(page: Page, name: str = "map") -> list[tuple[str, float]]:
    """Each tree's label on the map and its contrast with the tree's disc."""
    figure, labels, i = page.figures[name], [], 0
    while (disc := by_id(figure, f"{name}-tree-{i}")) is not None:
        label = by_id(figure, f"{name}-label-{i}")
        (text,) = texts(label)
        labels.append((text, contrast(fill(disc), fill(label))))
        i += 1
    return labels


# --- trees named by the field map --------------------------------------------------------


def test_the_map_and_the_table_name_trees_by_their_field_map_ids(run_dir, run_page):
    stored = _store_trees(run_dir)
    assert sorted(f for _, f in stored) == ["T1", "T2", "T3", "T4"]  # every tree matched
    assert sorted(i for i, _ in stored) == ["1", "2", "3", "4"]  # the run's own ids differ
    assert sorted(text for text, _ in _map_labels(run_page)) == ["T1", "T2", "T3", "T4"]
    header, *rows = run_page.table("tree")
    assert header[:2] == ["tree", "run id"]
    assert sorted((r[0], r[1]) for r in rows) == sorted((f, i) for i, f in stored)
    assert run_page.facts()["matched to the field map"] == "4 of 4"


def test_a_tree_off_the_field_map_keeps_its_run_id_marked(without_gnss):
    run_dir, page = without_gnss
    stored = _store_trees(run_dir)
    assert stored and all(f is None for _, f in stored)
    _, *rows = page.table("tree")
    assert sorted((r[0], r[1]) for r in rows) == sorted((f"#{i}", i) for i, _ in stored)
    assert any("are the run's own ids" in note for note in page.notes)


# --- legible labels ----------------------------------------------------------------------


@pytest.mark.parametrize("colour", ["height", "ndvi"])
def test_every_label_is_legible_on_its_disc(run_dir, colour, tmp_path):
    page = _report(run_dir, tmp_path / "run.html", "--colour", colour)
    labels = _map_labels(page)
    assert len(labels) == 4
    for text, ratio in labels:
        assert ratio >= LEGIBLE, (colour, text, ratio)


def test_the_season_maps_labels_are_legible(season_page):
    for name in ("map", "growth"):
        labels = _map_labels(season_page, name)
        assert sorted(text for text, _ in labels) == ["T1", "T2", "T3", "T4"]
        assert all(ratio >= LEGIBLE for _, ratio in labels), (name, labels)


# --- axes ---------------------------------------------------------------------------------


def test_the_histograms_count_trees_in_whole_numbers(run_page, season_page):
    for page in (run_page, season_page):
        figure = page.figures["histograms"]
        for trait, unit_label in (("width_m", "width (m)"), ("height_m", "height (m)")):
            axes = by_id(figure, f"histograms-{trait}")
            counts = texts(by_id(axes, f"histograms-{trait}-counts"))
            assert counts[-1] == "number of trees"
            assert counts[:-1] and all(re.fullmatch(r"\d+", c) for c in counts[:-1]), counts
            assert unit_label in texts(axes)


def test_the_time_axis_spans_the_surveys(season, season_page):
    with SeasonStore(season, create=False) as store:
        dates = sorted({dt.date.fromisoformat(_iso(s.t_start)) for s in store.surveys()})
    assert dates == [dt.date(2026, 5, 11), dt.date(2026, 5, 12)]  # a day apart
    figure = season_page.figures["histories"]
    for trait in ("width_m", "height_m", "ndvi"):
        ticks = texts(by_id(figure, f"histories-{trait}-dates"))
        assert ticks[-1] == "survey date (UTC)"
        days = [dt.date.fromisoformat(t) for t in ticks[:-1]]  # every tick is a date
        assert days[0] <= dates[0] and days[-1] >= dates[-1]
        assert (days[-1] - days[0]).days <= (dates[-1] - dates[0]).days + 3  # a day's margin


def _iso(ns: int) -> str:
    return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.timezone.utc).strftime("%Y-%m-%d")


# --- title and units ------------------------------------------------------------------


def _doubled(title: str) -> list[str]:
    words = re.findall(r"[a-z]+", title.lower())
    return [w for w, n in Counter(words).items() if n > 1]


def test_the_titles_name_the_season_and_the_run_once(season_page, run_page):
    assert season_page.title == season_page.headings[0] == "Season, 2026-05-11 to 2026-05-12"
    assert run_page.title == run_page.headings[0] == "Survey, 2026-05-12"  # survey.mcap
    for page in (season_page, run_page):
        assert _doubled(page.title) == []


@pytest.mark.parametrize(
    ("kind", "name", "dates", "title"),
    [
        ("Season", "season", ["2026-05-12"], "Season, 2026-05-12"),
        (
            "Season",
            "north-2026",
            ["2026-06-01", "2026-05-12"],
            "Season north-2026, 2026-05-12 to 2026-06-01",
        ),
        ("Season", "citrus_season_b", [], "Citrus_season_b"),
        ("Survey", "north-0512", ["2026-05-12"], "Survey north-0512, 2026-05-12"),
    ],
)
def test_page_titles(kind, name, dates, title):
    assert page_title(kind, name, dates) == title


def test_widths_and_heights_carry_their_unit_everywhere(season_page, run_page):
    for page in (season_page, run_page):
        headers = [cell for table in page.tables for cell in table[0]]
        for cell in headers:
            if re.search(r"\b(width|height)\b", cell):
                assert "(m" in cell, cell
        for name, figure in page.figures.items():
            for text in texts(figure):
                if re.search(r"\b(width|height|easting|northing)\b", text):
                    assert "(m" in text, (name, text)
    map_texts = texts(run_page.figures["map"])
    assert "height (m)" in map_texts  # the colour bar
    assert any(t.startswith("easting − ") and t.endswith("(m)") for t in map_texts)


# --- no GNSS, rejected objects ----------------------------------------------------------


def test_a_run_without_gnss_says_so_instead_of_an_empty_map(without_gnss):
    run_dir, page = without_gnss
    with sqlite3.connect(run_dir / "traits.sqlite") as db:
        facts = dict(db.execute("SELECT key, value FROM run"))
    assert facts["world_frame"] == "odom" and facts["fixes"] == "0"
    assert facts["utm_zone"] == "null"
    assert "map" not in page.figures  # no empty map
    (note,) = [n for n in page.notes if "GNSS" in n]
    assert note.startswith("This run had no GNSS fix: its trees were mapped in the robot's")
    assert "no map of the block is drawn" in note
    shown = page.facts()
    assert shown["positions"] == "local frame only (wheel odometry): no GNSS fix"
    assert shown["GNSS fixes"] == "0"
    assert "null" not in " ".join(shown.values())
    # Every found tree is still listed with its traits.
    header, *rows = page.table("tree")
    assert len(rows) == len(_store_trees(run_dir)) >= 4
    # One lane between the two rows: every crown seen from one side, its width marked.
    assert all(re.fullmatch(r">\d\.\d\d", r[header.index("width (m)")]) for r in rows)


def test_rejected_objects_are_counted_with_their_reasons(without_gnss):
    run_dir, page = without_gnss
    with sqlite3.connect(run_dir / "traits.sqlite") as db:
        reasons = Counter(r for (r,) in db.execute("SELECT reason FROM rejected"))
    assert sum(reasons.values()) >= 3 and len(reasons) >= 2  # posts, a person, a wall...
    (note,) = [n for n in page.notes if "rejected" in n]
    total = sum(reasons.values())
    listed = ", ".join(f"{n} {r.replace('_', ' ')}" for r, n in reasons.most_common())
    assert note.startswith(f"{total} objects seen as often as a tree were rejected: ")
    said = dict(
        (m.group(2), int(m.group(1))) for m in re.finditer(r"(\d+) ([a-z ]+?)(?:,|\.$)", note)
    )
    assert said == {r.replace("_", " "): n for r, n in reasons.items()}, (note, listed)
    assert page.facts()["objects rejected (not trees)"] == str(total)
    # Each reason explained, each object listed with its cues.
    for reason in reasons:
        assert f"{reason.replace('_', ' ')}: {REASON_TEXT[reason]}" in page.items
    header, *rows = page.table("object (run id)")
    assert "texture (m)" in header and len(rows) == total
    assert Counter(r[1] for r in rows) == {r.replace("_", " "): n for r, n in reasons.items()}


def test_every_rejection_reason_is_explained():
    assert set(REASON_TEXT) == set(classify.REASONS)


def test_a_season_lists_each_surveys_rejected_objects(season_page):
    header, *rows = season_page.table("date (UTC)")
    assert header == [
        "date (UTC)",
        "block",
        "recording",
        "trees found",
        "missing",
        "rejected",
        "read",
    ]
    assert [r[0][:10] for r in rows] == ["2026-05-11", "2026-05-12"]
    assert all(r[3] == "4" and r[6] == "whole" for r in rows)


def test_growth_over_a_day_is_said_to_be_noise(season_page):
    (note,) = [n for n in season_page.notes if "per 30 days" in n]
    assert note.startswith("The surveys span 1.0 days: ")


def test_a_season_whose_recordings_all_failed_says_so(tmp_path):
    notes = tmp_path / "notes.mcap"
    notes.write_text("not a recording\n")
    season = tmp_path / "empty.sqlite"
    argv = ["batch", str(notes), "--season", str(season), "--workers", "1"]
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(argv) == 3
    page = _report(season, tmp_path / "empty.html")
    assert page.facts()["surveys"] == "0"
    assert "Surveys" in page.headings and "Growth" not in page.headings


def test_the_drives_are_what_the_season_says(season):
    """The fixture's premise: each drive is its own survey, a day apart, 4 trees each."""
    with SeasonStore(season, create=False) as store:
        surveys = store.surveys()
    assert [s.summary["trees"] for s in surveys] == [4, 4]
    assert surveys[1].t_start - surveys[0].t_start == pytest.approx(DAY_S * 1e9, abs=5e9)


def test_a_run_store_from_before_the_width_flag_shows_its_widths_unmarked(tmp_path):
    """A run's store written before `width_sides_seen` (its `trees` table without the
    column), read as it is: its heights marked as its flag says, its widths shown as
    measured (not known either way), and the store left unchanged."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    with sqlite3.connect(run_dir / "traits.sqlite") as db:
        db.execute(
            "CREATE TABLE trees (tree_id TEXT PRIMARY KEY, field_id TEXT, row TEXT, "
            "easting REAL, northing REAL, utm_zone TEXT, lat REAL, lon REAL, width_m REAL, "
            "height_m REAL, ndvi REAL, observations INTEGER NOT NULL, first_seen INTEGER, "
            "last_seen INTEGER, status TEXT NOT NULL DEFAULT 'found', height_top_seen INTEGER)"
        )
        db.execute("CREATE TABLE run (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        db.execute(
            "INSERT INTO trees (tree_id, width_m, height_m, observations, height_top_seen) "
            "VALUES ('1', 2.71, 2.55, 30, 0), ('2', 2.68, 2.60, 30, 1)"
        )
    before = (run_dir / "traits.sqlite").read_bytes()
    page = _report(run_dir, tmp_path / "run.html")
    header, *rows = page.table("tree")
    cells = {r[1]: (r[header.index("width (m)")], r[header.index("height (m)")]) for r in rows}
    assert cells == {"1": ("2.71", ">2.55"), "2": ("2.68", "2.60")}
    assert (run_dir / "traits.sqlite").read_bytes() == before
