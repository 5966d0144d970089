"""docs/cli.md, "Every command, same rules": read-only inputs are read and left as they
were, a directory where a file is wanted is refused before any work, damage is reported
by every command that reads a recording (exit 3, --allow-damaged), a text file is no
NMEA log, and a ROS bag is refused with the import to run first. Real twin recordings,
real SQLite stores, the real ROS 2 bag of tests/fixtures."""

from __future__ import annotations

import json
import shlex
import shutil
import time
from pathlib import Path

import pytest

from tests.helpers.captures import VLP16_DIR
from tests.helpers.net import free_udp_port
from tests.helpers.paths import FIXTURES
from tests.helpers.readonly import run_with_read_only
from tests.helpers.season import small_season
from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.errors import EXIT_DATA_LOSS, EXIT_USAGE
from treetraits.sim.run import SurveySettings

NEBULA_BAG = VLP16_DIR / "nebula_vlp16_dual_10hz_bag"
NMEA_LOG = FIXTURES / "nmea" / "ublox-zed-f9p-nmea.nmea"


@pytest.fixture(scope="module")
def survey():
    # Two trees, 3 m driven, camera frames included: a real recording in a few seconds.
    return twin_survey(SurveySettings(columns=2, rows=1, goal=3.0, seed=0))


@pytest.fixture(scope="module")
def run_dir(survey, tmp_path_factory) -> Path:
    """A replay's output directory (traits.sqlite closed: no -wal, no -shm)."""
    out = tmp_path_factory.mktemp("rules") / "run"
    assert main(["replay", str(survey.recording), "--out", str(out), "--json"]) == 0
    return out


