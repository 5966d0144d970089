"""Twin drives simulated once and shared: by every test module of a session, by the
workers of a parallel run and by the next session while nothing they are made of changed.

Simulating is the slow part of most end-to-end tests, and many modules drive the same
settings. A drive is cached under `out/test-twins/<key>/`, keyed like `treetraits eval`'s
cache (the settings, the version, the simulator's code and data) and also by the code that
encodes what the sensors send (drivers/, firmware_bridge/), so an encoder's change makes a
new recording. A file lock lets one worker simulate while the others wait for it. Tests
read the shared files and write elsewhere; `twin_survey` refuses a recording changed since
it was made.
"""

from __future__ import annotations

import csv
import dataclasses
import fcntl
import hashlib
import os
import pickle
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path

from tests.helpers.paths import REPO
from treetraits.evaluation.run import cache_key
from treetraits.sim.run import SurveyResult, SurveySettings, simulate_survey

TWIN_CACHE = REPO / "out" / "test-twins"
# Besides the simulator (in eval's key): what turns its world into the sensors' bytes.
ENCODER_FOLDERS = ("drivers", "firmware_bridge")
_RESULT = "result.pickle"


@cache
def _encoders_digest() -> str:
    digest = hashlib.sha256()
    for folder in ENCODER_FOLDERS:
        for path in sorted((REPO / folder).rglob("*.py")):
            digest.update(str(path.relative_to(REPO)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:8]


def survey_key(settings: SurveySettings) -> str:
    return f"{cache_key(settings)}-{_encoders_digest()}"


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _stamp(path: Path) -> tuple[int, int]:
    stat = path.stat()
    return stat.st_size, stat.st_mtime_ns


def _cached(settings: SurveySettings) -> SurveyResult:
    key = survey_key(settings)
    folder = TWIN_CACHE / key
    done = folder / _RESULT
    with _locked(TWIN_CACHE / f"{key}.lock"):
        if not done.is_file():
            shutil.rmtree(folder, ignore_errors=True)  # a drive cut short by a crash
            folder.mkdir(parents=True)
            result = simulate_survey(folder / "survey.mcap", settings)
            temp = done.with_suffix(".tmp")
            temp.write_bytes(pickle.dumps((result, _stamp(result.recording))))
            os.replace(temp, done)  # last: its presence means the drive is whole
    result, stamp = pickle.loads(done.read_bytes())
    if _stamp(result.recording) != stamp:
        raise AssertionError(
            f"{result.recording} changed since it was simulated: a test wrote to a shared "
            "twin drive (write a copy instead)"
        )
    return result


def twin_survey(settings: SurveySettings, into: Path | None = None) -> SurveyResult:
    """The drive of `settings`; with `into`, its files are linked into that folder (a test
    that writes beside the recording gets a folder of its own)."""
    result = _cached(settings)
    if into is None:
        return result
    into.mkdir(parents=True, exist_ok=True)
    linked = {}
    for field in ("recording", "truth_csv", "field_map", "objects_csv"):
        source = getattr(result, field)
        if source is None:
            continue
        link = into / source.name
        link.symlink_to(source)
        linked[field] = link
    return dataclasses.replace(result, **linked)


def truth_rows(survey):
    with open(survey.truth_csv) as f:
        return {r["tree_id"]: r for r in csv.DictReader(f)}


def offsets_from_truth(report, truth) -> list[tuple[float, float]]:
    """(east, north) of each reported tree from its field-map tree's truth, metres."""
    return [
        (
            t.easting - float(truth[t.field_id]["easting"]),
            t.northing - float(truth[t.field_id]["northing"]),
        )
        for t in report.trees
    ]
