"""The suite's pytest fixtures (the shared builders are in tests/helpers)."""

from __future__ import annotations

import os

import cv2
import pytest

from tests.helpers.captures import VLP16_CAPTURES

# The modules whose tests drive the twin end to end, the longest first (measured with
# --durations). `make test` keeps a module on one worker (--dist loadfile) and hands the
# modules out in this order, so that the workers end together on short modules instead of
# one waiting for the other's last replay.
LONGEST_FIRST = (
    "tests/service/test_replay.py",
    "tests/service/test_replay_hedgerow.py",
    "tests/sim/test_run.py",
    "tests/drivers/rosbag/test_citrusfarm.py",
    "tests/drivers/rosbag/test_convert.py",
    "tests/test_jit.py",
    "tests/season/test_batch.py",
    "tests/season/test_report.py",
    "tests/cli/test_rules.py",
    "tests/service/test_process.py",
    "tests/cli/test_errors.py",
    "tests/evaluation/test_evaluation.py",
    "tests/service/test_outputs.py",
    "tests/export/test_foxglove.py",
    "tests/pipeline/test_mapper.py",
)


def pytest_collection_modifyitems(config, items) -> None:
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return  # one process: the order does not change how long it takes
    rank = {path: i for i, path in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::", 1)[0], len(rank)))


@pytest.fixture(params=VLP16_CAPTURES)
def capture(request) -> str:
    return request.param


@pytest.fixture
def decode_calls(monkeypatch):
    """Counts every JPEG decode in the process, OpenCV's (`cv2.imdecode`) and the frames'
    (`simplejpeg.decode_jpeg`, `Frame.decode`); the real ones still run."""
    import simplejpeg

    calls = []

    def counting(real):
        def decode(*args, **kwargs):
            calls.append(1)
            return real(*args, **kwargs)

        return decode

    monkeypatch.setattr(cv2, "imdecode", counting(cv2.imdecode))
    monkeypatch.setattr(simplejpeg, "decode_jpeg", counting(simplejpeg.decode_jpeg))
    return calls
