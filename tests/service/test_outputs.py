"""Orchard scale: trees out of range are finalised and dropped from memory with their
records unchanged, and the outputs are the same as when every tree is kept (issue 13)."""

from __future__ import annotations

import dataclasses
import json
import sqlite3

import numpy as np
import pytest

from tests.helpers.surveys import twin_survey
from tests.helpers.twin import grid_drive
from treetraits.drivers.records import POINT_DTYPE
from treetraits.errors import ConfigError
from treetraits.pipeline.config import MapperConfig, TrackingConfig, TraitsConfig
from treetraits.pipeline.georef import _feature, write_trees_geojson
from treetraits.pipeline.mapper import TreeMapper
from treetraits.service.outputs import RunWriter
from treetraits.service.survey import ScanOutcome, SurveyProcessor

FAR_M = 100.0  # beyond the default tracking.retire_m (50 m)


def config(method: str, retire_m: float) -> MapperConfig:
    return MapperConfig(
        tracking=TrackingConfig(retire_m=retire_m), traits=TraitsConfig(method=method)
    )


def survey(method: str, retire_m: float, out_dir):
    """The grid drive through a mapper and a RunWriter, then two scans 100 m on (an empty
    one: the robot drove away from the trees). Returns the mapper, the writer and the
    ScanResults of the drive and of the two far scans."""
    data = grid_drive()
    mapper = TreeMapper(config(method, retire_m), data.calibration)
    out_dir.mkdir()
    writer = RunWriter(out_dir, SurveyProcessor(mapper, data.calibration))
    results = []
    for scan, frame, pose in zip(data.scans, data.frames, data.poses, strict=True):
        result = mapper.process(scan, frame, pose)
        writer.commit(ScanOutcome(scan, pose, frame, result))
        results.append(result)
    far = []
    # An empty scan where the robot drove on to (same times: nothing else changes).
    empty = dataclasses.replace(data.scans[-1], points=np.zeros(0, POINT_DTYPE))
    pose = dataclasses.replace(data.poses[-1], x=data.poses[-1].x + FAR_M)
    for _ in range(2):
        result = mapper.process(empty, None, pose)
        writer.commit(ScanOutcome(empty, pose, None, result))
        far.append(result)
    writer.export()
    writer.close()
    return mapper, writer, results, far


@pytest.fixture(scope="module")
def surveyed(tmp_path_factory):
    """`survey` of a method and retire_m, run once for the module's tests (they only read
    it) into a folder of its own: the returns of `survey` and that folder."""
    done = {}

    def run(method: str, retire_m: float):
        if (method, retire_m) not in done:
            out_dir = tmp_path_factory.mktemp(f"{method}-retire-{retire_m:g}") / "run"
            done[method, retire_m] = (*survey(method, retire_m, out_dir), out_dir)
        return done[method, retire_m]

    return run


@pytest.mark.parametrize("method", ["paper", "robust"])
def test_trees_out_of_range_are_finalised_once_and_unchanged(method, surveyed):
    kept, _, kept_results, _, _ = surveyed(method, 0.0)
    finalised, _, results, far, _ = surveyed(method, 50.0)
    # While the robot is among the trees none is finalised, and every scan's outcome is
    # the same as when all are kept.
    assert all(r.retired == [] for r in results)
    assert [repr(r.clusters) for r in results] == [repr(r.clusters) for r in kept_results]
    # 100 m on, every tree goes at once, the first time only; none is kept in memory.
    ids = [t.tree_id for t in kept.trees()]
    assert len(ids) >= 4
    assert far[0].retired == ids and far[1].retired == []
    assert finalised.tracker.tracks == [] and not finalised._trees
    # Their records are the ones the mapper that keeps every tree reports.
    assert repr(finalised.trees()) == repr(kept.trees())
    assert repr(finalised.trees({ids[0]})) == repr([kept.trees()[0]])


def test_outputs_are_the_same_with_trees_finalised(surveyed):
    runs = {"kept": surveyed("paper", 0.0)[-1], "finalised": surveyed("paper", 50.0)[-1]}
    for name in ("trees.csv", "trees.geojson", "rejected.geojson"):
        kept = (runs["kept"] / name).read_bytes()
        assert (runs["finalised"] / name).read_bytes() == kept, name
    tables = []
    for run in ("kept", "finalised"):
        with sqlite3.connect(runs[run] / "traits.sqlite") as db:
            tables.append(
                (
                    db.execute("SELECT * FROM trees ORDER BY tree_id").fetchall(),
                    db.execute("SELECT * FROM observations ORDER BY rowid").fetchall(),
                )
            )
    assert len(tables[0][0]) >= 4
    assert repr(tables[1]) == repr(tables[0])


def test_retire_m_must_keep_trees_in_view():
    with pytest.raises(ConfigError, match="retire_m"):
        MapperConfig(tracking=TrackingConfig(retire_m=20.0))  # the view reaches 27 m
    with pytest.raises(ConfigError, match="retire_m"):
        TrackingConfig(retire_m=-1.0)
    assert MapperConfig(tracking=TrackingConfig(retire_m=0.0)).tracking.retire_m == 0.0


