"""`treetraits replay` of a damaged twin recording: the damage is skipped, the rest is
replayed, the summary says what was lost, and the exit status is 3 ("completed with data
loss") unless --allow-damaged."""

from __future__ import annotations

import json
import random
import sqlite3

import pytest

from tests.helpers.recordings import chunk_spans
from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.drivers import recording as rec
from treetraits.drivers.recording.rotation import RotatingRecorder
from treetraits.errors import EXIT_DATA_LOSS
from treetraits.sim.run import SurveySettings


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    # Two trees, 3 m driven: about 60 scans in some 25 chunks of 256 KiB.
    return twin_survey(SurveySettings(columns=2, rows=1, goal=3.0, seed=0))


def replay(path, out, capsys, *options) -> tuple[int, dict, str]:
    """Exit status, the --json summary and stderr of a replay."""
    capsys.readouterr()
    status = main(["replay", str(path), "--out", str(out), "--json", *options])
    captured = capsys.readouterr()
    return status, json.loads(captured.out), captured.err


@pytest.fixture(scope="module")
def intact(survey, tmp_path_factory) -> dict:
    """The run facts of the intact recording's replay (scans, trees, ...)."""
    out = tmp_path_factory.mktemp("intact")
    assert main(["replay", str(survey.recording), "--out", str(out), "--json"]) == 0
    db = sqlite3.connect(out / "traits.sqlite")
    return {key: _fact(value) for key, value in db.execute("SELECT key, value FROM run")}


def _fact(text: str):
    """A run fact: JSON, or a plain string (strings are stored as they are)."""
    try:
        return json.loads(text)
    except ValueError:
        return text


def last_scan_t(out) -> int:
    db = sqlite3.connect(out / "traits.sqlite")
    return db.execute("SELECT MAX(scan_t) FROM observations").fetchone()[0]


def test_an_intact_recording_reports_no_loss(intact):
    assert intact["damaged_chunks"] == 0 and intact["truncated"] is False
    assert intact["lost"] == [] and intact["data_loss"] is False
    assert intact["scans"] > 50


@pytest.mark.parametrize("where", ["data", "frame"])
def test_a_damaged_middle_chunk_is_skipped_and_the_rest_replayed(
    survey, intact, tmp_path, capsys, where
):
    """64 zero bytes in the middle chunk: inside its compressed data (its CRC fails), or
    over its frame (opcode, length, times: the reader finds the next chunk)."""
    chunks = chunk_spans(survey.recording)
    assert len(chunks) > 10
    start, end, chunk = chunks[len(chunks) // 2]
    at = (start + end) // 2 if where == "data" else start
    data = bytearray(survey.recording.read_bytes())
    data[at : at + 64] = bytes(64)
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))

    out = tmp_path / "out"
    status, summary, err = replay(damaged, out, capsys)

    assert status == EXIT_DATA_LOSS
    assert summary["damaged_chunks"] == 1 and summary["truncated"] is False
    assert summary["data_loss"] is True and len(summary["lost"]) == 1
    assert summary["lost"][0]["from"] and summary["lost"][0]["to"]
    assert "1 damaged chunk(s) skipped" in err and err.count("\n") == 1
    # One chunk is about a quarter of a second: a few scans lost, not the half after it.
    assert intact["scans"] - 6 <= summary["scans"] < intact["scans"]
    assert last_scan_t(out) > chunk.message_end_time + 1_000_000_000
    assert summary["trees"] == intact["trees"]

    # Accepted: the same outputs, exit 0; the table says what was lost.
    capsys.readouterr()
    argv = ["replay", str(damaged), "--out", str(out), "--force", "--allow-damaged"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "DATA LOSS: 1 damaged chunk(s) skipped; messages lost between" in printed


def test_a_recording_cut_at_60_percent_says_so(survey, intact, tmp_path, capsys):
    data = survey.recording.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])

    status, summary, err = replay(cut, tmp_path / "out", capsys)

    assert status == EXIT_DATA_LOSS
    assert summary["truncated"] is True and summary["damaged_chunks"] == 0
    assert summary["data_loss"] is True
    (lost,) = summary["lost"]
    assert lost["from"] and lost["to"] == ""  # from the last message read to the end
    assert "the file is cut short" in err
    assert 0.45 * intact["scans"] <= summary["scans"] <= 0.7 * intact["scans"]

    status, summary, _ = replay(cut, tmp_path / "out", capsys, "--force", "--allow-damaged")
    assert status == 0 and summary["truncated"] is True


