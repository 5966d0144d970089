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


def tree(tree_id, east, north, width=2.5, height=2.4, ndvi=0.7, field_id=None, status="found"):
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
        add(store, "a", T0, [tree("1", *GRID[0], width=2.0, height=2.0, ndvi=0.70)])
        add(
            store,
            "b",
            T0 + 60 * DAY_NS,
            [tree("7", GRID[0][0] + 0.3, GRID[0][1], width=2.4, height=2.3, ndvi=0.62)],
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
