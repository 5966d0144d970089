"""Things that are not trees, and trees that are hard: every clutter kind is a mesh of its
own in the scene (a ray at it hits its label) and a row of the objects file; young, old,
hedgerow, irregular and missing trees in the truth."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest

from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.sim.clutter import KINDS, ClutterSettings
from treetraits.sim.orchard import TreeSettings
from treetraits.sim.paths import drive, waypoints
from treetraits.sim.run import SurveySettings, build_world

EVERYTHING = ClutterSettings(
    weeds=40,
    drip_lines="ground",
    posts=True,
    wires=True,
    standing_people=1,
    walking_people=1,
    vehicle=True,
    wall=True,
)


@pytest.fixture(scope="module")
def world():
    settings = SurveySettings(path="straight", rows=2, goal=14.0, clutter=EVERYTHING)
    poses = drive(waypoints(settings.path, settings.width, settings.length, settings.goal))
    return build_world(settings, np.random.default_rng(0), poses, 0.0), poses


def down(scene, x, y, t_s=0.0):
    """The label a vertical ray from 10 m up at (x, y) hits at time t_s."""
    _, label = scene.cast(np.array([[x, y, 10.0]]), np.array([[0.0, 0.0, -1.0]]), t_s * 1e9)
    return int(label[0])


def test_every_clutter_kind_is_in_the_scene_with_its_own_label(world):
    world, poses = world
    kinds = {o.kind for o in world.objects}
    assert kinds == set(KINDS)
    assert len({o.label for o in world.objects}) == len(world.objects)  # one label each
    tree_labels = set(range(1, len(world.trees) + 1))
    assert not tree_labels & {o.label for o in world.objects}
    for o in world.objects:
        if o.kind in ("weed", "wire", "walking_person"):
            continue  # porous, thin or moving: below
        x, y = o.x, o.y
        if o.kind == "drip_line":
            x = o.x - o.length / 2 + 0.05  # at the row's end, clear of the crowns
        assert down(world.scene, x, y) == o.label, o
    # A weed clump is porous, but a few rays into its middle find it.
    weed = next(o for o in world.objects if o.kind == "weed")
    hits = {
        down(world.scene, weed.x + dx, weed.y + dy)
        for dx in (-0.05, 0.0, 0.05)
        for dy in (-0.05, 0.0, 0.05)
    }
    assert weed.label in hits
    # The wire: a ray across the row at its height, between the post and the first crown.
    wire = next(o for o in world.objects if o.kind == "wire")
    x = wire.x - wire.length / 2 + 0.4
    _, label = world.scene.cast(
        np.array([[x, wire.y - 0.5, wire.height]]), np.array([[0.0, 1.0, 0.0]]), 0.0
    )
    assert int(label[0]) == wire.label
    # Nothing but weeds stands where the robot drives.
    path = poses[:, 1:3]
    for o in world.objects:
        if o.kind in ("weed", "walking_person", "drip_line", "wire"):
            continue
        assert np.hypot(*(path - (o.x, o.y)).T).min() > 1.0, o


def test_the_walking_person_crosses_the_rows_and_keeps_clear_of_the_robot(world):
    world, poses = world
    walker = next(o for o in world.objects if o.kind == "walking_person")
    assert walker.length > 8.0  # walks from beyond one side of the path to the other
    # Where is the person at a few times: a ray down where the walk says they are hits
    # them, and their old place is empty again.
    walk = next(m for m in world.scene._moving if m[1] == walker.label)[2]
    seen = []
    for t in (0.0, 3.0, 6.0):
        y = float(walk.y_at(t))
        assert down(world.scene, walker.x, y, t) == walker.label
        seen.append(y)
    assert max(seen) - min(seen) > 1.0
    # At every moment of the drive, 1 m or more between the person and the robot.
    times = poses[::10, 0]
    gap = np.hypot(poses[::10, 1] - walker.x, poses[::10, 2] - walk.y_at(times))
    assert gap.min() > 1.0


def test_hard_trees_young_old_hedgerow_irregular_and_missing():
    settings = SurveySettings(
        rows=3,
        columns=2,
        trees=TreeSettings(young_fraction=0.34, old_fraction=0.34, missing=1),
    )
    world = build_world(settings, np.random.default_rng(0))
    planted = [t for t in world.trees if t.kind == "tree"]
    assert sum(t.kind == "missing" for t in world.trees) == 1
    assert all(math.isnan(t.width) for t in world.trees if t.kind == "missing")
    heights = sorted(t.height for t in planted)
    assert 0.9 < heights[0] < 1.6  # a young tree (1.0-1.5 m by construction)
    assert 4.6 < heights[-1] < 5.4  # an old one (~5 m)
    hedge = SurveySettings(length=2.75, rows=4, trees=TreeSettings(hedgerow=True))
    trees = build_world(hedge, np.random.default_rng(0)).trees
    # Crowns wider than the in-row spacing: neighbours touch and overlap.
    assert all(t.width > 2.75 for t in trees)
    # Irregular crowns: lopsided, the crown's middle off the trunk.
    lobed = SurveySettings(trees=TreeSettings(irregular_fraction=1.0))
    assert (
        build_world(lobed, np.random.default_rng(0)).trees
        != build_world(SurveySettings(), np.random.default_rng(0)).trees
    )


def test_objects_and_missing_trees_in_the_files_beside_the_recording(tmp_path):
    settings = SurveySettings(
        path="straight",
        rows=1,
        goal=7.0,
        trees=TreeSettings(missing=1),
        clutter=dataclasses.replace(EVERYTHING, weeds=10, drip_lines="hung"),
    )
    survey = twin_survey(settings)
    with open(survey.objects_csv) as f:
        objects = list(csv.DictReader(f))
    assert {o["kind"] for o in objects} == set(KINDS)
    assert {"kind", "x", "y", "size_m"} <= set(objects[0])
    with open(survey.truth_csv) as f:
        reader = csv.DictReader(f)
        truth = list(reader)
    # The truth's columns keep their order; kind is appended.
    assert reader.fieldnames[-1] == "kind" and reader.fieldnames[:2] == ["tree_id", "row"]
    assert sorted(r["kind"] for r in truth) == ["missing", "tree"]
    missing = next(r for r in truth if r["kind"] == "missing")
    assert missing["width_m"] == "" and missing["height_m"] == ""
    # The field map keeps the missing position.
    field_map = json.loads(survey.field_map.read_text())
    assert missing["tree_id"] in {f["properties"]["id"] for f in field_map["features"]}


def test_sim_command_refuses_bad_field_conditions(tmp_path, capsys):
    out = str(tmp_path / "x.mcap")
    for bad in (
        ["--slope", "nan"],
        ["--slope", "0.3"],
        ["--slope-across", "inf"],
        ["--undulation", "0.5"],
        ["--young", "0.7", "--old", "0.7"],
        ["--missing", "99"],
        ["--weeds", "-1"],
        ["--wires"],
        ["--grid", "nanx5"],
    ):
        assert main(["sim", "--out", out, *bad]) == 2, bad
    assert "--slope must be a finite number" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (["--goal", "-1"], "--goal must be a finite number in [0.1, 1000], got -1.0"),
        (["--goal", "1e9"], "--goal must be a finite number in [0.1, 1000]"),
        (["--goal", "inf"], "--goal must be a finite number in [0.1, 1000], got inf"),
        (["--outage", "5:1"], "--outage START must come before END, got '5:1'"),
        (["--outage", "nan:5"], "--outage START must be a finite number in [0, 86400]"),
        (["--outage", "0:1e12"], "--outage END must be a finite number in [0, 86400]"),
        (["--slope", "inf"], "--slope must be a finite number in [-0.15, 0.15], got inf"),
        (["--grid", "1e300x5"], "--grid values must be finite and in [0.5, 30]"),
        (["--layout", "1000x1000"], "--layout values must be finite and in [1, 50]"),
        (["--layout", "0x3"], "--layout values must be finite and in [1, 50]"),
        (["--seed", "-1"], "--seed must be a non-negative integer, got -1"),
    ],
)
def test_sim_options_name_the_option_and_its_range(tmp_path, capsys, bad, message):
    """Issue 14, case 6: each refused with one line (exit 2), nothing written."""
    out = tmp_path / "x.mcap"
    assert main(["sim", "--out", str(out), *bad]) == 2
    err = capsys.readouterr().err
    assert err.startswith("treetraits: error: ") and err.count("\n") == 1, err
    assert message in err
    assert list(tmp_path.iterdir()) == []