def test_sparse_bit_flips_are_reported_not_zero_trees_with_exit_0(survey, intact, tmp_path, capsys):
    """Issue 14, case 2: 30 single-bit flips spread over the file used to replay as
    "0 trees from 0 scans", exit 0. Every chunk a flip lands in fails its CRC and is
    skipped; the rest is replayed and the loss is said."""
    data = bytearray(survey.recording.read_bytes())
    rng = random.Random(1)
    for _ in range(30):
        data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    flipped = tmp_path / "flipped.mcap"
    flipped.write_bytes(bytes(data))

    status, summary, err = replay(flipped, tmp_path / "out", capsys)

    assert status == EXIT_DATA_LOSS
    assert summary["data_loss"] is True and summary["damaged_chunks"] >= 10
    assert len(summary["lost"]) == summary["damaged_chunks"]
    assert 0 < summary["scans"] < intact["scans"]
    assert "damaged chunk(s) skipped" in err and err.count("\n") == 1


def test_a_recording_cut_inside_its_attachment_says_the_field_map_is_lost(
    survey, intact, tmp_path, capsys
):
    """The twin attaches its field map at the end: cut there, every scan is read but the
    field map is gone, and the trees go unmatched. That is said, not silent."""
    data = survey.recording.read_bytes()
    name = data.find(rec.FIELD_MAP_NAME.encode())  # the attachment record (its index follows)
    assert name > 0.9 * len(data)  # the attachment is at the end
    cut = tmp_path / "cut_attachment.mcap"
    cut.write_bytes(data[: name + 200])

    status, summary, err = replay(cut, tmp_path / "out", capsys)

    assert status == EXIT_DATA_LOSS
    assert summary["truncated"] is True and summary["field_map"] == {"source": "none", "trees": 0}
    assert summary["scans"] == intact["scans"] and summary["matched"] == 0
    assert intact["matched"] == intact["trees"] > 0
    assert "no field map was read" in err and "--field-map" in err

    # Given the map, the same trees are matched again (the loss is the map, said).
    status, summary, _ = replay(
        cut, tmp_path / "out", capsys, "--force", "--field-map", str(survey.field_map)
    )
    assert status == EXIT_DATA_LOSS and summary["matched"] == intact["matched"]
    assert summary["field_map"]["source"] == "--field-map"


def test_a_live_recording_cut_short_replays_with_data_loss_and_its_field_map(
    survey, tmp_path, capsys
):
    """`run --record` writes through `RotatingRecorder`, which attaches the field map at
    the start of each file: cut at 60 %, the file replays with exit 3 ("completed with
    data loss"), says it is cut, and still matches its trees to the map."""
    live = tmp_path / "live.mcap"
    with rec.read_recording(survey.recording) as source:
        calibration = source.metadata.calibration
        recorder = RotatingRecorder(
            live,
            max_bytes=1 << 30,
            chunk_bytes=256 * 1024,
            fsync_every_s=1.0,
            calibration=calibration,
            field_map=survey.field_map.read_bytes(),
        )
        with recorder:
            for m in source:
                recorder.write(m.topic, m.data, m.log_time, m.publish_time)
    data = live.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])

    capsys.readouterr()
    status = main(["replay", str(cut), "--out", str(tmp_path / "out"), "--json"])
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert status == EXIT_DATA_LOSS
    assert summary["truncated"] is True and summary["data_loss"] is True
    assert summary["field_map"]["source"] == "attachment" and summary["matched"] >= 1
    assert "the file is cut short" in captured.err and "no field map" not in captured.err
