"""Foliage and the mount in the evaluation: `eval --foliage` and `--lidar-height` reach
every case, the field suite grows every model, the paper suite the original twin's, and
the cache tells them apart."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from treetraits.evaluation import run as run_module
from treetraits.evaluation.cases import CASES, FIELD_CASES
from treetraits.evaluation.run import cache_key
from treetraits.sim.foliage import MODELS
from treetraits.sim.orchard import TreeSettings
from treetraits.sim.run import SurveySettings


def _models(settings: SurveySettings) -> set[str]:
    trees = settings.trees
    return set(trees.foliage_mix) if trees.foliage_mix else {trees.foliage}


def _cases_run_by(argv: list[str], tmp_path, monkeypatch) -> list:
    """The cases `treetraits eval ARGV` hands to the evaluation (which is not run)."""
    from treetraits.cli.eval import register

    seen: list = []

    def run_evaluation(cases, *args, **kwargs):
        seen.extend(cases)
        raise SystemExit(0)  # stop before simulating anything

    monkeypatch.setattr(run_module, "run_evaluation", run_evaluation)
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["eval", *argv, "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        args.run(args)
    return seen


@pytest.mark.parametrize("suite", ["paper", "field"])
def test_eval_foliage_reaches_every_case(suite, tmp_path, monkeypatch):
    cases = _cases_run_by(
        ["--suite", suite, "--cases", "all", "--foliage", "clumped"], tmp_path, monkeypatch
    )
    assert len(cases) == sum(c.suite == suite for c in CASES)
    for case in cases:
        assert _models(case.settings(3)) == {"clumped"}, case.name
        # Only the foliage is replaced.
        original = next(c for c in CASES if c.name == case.name)
        assert case.survey.trees.young_fraction == original.survey.trees.young_fraction
        assert case.survey.path == original.survey.path


def test_without_the_option_the_cases_keep_their_own_foliage(tmp_path, monkeypatch):
    cases = _cases_run_by(["--suite", "field", "--cases", "all"], tmp_path, monkeypatch)
    assert [c.survey for c in cases] == [c.survey for c in CASES if c.suite == "field"]


def test_the_field_suite_grows_every_model_and_the_paper_suite_the_original():
    field = set().union(*(_models(c.survey) for c in FIELD_CASES))
    assert field == set(MODELS)
    singly = [c.survey.trees.foliage for c in FIELD_CASES if not c.survey.trees.foliage_mix]
    assert len(set(singly)) >= 4  # not only through one mixed case
    for case in CASES:
        if case.suite == "paper":
            assert case.survey.trees == TreeSettings(), case.name


def test_the_cache_key_follows_the_foliage():
    keys = {cache_key(SurveySettings(trees=TreeSettings(foliage=name))) for name in MODELS}
    assert len(keys) == len(MODELS)
    mixed = SurveySettings(trees=TreeSettings(foliage_mix=("dense", "sparse")))
    assert cache_key(mixed) not in keys
    assert cache_key(SurveySettings()) == cache_key(
        SurveySettings(trees=TreeSettings(foliage="scattered"))
    )


def test_eval_rejects_an_unknown_model(tmp_path, capsys):
    from treetraits.cli.eval import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    with pytest.raises(SystemExit):
        parser.parse_args(["eval", "--foliage", "hedge", "--out", str(tmp_path)])
    assert "hedge" in capsys.readouterr().err


def test_eval_lidar_height_mounts_every_case_higher_and_the_cache_tells_it_apart(
    tmp_path, monkeypatch
):
    """`eval --lidar-height`: every case simulated with the LiDAR that high, nothing else
    changed, in recordings of their own; out of 0.2-5 m refused before any work."""
    argv = ["--suite", "field", "--cases", "all", "--lidar-height", "1.7"]
    cases = _cases_run_by(argv, tmp_path, monkeypatch)
    originals = [c for c in CASES if c.suite == "field"]
    assert [c.name for c in cases] == [c.name for c in originals]
    for case, original in zip(cases, originals, strict=True):
        assert case.settings(1).lidar_height == 1.7
        assert dataclasses.replace(case.survey, lidar_height=None) == original.survey
        assert cache_key(case.settings(1)) != cache_key(original.settings(1))
    from treetraits.cli import main

    assert main(["eval", "--out", str(tmp_path / "x"), "--lidar-height", "9"]) == 2
    assert not (tmp_path / "x").exists()