@pytest.mark.parametrize("per_write", [1000, 1, 2, 3])
def test_geojson_is_json_dumps_text_and_reused(tmp_path, monkeypatch, per_write, surveyed):
    """trees.geojson's text is json.dump(indent=1)'s byte for byte, when records are
    reused from the previous write too, and however many features are joined per write
    (a slice boundary between any two of them)."""
    from treetraits.pipeline import georef
    from treetraits.pipeline.georef import RenderCache

    monkeypatch.setattr(georef, "FEATURES_PER_WRITE", per_write)
    _, writer, _, _, _ = surveyed("paper", 0.0)
    trees = writer.georeferenced()
    assert len(trees) >= 4
    cache = RenderCache()
    for rows in ([], trees, trees[:2] + trees[3:], trees):
        write_trees_geojson(tmp_path / "ours.geojson", rows, cache)
        with open(tmp_path / "json.geojson", "w", encoding="utf-8") as f:
            json.dump(
                {"type": "FeatureCollection", "features": [_feature(t) for t in rows]}, f, indent=1
            )
            f.write("\n")
        assert (tmp_path / "ours.geojson").read_bytes() == (tmp_path / "json.geojson").read_bytes()


def test_missing_trees_taken_in_piece_by_piece_are_those_of_the_whole_path(tmp_path):
    """Each export takes in the path driven since the last one (`RunWriter.missing`). On
    a twin survey that starts without a fix (its path first in odom, placed once the map
    is re-anchored to UTM) and with two field-map trees that are not there, the missing
    trees after every 5 scans are those the whole path gives: each field-map tree's
    nearest approach by a k-d tree over every path point placed so far, as before."""
    from scipy.spatial import cKDTree

    from treetraits.drivers import recording as rec
    from treetraits.drivers.calibration import load_calibration
    from treetraits.pipeline.fieldmap import load_field_map
    from treetraits.pipeline.georef import FieldMapIndex, georeference, missing_trees
    from treetraits.service.config import ServiceConfig
    from treetraits.service.survey import make_processor
    from treetraits.sim.gnss import GnssSettings
    from treetraits.sim.orchard import TreeSettings
    from treetraits.sim.run import SurveySettings

    settings = SurveySettings(
        path="straight",
        goal=12.0,
        seed=1,
        trees=TreeSettings(missing=2),
        # Longer than the 10 s scans wait for a first fix: the run maps in odom first.
        gnss=GnssSettings(outages=((0.0, 13.0),)),
    )
    result = twin_survey(settings)
    with rec.read_recording(result.recording) as recording:
        calibration = load_calibration(recording.metadata.calibration)
        messages = [(m.topic, bytes(m.data), m.log_time, m.publish_time) for m in recording]
    processor = make_processor(ServiceConfig(), calibration)
    field_map = load_field_map(result.field_map)
    (tmp_path / "out").mkdir()
    writer = RunWriter(tmp_path / "out", processor, field_map)
    checked, seen_odom, seen_missing = 0, False, 0
    for message in messages:
        for outcome in processor.feed(*message):
            writer.commit(outcome)
            seen_odom |= outcome.pose is not None and outcome.pose.frame == "odom"
            if writer.scans % 5:
                continue
            found = writer.georeferenced()
            missing = writer.missing(found)
            grid = processor.localizer.grid
            if grid is None:
                assert missing == []
                continue
            path = georeference(writer._path, grid, (), utm_from_odom=processor.utm_from_odom)
            xy = np.array([(p.easting, p.northing) for p in path if p.easting is not None])
            index = FieldMapIndex(field_map, grid)
            passed, _ = cKDTree(xy).query(index.xy)
            assert missing == missing_trees(index, found, passed, writer.missing_range_m)
            checked += 1
            seen_missing = max(seen_missing, len(missing))
    writer.close()
    assert seen_odom and processor.anchor is not None  # the path began in odom
    assert checked > 10 and seen_missing == 2


def test_an_export_that_takes_longer_pushes_the_next_back():
    """Exports rewrite every tree, so they cost more as a survey grows: the next one waits
    until they take no more than `max_share` of the time, and never less than `every_s`."""
    from treetraits.service.outputs import next_export_after

    assert next_export_after(100.0, 0.01, 5.0, 0.02) == 105.0  # 0.01 s: the period rules
    # 0.4 s (50,000 trees here): 19.6 s after it, so 0.4 of every 20 s.
    later = next_export_after(100.0, 0.4, 5.0, 0.02)
    assert later == pytest.approx(119.6)
    assert 0.4 / (later - 100.0 + 0.4) == pytest.approx(0.02)
    assert next_export_after(100.0, 3.0, 5.0, 1.0) == 105.0  # a share of 1: the period only
