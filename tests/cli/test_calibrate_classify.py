"""`treetraits calibrate classify`: the vegetation cues of the objects at field-map trees
and of the others, from a twin drive with clutter, and the pivots and weights proposed
from them (pipeline/vegetation_fit.py)."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math

import numpy as np
import pytest

from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.errors import EXIT_OUTPUT_EXISTS, EXIT_USAGE
from treetraits.pipeline import vegetation_fit as fit
from treetraits.pipeline.config import ClassifyConfig
from treetraits.service.config import load_config
from treetraits.sim.clutter import ClutterSettings
from treetraits.sim.gnss import GnssSettings
from treetraits.sim.run import SurveySettings

# Two rows of two trees, 11 m driven, with posts, a person, a parked vehicle and a wall:
# the smallest twin drive with trees and clutter of every kind the evidence must tell
# apart (about 20 s to simulate, 40 s to replay).
CLUTTERED = SurveySettings(
    path="straight",
    rows=2,
    goal=11.0,
    clutter=ClutterSettings(posts=True, standing_people=1, vehicle=True, wall=True),
)
# Two trees, 3 m driven: a recording in a few seconds, for the errors.
TINY = SurveySettings(columns=2, rows=1, goal=3.0, seed=0)


@pytest.fixture(scope="module")
def drive():
    return twin_survey(CLUTTERED)


@pytest.fixture(scope="module")
def calibrated(drive, tmp_path_factory):
    """One run of the command, --json --out: (its JSON, the written file)."""
    out = tmp_path_factory.mktemp("classify") / "classify.toml"
    argv = ["calibrate", "classify", str(drive.recording), "--field-map", str(drive.field_map)]
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        status = main([*argv, "--out", str(out), "--json"])
    assert status == 0, text.getvalue()
    return json.loads(text.getvalue()), out


def test_both_groups_are_found_and_match_a_plain_replay(drive, calibrated, tmp_path, capsys):
    result, _ = calibrated
    assert result["matched"] > 0 and result["others"] > 0
    assert len(result["objects"]["trees"]) == result["matched"]
    assert len(result["objects"]["others"]) == result["others"]
    assert main(["replay", str(drive.recording), "--out", str(tmp_path / "r"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    # The objects at field-map trees are the replay's own matches (plus rejected objects
    # at a field-map tree no found tree matched, none on this drive).
    assert result["matched_as_trees"] == summary["matched"] > 0
    assert result["matched"] == summary["matched"]
    assert {o["field_id"] for o in result["objects"]["trees"]} <= {t.tree_id for t in drive.trees}
    assert all(o["field_id"] is None for o in result["objects"]["others"])


def test_distributions_are_those_of_the_objects(calibrated):
    result, _ = calibrated
    objects = result["objects"]
    assert [c["cue"] for c in result["cues"]] == [c.name for c in fit.CUES]
    for cue in result["cues"]:
        for group in ("trees", "others"):
            values = [o[cue["cue"]] for o in objects[group] if o[cue["cue"]] is not None]
            shown = cue[group]
            assert shown["count"] == len(values)
            if values:
                p10, p50, p90 = np.percentile(values, [10, 50, 90])
                assert shown["p10"] == pytest.approx(p10)
                assert shown["p50"] == pytest.approx(p50)
                assert shown["p90"] == pytest.approx(p90)
    texture = next(c for c in result["cues"] if c["cue"] == "texture")
    # The twin's crowns are rougher than its posts, people, vehicle and wall.
    assert texture["trees"]["count"] > 0 and texture["others"]["count"] > 0
    assert texture["margin"] > 0
    assert texture["others"]["p90"] < texture["pivot"] < texture["trees"]["p10"]


def test_out_is_a_config_the_loader_takes(calibrated):
    result, out = calibrated
    assert result["written"] == str(out)
    section = result["section"]["detection"]["classify"]
    assert section
    assert set(section) <= {f.name for f in dataclasses.fields(ClassifyConfig)}
    config = load_config(out)
    for key, value in section.items():
        assert getattr(config.detection.classify, key) == pytest.approx(value)
    # Keys not proposed keep their defaults.
    assert config.detection.classify.min_height_m == ClassifyConfig().min_height_m


def test_text_output_prints_the_table_and_section(calibrated, drive, monkeypatch, capsys):
    """The printed table is the JSON's numbers (the replay's collection stubbed with the
    objects the real run found)."""
    from treetraits.cli import calibrate

    result, _ = calibrated
    data = {
        "summary": {"fixes": 1},
        "field_map_trees": result["field_map_trees"],
        "trees": result["objects"]["trees"],
        "others": result["objects"]["others"],
        "near": result["objects"]["near"],
        "found_matched": result["matched_as_trees"],
        "gate_m": result["gate_m"],
    }
    monkeypatch.setattr(calibrate, "collect_cues", lambda *args: data)
    argv = ["calibrate", "classify", str(drive.recording), "--field-map", str(drive.field_map)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"{result['matched']} objects at field-map trees" in out
    assert f"{result['others']} others" in out
    texture = next(c for c in result["cues"] if c["cue"] == "texture")
    assert f"{texture['trees']['p50']:.4g}" in out
    assert "[detection.classify]" in out
    for key in result["section"]["detection"]["classify"]:
        assert f"{key} = " in out


def test_out_over_an_existing_file_needs_force(drive, tmp_path, capsys):
    out = tmp_path / "mine.toml"
    out.write_text("# mine\n")
    argv = ["calibrate", "classify", str(drive.recording), "--field-map", str(drive.field_map)]
    assert main([*argv, "--out", str(out)]) == EXIT_OUTPUT_EXISTS == 4
    assert "--force" in capsys.readouterr().err
    assert out.read_text() == "# mine\n"


def test_no_field_map_tree_matched_exits_2(tmp_path, capsys):
    tiny = twin_survey(TINY)
    far = tmp_path / "elsewhere.csv"
    far.write_text("id,lat,lon\nA1,10.0,10.0\n")  # an orchard the robot never drove
    argv = ["calibrate", "classify", str(tiny.recording), "--field-map", str(far)]
    assert main(argv) == EXIT_USAGE == 2
    err = capsys.readouterr().err
    assert "GNSS fixes" in err and "field map covering" in err
    assert "Traceback" not in err


def test_a_recording_without_gnss_exits_2(tmp_path, capsys):
    # The receiver out for the whole drive: the run maps in odom, nothing is placed.
    blind = twin_survey(dataclasses.replace(TINY, gnss=GnssSettings(outages=((0.0, 1e6),))))
    argv = ["calibrate", "classify", str(blind.recording), "--field-map", str(blind.field_map)]
    assert main(argv) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "GNSS fixes" in err and "(GNSS fixes in the recording: 0)" in err


def test_an_empty_field_map_exits_2(tmp_path, capsys):
    tiny = twin_survey(TINY)
    empty = tmp_path / "empty.csv"
    empty.write_text("id,lat,lon\n")
    argv = ["calibrate", "classify", str(tiny.recording), "--field-map", str(empty)]
    assert main(argv) == EXIT_USAGE
    assert "holds no trees" in capsys.readouterr().err


# --- the statistics, on hand-made distributions ---------------------------------------


def _cue(name: str) -> fit.Cue:
    return next(c for c in fit.CUES if c.name == name)


def test_texture_apart_gives_the_geometric_middle_and_the_default_weight():
    trees = fit.distribution(np.linspace(0.06, 0.12, 21))
    others = fit.distribution(np.linspace(0.005, 0.03, 21))
    proposal = fit.propose(_cue("texture"), trees, others)
    assert trees.count == others.count == 21
    assert trees.p10 == pytest.approx(0.066) and others.p90 == pytest.approx(0.0275)
    assert proposal.margin == pytest.approx(0.066 - 0.0275)
    assert 0.03 < proposal.pivot < 0.06
    assert proposal.pivot == pytest.approx(math.sqrt(0.066 * 0.0275))
    assert proposal.weight == ClassifyConfig().texture_weight
    assert proposal.section == {"texture_pivot_m": proposal.pivot, "texture_weight": 1.0}


def test_overlapping_groups_weigh_nothing():
    trees = fit.distribution(np.linspace(0.02, 0.12, 21))
    others = fit.distribution(np.linspace(0.005, 0.06, 21))
    proposal = fit.propose(_cue("texture"), trees, others)
    assert proposal.margin < 0
    assert proposal.weight == 0.0 and proposal.pivot is None
    assert proposal.section == {"texture_weight": 0.0}


def test_planar_share_is_lower_on_foliage():
    trees = fit.distribution(np.linspace(0.0, 0.2, 11))  # p90 0.18
    others = fit.distribution(np.linspace(0.6, 1.0, 11))  # p10 0.64
    proposal = fit.propose(_cue("planar"), trees, others)
    assert proposal.margin == pytest.approx(0.64 - 0.18)
    assert proposal.pivot == pytest.approx((0.18 + 0.64) / 2)  # linear: arithmetic middle
    assert proposal.weight == ClassifyConfig().planar_weight
    # Reversed (the trees flatter than the others): they overlap on vegetation's side.
    assert fit.propose(_cue("planar"), others, trees).weight == 0.0


def test_intensity_apart_gets_a_weight_though_its_default_is_0():
    assert ClassifyConfig().intensity_weight == 0.0
    proposal = fit.propose(
        _cue("intensity"), fit.distribution([30, 35, 40, 45]), fit.distribution([3, 5, 8])
    )
    assert proposal.weight > 0 and 8 < proposal.pivot < 30


def test_a_cue_not_measured_on_a_group_keeps_the_config():
    proposal = fit.propose(
        _cue("ndvi"), fit.distribution([0.6, 0.7]), fit.distribution([None, math.nan])
    )
    assert proposal.pivot is None and proposal.weight is None and proposal.section == {}
    assert math.isnan(proposal.margin)
    assert fit.distribution([]) == fit.Distribution(0)


def test_section_rounds_and_keeps_only_the_proposed_keys():
    proposals = fit.propose_all(
        {"texture": [0.06, 0.1, 0.12], "planar": [0.1, 0.5]},
        {"texture": [0.01, 0.02], "planar": [0.2, 0.9]},
    )
    keys = fit.section(proposals)
    assert set(keys) == {"texture_pivot_m", "texture_weight", "planar_weight"}
    assert keys["planar_weight"] == 0.0
    assert keys["texture_pivot_m"] == float(f"{keys['texture_pivot_m']:.4g}")


def test_help_says_when_to_use_it():
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-m", "treetraits", "calibrate", "classify", "--help"],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0
    text = " ".join(result.stdout.split())
    for words in ("new orchard", "different sensor", "field map", "[detection.classify]"):
        assert words in text
