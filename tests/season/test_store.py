"""The season's tree identity (pipeline/linking.py) and the season store
(treetraits/season/store.py): trees linked across surveys by field id or by position, missing trees
flagged, growth per 30 days. The batch over real twin recordings is tests/season/test_batch.py."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest

from treetraits.cli import main
from treetraits.pipeline.linking import (
    DEFAULT_LINK_GATE_M,
    growth_per_30_days,
    link_by_position,
    link_surveys,
)
from treetraits.pipeline.trees import CSV_COLUMNS, TREE_FIELD, Tree, csv_row
from treetraits.season.export import write_season_csv
from treetraits.season.store import SURVEY_TREE_COLUMNS, VISIT_COLUMNS, SeasonStore, Survey

DAY_NS = 86400 * 10**9
T0 = 1_778_605_200 * 10**9  # 2026-05-12T17:00:00Z
# A block of 3 rows x 4 trees, 5 m apart (the twin's default spacing), UTM 11N.
GRID = [(467000.0 + 5 * c, 3758000.0 + 5 * r) for r in range(3) for c in range(4)]


def tree(
    tree_id,
    east,
    north,
    width=2.5,
    height=2.4,
    ndvi=0.7,
    field_id=None,
    status="found",
    top_seen=None,
    sides=None,
):
    return Tree(
        tree_id,
        east,
        north,
        "11N",
        None,
        None,
        width,
        height,
        ndvi,
        20,
        None,
        None,
        field_id,
        None,
        status,
        height_top_seen=top_seen,
        width_sides_seen=sides,
    )


def test_hungarian_links_each_tree_to_itself_under_gnss_noise():
    rng = np.random.default_rng(7)
    known = np.array(GRID)
    # DGPS-like noise, 0.25 m per axis; the survey lists its trees in another order.
    order = rng.permutation(len(known))
    new = known[order] + rng.normal(0, 0.25, known.shape)
    assert link_by_position(known, new) == [int(i) for i in order]


def test_a_tree_beyond_the_gate_is_not_taken_for_its_neighbour():
    known = np.array([(0.0, 0.0), (5.0, 0.0)])
    # Greedy nearest would give the first new tree (2.4 m from both) to known 0 or 1;
    # the gate refuses both, and the second new tree is known 1.
    new = np.array([(2.4, 0.6), (5.2, 0.1)])
    assert link_by_position(known, new) == [None, 1]
    # Two new trees near one known tree: the nearer one is it, the other is new.
    assert link_by_position(known, np.array([(0.5, 0.0), (0.1, 0.0)])) == [None, 0]


def test_surveys_linked_by_position_with_gnss_noise_and_one_tree_removed():
    rng = np.random.default_rng(3)
    first = [tree(str(i + 1), e, n, width=2.0 + 0.01 * i) for i, (e, n) in enumerate(GRID)]
    noisy = np.array(GRID) + rng.normal(0, 0.25, (len(GRID), 2))
    removed = 5  # the sixth tree died between the surveys
    second = [
        tree(str(100 + i), e, n, width=2.3 + 0.01 * i)
        for i, (e, n) in enumerate(noisy)
        if i != removed
    ][::-1]  # another run's ids, in another order
    trees = link_surveys([(1, first), (2, second)])
    assert len(trees) == len(GRID)  # no tree counted twice
    for i, t in enumerate(trees):
        assert t.tree_id == f"pos-{i + 1}"
        (s1, st1, a), (s2, st2, b) = t.visits
        assert (s1, st1, a.tree_id) == (1, "found", str(i + 1))
        if i == removed:
            assert (s2, st2) == (2, "missing")
        else:
            assert (s2, st2, b.tree_id) == (2, "found", str(100 + i))
            assert b.width_m == pytest.approx(a.width_m + 0.3)


def test_a_survey_of_another_part_of_the_block_does_not_make_trees_missing():
    first = [tree(str(i), e, n) for i, (e, n) in enumerate(GRID)]
    # The second drive covered the first row only (y = 3758000).
    second = [tree(str(i), e, n + 0.1) for i, (e, n) in enumerate(GRID[:4])]
    trees = link_surveys([(1, first), (2, second)])
    assert [len(t.visits) for t in trees] == [2] * 4 + [1] * 8
    assert all(v[1] == "found" for t in trees for v in t.visits)


def test_field_ids_link_whatever_the_positions_say():
    first = [tree("1", 0.0, 0.0, field_id="A1"), tree("2", 5.0, 0.0, field_id="A2")]
    # A bad fix moved the whole second survey by 3 m: the field ids still hold.
    second = [
        tree("9", 3.0, 0.0, field_id="A1"),
        tree("", 8.0, 0.0, field_id="A2", status="missing"),
    ]
    trees = link_surveys([(1, first), (2, second)])
    assert [t.tree_id for t in trees] == ["A1", "A2"]
    assert [v[1] for v in trees[1].visits] == ["found", "missing"]


def test_growth_per_30_days_from_first_to_last_measurement():
    times = [T0, T0 + 15 * DAY_NS, T0 + 60 * DAY_NS]
    assert growth_per_30_days(times, [2.0, None, 2.6]) == pytest.approx(0.3)
    assert growth_per_30_days(times[:1], [2.0]) is None
    assert growth_per_30_days([T0, T0], [2.0, 2.2]) is None  # no time between them


def add(store, name, t_start, trees, block="north"):
    survey = Survey(
        block,
        f"{name}.mcap",
        f"fp-{name}",
        t_start,
        "treetraits test",
        "key",
        f"/runs/{name}",
        False,
        {"trees": len(trees)},
    )
    return store.add_survey(survey, trees, "2026-06-01T00:00:00Z")


def test_the_store_links_in_date_order_whatever_the_processing_order(tmp_path):
    a = [tree(str(i), e, n, width=2.0) for i, (e, n) in enumerate(GRID)]
    b = [tree(str(i), e + 0.2, n, width=2.5) for i, (e, n) in enumerate(GRID) if i != 0]
    results = []
    for name, order in (("forward", ("a", "b")), ("backward", ("b", "a"))):
        with SeasonStore(tmp_path / f"{name}.sqlite") as store:
            for survey in order:
                add(
                    store,
                    survey,
                    T0 if survey == "a" else T0 + 30 * DAY_NS,
                    a if survey == "a" else b,
                )
                store.relink("north", DEFAULT_LINK_GATE_M)
            results.append(
                [
                    (t.tree_id, [(v.recording, v.status, v.width_m) for v in t.visits])
                    for t in store.trees()
                ]
            )
    assert results[0] == results[1]
    first = dict(results[0])["pos-1"]
    assert first == [("a.mcap", "found", 2.0), ("b.mcap", "missing", None)]


def test_a_recording_processed_again_replaces_its_survey(tmp_path):
    path = tmp_path / "season.sqlite"
    with SeasonStore(path) as store:
        add(store, "a", T0, [tree("1", *GRID[0], width=2.0)])
        assert store.processed("north", "fp-a", "treetraits test", "key")
        assert not store.processed("north", "fp-a", "treetraits test", "other key")
        add(store, "a", T0, [tree("1", *GRID[0], width=2.2)])
        store.relink("north", DEFAULT_LINK_GATE_M)
        assert len(store.surveys()) == 1
        (t,) = store.trees()
        assert [v.width_m for v in t.visits] == [2.2]
    db = sqlite3.connect(path)
    assert db.execute("SELECT COUNT(*) FROM survey_trees").fetchone()[0] == 1


def test_two_blocks_may_share_field_ids(tmp_path, capsys):
    with SeasonStore(tmp_path / "season.sqlite") as store:
        for block, width in (("north", 2.0), ("south", 3.0)):
            add(store, block, T0, [tree("1", *GRID[0], width=width, field_id="T1")], block)
            store.relink(block, DEFAULT_LINK_GATE_M)
        trees = store.trees()
    assert [(t.block, t.tree_id, [v.width_m for v in t.visits]) for t in trees] == [
        ("north", "T1", [2.0]),
        ("south", "T1", [3.0]),
    ]
    assert (
        main(["season", "tree", "T1", "--season", str(tmp_path / "season.sqlite"), "--json"]) == 0
    )
    assert [t["block"] for t in json.loads(capsys.readouterr().out)["trees"]] == ["north", "south"]


def test_season_cli_json_export_and_errors(tmp_path, capsys):
    path = tmp_path / "season.sqlite"
    with SeasonStore(path) as store:
        measured = {"top_seen": True, "sides": 2}  # heights and widths whole
        add(store, "a", T0, [tree("1", *GRID[0], width=2.0, height=2.0, ndvi=0.70, **measured)])
        add(
            store,
            "b",
            T0 + 60 * DAY_NS,
            [tree("7", GRID[0][0] + 0.3, GRID[0][1], width=2.4, height=2.3, ndvi=0.62, **measured)],
        )
        store.relink("north", DEFAULT_LINK_GATE_M)
    assert main(["season", "trees", "--season", str(path), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    (only,) = document["trees"]
    assert only["id"] == "pos-1"
    assert [(s["date"], s["width_m"]) for s in only["surveys"]] == [
        ("2026-05-12T17:00:00.000Z", 2.0),
        ("2026-07-11T17:00:00.000Z", 2.4),
    ]
    assert main(["season", "tree", "pos-1", "--season", str(path)]) == 0
    assert "width 2.40 m" in capsys.readouterr().out
    assert main(["season", "tree", "nope", "--season", str(path)]) == 2
    assert "no tree 'nope'" in capsys.readouterr().err

    out = tmp_path / "export"
    assert main(["season", "export", "--season", str(path), "--out", str(out)]) == 0
    lines = (out / "season.csv").read_text().splitlines()
    assert lines[0].startswith("tree_id,block,field_id,row,survey_id,date")
    assert len(lines) == 3
    (feature,) = json.loads((out / "season.geojson").read_text())["features"]
    growth = feature["properties"]
    # 0.4 m wider and 0.3 m taller in 60 days; NDVI down 0.08.
    assert growth["width_change_m_per_30d"] == pytest.approx(0.2)
    assert growth["height_change_m_per_30d"] == pytest.approx(0.15)
    assert growth["ndvi_change"] == pytest.approx(-0.08)
    assert main(["season", "export", "--season", str(path), "--out", str(out)]) == 4

    not_a_season = tmp_path / "x.sqlite"
    not_a_season.write_bytes(b"this is not SQLite" * 100)
    assert main(["season", "trees", "--season", str(not_a_season)]) == 2
    assert "not a season store" in capsys.readouterr().err
    assert main(["season", "trees", "--season", str(tmp_path / "none.sqlite")]) == 2
    assert not (tmp_path / "none.sqlite").exists()


def test_the_season_keeps_a_run_trees_columns_as_the_run_does(tmp_path):
    run_tree = tree("1", *GRID[0], width=2.71234, height=2.60049, ndvi=0.612345)
    with SeasonStore(tmp_path / "season.sqlite") as store:
        add(store, "a", T0, [run_tree])
        store.relink("north", DEFAULT_LINK_GATE_M)
        types = {
            table: {c[1]: c[2] for c in store._db.execute(f"PRAGMA table_info({table})")}
            for table in ("survey_trees", "tree_surveys")
        }
        write_season_csv(tmp_path / "season.csv", store.trees())
    for name in SURVEY_TREE_COLUMNS:
        stored = "run_tree_id" if name == "tree_id" else name
        assert types["survey_trees"][stored] == TREE_FIELD[name].format.sql_type, name
    for name in VISIT_COLUMNS:
        assert types["tree_surveys"][name] == TREE_FIELD[name].format.sql_type, name
    # season.csv's tree cells are trees.csv's.
    header, line = (tmp_path / "season.csv").read_text().splitlines()
    season = dict(zip(header.split(","), line.split(","), strict=True))
    run = dict(zip(CSV_COLUMNS, csv_row(run_tree), strict=True))
    assert [season[name] for name in VISIT_COLUMNS] == [run[name] for name in VISIT_COLUMNS]
    assert season["width_m"] == "2.712" and season["ndvi"] == "0.6123"


def test_lower_bounds_are_kept_marked_and_left_out_of_the_height_change(tmp_path, capsys):
    """A tree measured whole in May and July, and in June from a drive that saw its crown
    from one lane with its top cut (2.00 m: it did not shrink). The season keeps each
    survey's flags; `season trees`, the JSON and season.csv mark June's values; the height
    change is May to July, the lower bound left out; the width change says when an end
    of it was seen from one side."""
    path = tmp_path / "season.sqlite"
    whole = {"top_seen": True, "sides": 2}
    cut = {"top_seen": False, "sides": 1}
    with SeasonStore(path) as store:
        for name, day, height, flags in (("may", 0, 2.79, whole), ("june", 30, 2.00, cut)):
            add(store, name, T0 + day * DAY_NS, [tree("1", *GRID[0], height=height, **flags)])
        add(store, "july", T0 + 60 * DAY_NS, [tree("1", *GRID[0], width=2.6, height=2.85, **whole)])
        store.relink("north", DEFAULT_LINK_GATE_M)
        (t,) = store.trees()
    assert [(v.height_top_seen, v.width_sides_seen) for v in t.visits] == [
        (True, 2),
        (False, 1),
        (True, 2),
    ]

    assert main(["season", "trees", "--season", str(path)]) == 0
    text = capsys.readouterr().out
    assert "width >2.50 m  height >2.00 m" in text  # June's
    assert "width 2.50 m  height 2.79 m" in text  # May's, unmarked
    assert "width >: a lower bound, the crown seen from one side only" in text
    assert "height >: a lower bound, the crown's top never bracketed within 5 %" in text
    assert main(["season", "trees", "--season", str(path), "--json"]) == 0
    surveys = json.loads(capsys.readouterr().out)["trees"][0]["surveys"]
    assert [(s["height_top_seen"], s["width_sides_seen"]) for s in surveys] == [
        (True, 2),
        (False, 1),
        (True, 2),
    ]

    out = tmp_path / "export"
    assert main(["season", "export", "--season", str(path), "--out", str(out)]) == 0
    header, *lines = (out / "season.csv").read_text().splitlines()
    rows = [dict(zip(header.split(","), line.split(","), strict=True)) for line in lines]
    assert [(r["height_top_seen"], r["width_sides_seen"]) for r in rows] == [
        ("true", "2"),
        ("false", "1"),
        ("true", "2"),
    ]
    (feature,) = json.loads((out / "season.geojson").read_text())["features"]
    growth = feature["properties"]
    # May to July: 0.06 m in 60 days; June's 2.00 m is left out (with it: -0.79 m).
    assert growth["height_change_m_per_30d"] == pytest.approx(0.03)
    assert growth["height_lower_bounds"] == 1
    assert growth["width_change_m_per_30d"] == pytest.approx(0.05)
    assert growth["width_change_one_sided"] is False  # May and July: both sides
    assert (growth["height_top_seen"], growth["width_sides_seen"]) == (True, 2)  # July's


def test_with_every_height_a_lower_bound_there_is_no_height_change(tmp_path):
    from treetraits.season.export import growth

    with SeasonStore(tmp_path / "season.sqlite") as store:
        for name, day, height in (("may", 0, 2.79), ("july", 60, 2.0)):
            trees = [tree("1", *GRID[0], height=height, top_seen=False, sides=1)]
            add(store, name, T0 + day * DAY_NS, trees)
        store.relink("north", DEFAULT_LINK_GATE_M)
        (t,) = store.trees()
    change = growth(t)
    assert change["height_change_m_per_30d"] is None and change["height_lower_bounds"] == 2
    assert change["width_change_one_sided"] is True


# Version 1 of the season store (before it kept the flags): the tables that changed,
# restated as the stores on disk hold them.
VERSION_1_TABLES = """
CREATE TABLE season (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE surveys (
    survey_id INTEGER PRIMARY KEY, block TEXT NOT NULL, recording TEXT NOT NULL,
    fingerprint TEXT NOT NULL, t_start INTEGER NOT NULL, software TEXT NOT NULL,
    config_key TEXT NOT NULL, run_dir TEXT NOT NULL, data_loss INTEGER NOT NULL,
    summary TEXT NOT NULL, processed_at TEXT NOT NULL, UNIQUE (block, fingerprint)
);
CREATE TABLE survey_trees (
    survey_id INTEGER NOT NULL REFERENCES surveys (survey_id) ON DELETE CASCADE,
    run_tree_id TEXT NOT NULL, status TEXT NOT NULL, field_id TEXT, row TEXT,
    easting REAL, northing REAL, utm_zone TEXT, lat REAL, lon REAL,
    width_m REAL, height_m REAL, ndvi REAL, observations INTEGER NOT NULL
);
CREATE TABLE trees (
    tree_id TEXT NOT NULL, block TEXT NOT NULL, field_id TEXT, row TEXT,
    easting REAL, northing REAL, utm_zone TEXT, lat REAL, lon REAL,
    PRIMARY KEY (block, tree_id)
);
CREATE TABLE tree_surveys (
    tree_id TEXT NOT NULL,
    survey_id INTEGER NOT NULL REFERENCES surveys (survey_id) ON DELETE CASCADE,
    status TEXT NOT NULL, run_tree_id TEXT,
    easting REAL, northing REAL, lat REAL, lon REAL,
    width_m REAL, height_m REAL, ndvi REAL, observations INTEGER,
    PRIMARY KEY (tree_id, survey_id)
);
CREATE TABLE failures (
    recording TEXT NOT NULL, block TEXT NOT NULL, software TEXT NOT NULL,
    config_key TEXT NOT NULL, error TEXT NOT NULL, at TEXT NOT NULL
);
INSERT INTO season VALUES ('schema_version', '1');
INSERT INTO surveys VALUES (1, 'north', 'may.mcap', 'fp-may', 1778605200000000000,
    'treetraits 0.1.0', 'key', '/runs/may', 0, '{}', '2026-05-12T18:00:00Z');
INSERT INTO survey_trees VALUES (1, '1', 'found', NULL, NULL, 467000.0, 3758000.0, '11N',
    NULL, NULL, 2.5, 2.79, 0.7, 20);
INSERT INTO trees VALUES ('pos-1', 'north', NULL, NULL, 467000.0, 3758000.0, '11N', NULL,
    NULL);
INSERT INTO tree_surveys VALUES ('pos-1', 1, 'found', '1', 467000.0, 3758000.0, NULL, NULL,
    2.5, 2.79, 0.7, 20);
"""


def test_a_version_1_season_is_read_with_its_flags_unknown_and_upgraded_by_a_writer(
    tmp_path, capsys
):
    path = tmp_path / "season.sqlite"
    with sqlite3.connect(path) as db:
        db.executescript(VERSION_1_TABLES)
    # Read as it is (`season`, `report` open it read-only): its flags not known.
    with SeasonStore(path, create=False) as store:
        (t,) = store.trees()
    assert [(v.height_m, v.height_top_seen, v.width_sides_seen) for v in t.visits] == [
        (2.79, None, None)
    ]
    assert main(["season", "trees", "--season", str(path)]) == 0
    text = capsys.readouterr().out
    assert "height 2.79 m" in text and "not known whether they are lower bounds" in text
    assert sqlite3.connect(path).execute("SELECT value FROM season").fetchone() == ("1",)

    # A batch's writer adds the columns (NULL for the survey there) and the next survey
    # comes with its flags.
    with SeasonStore(path) as store:
        add(store, "july", T0 + 60 * DAY_NS, [tree("1", *GRID[0], top_seen=False, sides=1)])
        store.relink("north", DEFAULT_LINK_GATE_M)
        (t,) = store.trees()
    assert [(v.height_top_seen, v.width_sides_seen) for v in t.visits] == [(None, None), (False, 1)]
    db = sqlite3.connect(path)
    assert db.execute("SELECT value FROM season").fetchone() == ("2",)
    for table in ("survey_trees", "tree_surveys"):
        columns = [c[1] for c in db.execute(f"PRAGMA table_info({table})")]
        assert columns[-2:] == ["height_top_seen", "width_sides_seen"], table