@pytest.fixture(scope="module")
def cut(survey, tmp_path_factory) -> Path:
    """The recording cut in half (a power cut, a copy stopped short)."""
    data = survey.recording.read_bytes()
    path = tmp_path_factory.mktemp("cut") / "cut.mcap"
    path.write_bytes(data[: len(data) // 2])
    return path


def listing(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def one_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("treetraits: error: ") and err.count("\n") == 1, err
    return err


# --- 1. read-only inputs are read -----------------------------------------------------


def test_a_read_only_run_directory_and_season_are_read(run_dir, tmp_path):
    """On a read-only disk (a bind mount as root, no write permission otherwise) `report`
    said `not an SQLite store (unable to open database file)` and `season trees` said
    `SQLite: unable to open database file` naming no file. Both read now, and nothing is
    left beside the stores."""
    before = listing(run_dir)
    page = tmp_path / "run.html"
    result = run_with_read_only(run_dir, ["report", str(run_dir), "--out", str(page)])
    assert result.returncode == 0, result.stderr
    assert page.read_text().startswith("<!DOCTYPE html>")
    assert listing(run_dir) == before

    folder = tmp_path / "season"
    folder.mkdir()
    season = small_season(folder / "season.sqlite")
    trees = run_with_read_only(folder, ["season", "trees", "--season", str(season), "--json"])
    assert trees.returncode == 0, trees.stderr
    assert '"id": "pos-3"' in trees.stdout
    page = tmp_path / "season.html"
    result = run_with_read_only(folder, ["report", str(season), "--out", str(page)])
    assert result.returncode == 0, result.stderr
    assert listing(folder) == ["season.sqlite"]


def test_commands_that_only_read_a_run_leave_no_wal_or_shm_in_it(run_dir, tmp_path, capsys):
    """`report` and `export foxglove` of a run directory left traits.sqlite-wal and -shm
    there (SQLite's mode=ro makes them)."""
    before = listing(run_dir)
    assert "traits.sqlite-wal" not in before
    assert main(["report", str(run_dir), "--out", str(tmp_path / "run.html")]) == 0
    assert listing(run_dir) == before
    view = tmp_path / "view.mcap"
    assert main(["export", "foxglove", str(run_dir), "--out", str(view), "--json"]) == 0
    assert listing(run_dir) == before
    season = small_season(tmp_path / "season.sqlite")
    for argv in (
        ["season", "trees", "--season", str(season)],
        ["season", "export", "--season", str(season), "--out", str(tmp_path / "export")],
        ["report", str(season), "--out", str(tmp_path / "season.html")],
    ):
        assert main(argv) == 0, argv
    assert not list(tmp_path.glob("season.sqlite-*"))


def test_an_sqlite_error_names_the_store(tmp_path, capsys):
    not_sqlite = tmp_path / "notes.sqlite"
    not_sqlite.write_bytes(b"these are notes, not a store\n" * 200)
    assert main(["season", "trees", "--season", str(not_sqlite)]) == EXIT_USAGE
    assert f"{not_sqlite}: not a season store" in one_error(capsys)
    run = tmp_path / "run"
    run.mkdir()
    (run / "traits.sqlite").write_bytes(not_sqlite.read_bytes())
    assert main(["report", str(run), "--out", str(tmp_path / "r.html")]) == EXIT_USAGE
    assert f"{run / 'traits.sqlite'}: not an SQLite store" in one_error(capsys)


# --- 2. a directory where a file is wanted ----------------------------------------------


def test_a_directory_where_a_file_is_wanted_is_refused_before_any_work(
    survey, run_dir, tmp_path, capsys
):
    """Every command's one-file output: exit 2 naming the directory, with or without
    --force (export foxglove --force ran its whole pipeline, then failed `Is a
    directory`), in less time than reading the input would take."""
    folder = tmp_path / "a_folder"
    folder.mkdir()
    rec, out = str(survey.recording), str(folder)
    season = small_season(tmp_path / "season.sqlite")
    cases = [
        (["report", str(run_dir), "--out", out], "--out"),
        (["report", str(season), "--out", out, "--force"], "--out"),
        (["export", "foxglove", rec, "--out", out], "--out"),
        (["export", "foxglove", rec, "--out", out, "--force"], "--out"),
        (["import", str(NEBULA_BAG), "--out", out, "--force"], "--out"),
        (["sim", "--goal", "1", "--out", out, "--force"], "--out"),
        (["inspect", rec, "--png", out], "--png"),
        (["fuse", rec, "--scan", "2", "--out", out], "--out"),
        (["play", rec, "--camera-video", out], "--camera-video"),
        (["batch", rec, "--season", out], "--season"),
        (["record", "--out", out], "--out"),
    ]
    for argv, option in cases:
        capsys.readouterr()
        start = time.monotonic()
        assert main(argv) == EXIT_USAGE, argv
        assert time.monotonic() - start < 2.0, argv  # the replay alone takes seconds
        err = one_error(capsys)
        assert err == (
            f"treetraits: error: {folder}: is a directory; {option} takes the file to write "
            f"(e.g. {folder / 'NAME'})\n"
        ), argv
    assert listing(folder) == []


def test_an_existing_file_output_is_exit_4_and_kept(survey, tmp_path, capsys):
    view = tmp_path / "view.mcap"
    view.write_bytes(b"an earlier view")
    assert main(["export", "foxglove", str(survey.recording), "--out", str(view)]) == 4
    assert "--force" in one_error(capsys)
    assert view.read_bytes() == b"an earlier view"


# --- 4. damage reported by every command that reads a recording ------------------------


def test_every_command_that_reads_a_cut_recording_says_so_exit_3(cut, tmp_path, capsys):
    """`export foxglove` of a recording cut in half exited 0 with no word, and so did
    `lidar info`, `lidar export`, `nmea info`, `fuse`, `play`, `camera info` and `camera
    grab`: now as `replay`, one DATA LOSS line on stderr naming the recording, exit 3, and
    --allow-damaged accepts it (exit 0) with the same line. What was read is used."""
    view = tmp_path / "view.mcap"
    frames = tmp_path / "frames"  # camera grab wants a new folder each time
    lidar = f"127.0.0.1:{free_udp_port()}"  # play sends to loopback only, 20x its pace
    cases = [
        ["replay", str(cut), "--out", str(tmp_path / "run"), "--force"],
        ["export", "foxglove", str(cut), "--out", str(view), "--force"],
        ["lidar", "info", str(cut)],
        ["lidar", "export", str(cut), "--out", str(tmp_path / "pcd"), "--force"],
        ["nmea", "info", str(cut)],
        ["fuse", str(cut), "--scan", "2", "--out", str(tmp_path / "fused.png")],
        ["play", str(cut), "--lidar", lidar, "--telemetry-port", "0", "--speed", "20"],
        ["camera", "info", str(cut)],
        ["camera", "grab", str(cut), "--out", str(frames)],
    ]
    for argv in cases:
        for allow, status in (([], EXIT_DATA_LOSS), (["--allow-damaged"], 0)):
            shutil.rmtree(frames, ignore_errors=True)
            capsys.readouterr()
            assert main([*argv, *allow]) == status, (argv, allow)
            err = capsys.readouterr().err
            (line,) = [x for x in err.splitlines() if "DATA LOSS" in x]
            assert line.startswith(f"treetraits: warning: {cut}: DATA LOSS: the file is cut short")
            assert line.endswith("(exit 3; --allow-damaged accepts it)"), line
    assert view.stat().st_size > 0 and (tmp_path / "pcd" / "scans.csv").is_file()
    assert list(frames.glob("*.jpg")) and (frames / "timestamps.csv").is_file()
    # `camera info`'s facts say it too, as `lidar info`'s do.
    capsys.readouterr()
    assert main(["camera", "info", str(cut), "--json", "--allow-damaged"]) == 0
    facts = json.loads(capsys.readouterr().out)
    assert facts["data_loss"] is True and facts["measured"]["frames"] > 0


def test_inspect_reports_damage_before_its_scan_and_past_the_cut(cut, tmp_path, capsys):
    """`inspect` reads up to its scan: a cut after it changes nothing shown (exit 0); a
    scan asked for past the cut names the cut, not just the count."""
    assert main(["inspect", str(cut), "--scan", "0", "--no-tracks"]) == 0
    assert "DATA LOSS" not in capsys.readouterr().err
    assert main(["inspect", str(cut), "--scan", "1000", "--no-tracks"]) == EXIT_USAGE
    err = one_error(capsys)
    assert "--scan 1000: the input holds" in err and f"{cut}: the file is cut short" in err


# --- 5. a text file is no NMEA log -----------------------------------------------------


def test_a_text_file_is_not_an_nmea_log_but_junk_around_sentences_is(tmp_path, capsys):
    text = tmp_path / "notes.txt"
    text.write_text("field notes\nrow 3 pruned, $5 of twine\n")
    assert main(["nmea", "info", str(text)]) == EXIT_USAGE
    assert one_error(capsys) == (
        f"treetraits: error: {text}: no NMEA sentence was found in it (expected an NMEA log, "
        "or a recording with /gnss/nmea)\n"
    )
    mixed = tmp_path / "mixed.nmea"
    lines = NMEA_LOG.read_bytes().splitlines(keepends=True)[:40]
    mixed.write_bytes(b"field notes\n\x00\xb5b binary\n" + b"".join(lines) + b"trailing junk\n")
    assert main(["nmea", "info", str(mixed), "--json"]) == 0
    assert '"valid": ' in capsys.readouterr().out


# --- 6. a ROS bag where a recording is read --------------------------------------------


def test_a_ros2_bag_directory_is_refused_with_the_import_to_run(tmp_path, capsys):
    """It was `no such file` (or `Is a directory`); now exit 2 and the exact command."""
    bag = str(NEBULA_BAG)
    command = f"treetraits import {shlex.quote(bag)} --out {shlex.quote(bag + '.mcap')}"
    for argv in (
        ["lidar", "info", bag],
        ["lidar", "export", bag, "--out", str(tmp_path / "pcd")],
        ["replay", bag, "--out", str(tmp_path / "run")],
        ["inspect", bag],
        ["nmea", "info", bag],
        ["play", bag],
        ["fuse", bag, "--scan", "0", "--out", str(tmp_path / "f.png")],
        ["export", "foxglove", bag, "--out", str(tmp_path / "v.mcap")],
        ["calibrate", "classify", bag, "--field-map", str(NMEA_LOG)],
    ):
        capsys.readouterr()
        assert main(argv) == EXIT_USAGE, argv
        err = one_error(capsys)
        assert err.startswith(f"treetraits: error: {bag}: a ROS 2 bag"), argv
        assert err.endswith(f"make a recording of the bag first: {command}\n"), argv
    (storage,) = NEBULA_BAG.glob("*.db3")
    assert main(["lidar", "info", str(storage)]) == EXIT_USAGE
    assert f"{storage}: a file of the ROS 2 bag {bag}, not" in one_error(capsys)
    assert not (tmp_path / "run").exists() and not (tmp_path / "pcd").exists()
