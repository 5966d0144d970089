"""`treetraits batch` on Dask distributed over three small twin recordings, the season it
writes, and `treetraits report` on it: a 2-worker LocalCluster; a scheduler and a worker
started as processes of their own on loopback; the page parsed, its SVG figures read and
rendered by a real headless Chromium."""

from __future__ import annotations

import io
import json
import os
import shutil
import socket
import sqlite3
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.report_page import SVG, Page, by_id, texts
from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.pipeline.linking import link_surveys
from treetraits.season.store import SeasonStore
from treetraits.sim.run import SurveySettings

# Three drives of a 2x2 block (5 m spacing), 10 m each: a few seconds of data, the
# GNSS noise of each drive its own (another seed).
SEEDS = (1, 2, 3)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> list[Path]:
    settings = SurveySettings(columns=2, rows=2, goal=10.0)
    return [twin_survey(replace(settings, seed=seed)).recording for seed in SEEDS]


@pytest.fixture(scope="module")
def batch(recordings, tmp_path_factory):
    """The three recordings and a file that is no recording, through a 2-worker cluster."""
    folder = tmp_path_factory.mktemp("batch")
    notes = folder / "notes.mcap"
    notes.write_text("not a recording\n")
    season = folder / "season.sqlite"
    args = ["batch", *map(str, recordings), str(notes), "--season", str(season)]
    status, out = _run([*args, "--workers", "2", "--json"])
    return season, args, status, json.loads(out), notes


def _run(argv: list[str]) -> tuple[int, str]:
    import contextlib

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        status = main(argv)
    return status, buffer.getvalue()


def test_a_local_cluster_processes_every_recording_and_reports_the_bad_one(batch, recordings):
    season, _, status, outcome, notes = batch
    assert status == 3  # completed, but a recording is not in the season
    assert sorted(outcome["processed"]) == sorted(map(str, recordings))
    assert list(outcome["failed"]) == [str(notes)]
    assert "not a pcap, pcapng or MCAP file" in outcome["failed"][str(notes)]
    # Each run directory holds a replay's outputs, the robot's path among its facts.
    with SeasonStore(season, create=False) as store:
        surveys = store.surveys()
        assert [f["recording"] for f in store.failures()] == [str(notes)]
    assert len(surveys) == 3
    for survey in surveys:
        run_dir = Path(survey.run_dir)
        assert (run_dir / "trees.csv").is_file()
        facts = dict(sqlite3.connect(run_dir / "traits.sqlite").execute("SELECT * FROM run"))
        path = json.loads(facts["path"])
        assert len(path) >= 8  # one point per metre of the 10 m drive
        assert survey.summary["trees"] == 4


def test_season_trees_lists_every_tree_with_every_survey(batch, recordings):
    season = batch[0]
    status, out = _run(["season", "trees", "--season", str(season), "--json"])
    assert status == 0
    trees = json.loads(out)["trees"]
    # The twin's field map names its trees T1..T4: each is linked by its field id.
    assert [t["id"] for t in trees] == ["T1", "T2", "T3", "T4"]
    for t in trees:
        assert sorted(s["recording"] for s in t["surveys"]) == sorted(map(str, recordings))
        assert all(s["status"] == "found" for s in t["surveys"])
        # The twin's citrus trees are 2.6-2.8 m wide.
        assert all(2.0 < s["width_m"] < 3.4 for s in t["surveys"])
        assert all(s["date"].startswith("2026-05-12T17:00") for s in t["surveys"])


def test_a_rerun_skips_what_the_season_has(batch, recordings):
    season, args, *_ = batch
    status, out = _run([*args[:-3], "--season", str(season), "--json"])  # notes left out
    assert status == 0
    assert json.loads(out)["skipped"] == list(map(str, recordings))
    assert json.loads(out)["processed"] == []


def test_position_linking_on_the_runs_trees(batch):
    """The three runs' own trees, field ids taken away, one tree removed from the last:
    linked by position alone they make the same four trees, the removed one missing."""
    season = batch[0]
    with SeasonStore(season, create=False) as store:
        surveys = [
            (s.survey_id, [replace(t, field_id=None) for t in store._survey_trees(s.survey_id)])
            for s in store.surveys()
        ]
    removed = surveys[-1][1][0]
    surveys[-1] = (surveys[-1][0], surveys[-1][1][1:])
    linked = link_surveys(surveys)
    assert len(linked) == 4
    for tree in linked:
        statuses = [status for _, status, _ in tree.visits]
        first = tree.visits[0][2]
        if (first.easting - removed.easting) ** 2 + (first.northing - removed.northing) ** 2 < 1:
            assert statuses == ["found", "found", "missing"]
        else:
            assert statuses == ["found"] * 3


def _decode_png(data: bytes) -> np.ndarray:
    import matplotlib.image

    assert data.startswith(b"\x89PNG\r\n\x1a\n")
    return matplotlib.image.imread(io.BytesIO(data), format="png")


