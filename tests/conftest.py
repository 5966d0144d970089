"""The suite's pytest fixtures (the shared builders are in tests/helpers)."""

from __future__ import annotations

import cv2
import pytest

from tests.helpers.captures import VLP16_CAPTURES


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