def test_the_season_report_is_one_page_with_its_figures(batch, tmp_path):
    season = batch[0]
    page = tmp_path / "season.html"
    assert main(["report", str(season), "--out", str(page)]) == 0
    parsed = Page.read(page.read_text())
    assert parsed.links == []  # nothing to fetch: it opens offline
    for heading in ("Map of the block", "Per row", "Distributions", "Growth"):
        assert heading in parsed.headings
    # Map, histograms, growth map, histories: inline SVG, drawn and labelled.
    assert set(parsed.figures) == {"map", "histograms", "growth", "histories"}
    for figure in parsed.figures.values():
        assert len(list(figure.iter(f"{SVG}path"))) > 20
        assert len(texts(figure)) > 10
    # The per-row table: the twin's two rows, two trees found in each.
    rows = {r[0]: r[1:3] for r in parsed.table("row")[1:]}
    assert rows == {"1": ["2", "0"], "2": ["2", "0"]}
    # The three surveys share the twin's one date: the time axis is the days around it
    # (matplotlib alone spreads a single date over years).
    ticks = texts(by_id(parsed.figures["histories"], "histories-width_m-dates"))
    assert ticks == ["2026-05-11", "2026-05-12", "2026-05-13", "2026-05-14", "survey date (UTC)"]
    assert main(["report", str(season), "--out", str(page)]) == 4  # kept without --force


def test_a_run_report_and_a_bad_source(batch, tmp_path, capsys):
    season = batch[0]
    with SeasonStore(season, create=False) as store:
        run_dir = store.surveys()[0].run_dir
    page = tmp_path / "run.html"
    assert main(["report", run_dir, "--out", str(page)]) == 0
    parsed = Page.read(page.read_text())
    assert set(parsed.figures) == {"map", "histograms"} and "Growth" not in parsed.headings
    # Heights whose top the LiDAR never saw are shown as lower bounds, as the store says.
    with sqlite3.connect(Path(run_dir) / "traits.sqlite") as db:
        flags = dict(
            db.execute("SELECT tree_id, height_top_seen FROM trees WHERE status = 'found'")
        )
    bounded = [tree_id for tree_id, seen in flags.items() if seen == 0]
    assert bounded  # a 10 m drive into a 2x2 block: no top in view (measured: 4 of 4)
    header, *rows = parsed.table("tree")
    heights = {r[header.index("run id")]: r[header.index("height (m)")] for r in rows}
    assert set(heights) == set(flags)
    for tree_id, seen in flags.items():
        assert heights[tree_id].startswith(">") == (seen == 0), (tree_id, heights[tree_id])
    text = page.read_text()  # the legend under the table says what the marks mean
    assert "Lower bounds: " in text and "the height is at least that" in text
    assert main(["report", str(tmp_path), "--out", str(tmp_path / "x.html")]) == 2
    assert "no traits.sqlite" in capsys.readouterr().err
    assert not (tmp_path / "x.html").exists()


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(
    CHROMIUM is None, reason="chromium not installed (`make test` installs it where apt has it)"
)
def test_chromium_renders_the_report(batch, tmp_path):
    page = tmp_path / "season.html"
    assert main(["report", str(batch[0]), "--out", str(page)]) == 0
    shot = tmp_path / "shot.png"
    result = subprocess.run(
        [
            CHROMIUM,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            "--window-size=1200,1800",
            f"--screenshot={shot}",
            page.as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    image = _decode_png(shot.read_bytes())
    assert image.shape[:2] == (1800, 1200)
    rgb = image[..., :3]
    # The page is drawn: the map's colours and the text, not a white or an error page.
    assert rgb.std() > 0.1
    assert len(np.unique((rgb * 255).astype(np.uint8).reshape(-1, 3), axis=0)) > 500


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_scheduler_and_a_worker_started_as_processes(recordings, tmp_path):
    port = _free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    started = []
    try:
        scheduler = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "distributed.cli.dask_scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--dashboard-address",
                ":0",
                "--no-show",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
        started.append(scheduler)
        address = f"tcp://127.0.0.1:{port}"
        _wait_for_port(port)
        worker = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "distributed.cli.dask_worker",
                address,
                "--nthreads",
                "1",
                "--nworkers",
                "1",
                "--no-dashboard",
                "--host",
                "127.0.0.1",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=env,
        )
        started.append(worker)
        season = tmp_path / "cluster.sqlite"
        status, out = _run(
            ["batch", str(recordings[0]), "--season", str(season), "--scheduler", address, "--json"]
        )
        assert status == 0
        assert json.loads(out)["processed"] == [str(recordings[0])]
        with SeasonStore(season, create=False) as store:
            assert len(store.trees()) == 4
    finally:
        for process in reversed(started):
            process.terminate()
        for process in reversed(started):
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def _wait_for_port(port: int, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise AssertionError(f"no scheduler on port {port} after {timeout} s")


def test_no_scheduler_there_is_a_clear_error(tmp_path, capsys):
    port = _free_port()
    rec = tmp_path / "x.mcap"
    rec.write_text("x")
    status = main(
        [
            "batch",
            str(rec),
            "--season",
            str(tmp_path / "s.sqlite"),
            "--scheduler",
            f"tcp://127.0.0.1:{port}",
            "--scheduler-timeout",
            "2",
        ]
    )
    assert status == 2
    assert "cannot connect" in capsys.readouterr().err


def test_a_cut_recording_is_reported_and_kept_as_far_as_it_reads(recordings, tmp_path, capsys):
    cut = tmp_path / "cut.mcap"
    data = recordings[0].read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    season = tmp_path / "cut.sqlite"
    argv = ["batch", str(cut), "--season", str(season), "--workers", "1", "--json"]
    status = main(argv)
    captured = capsys.readouterr()
    assert status == 3
    assert json.loads(captured.out)["damaged"] == [str(cut)]
    assert "damaged or cut" in captured.err
    with SeasonStore(season, create=False) as store:
        (survey,) = store.surveys()
    assert survey.data_loss and survey.summary["truncated"] is True
    # Kept in the season: a rerun skips it like any other recording.
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out)["skipped"] == [str(cut)]
