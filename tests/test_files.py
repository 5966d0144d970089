"""`treetraits.files`: the one atomic file write every layer uses, and the UTC stamp that
names runs and recordings."""

from __future__ import annotations

import os
from datetime import datetime, timezone

import pytest

from treetraits.files import utc_stamp, write_atomically


def test_text_is_utf8_with_newlines_as_written(tmp_path):
    path = tmp_path / "a.txt"
    write_atomically(path, lambda f: f.write("é\nb\r\n"))
    assert path.read_bytes() == "é\nb\r\n".encode()


def test_bytes_are_written_as_they_are(tmp_path):
    path = tmp_path / "a.bin"
    write_atomically(path, lambda f: f.write(b"\x00\n\xff"), binary=True)
    assert path.read_bytes() == b"\x00\n\xff"


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_the_mode_is_open_s_or_the_one_asked(tmp_path, umask):
    old = os.umask(umask)
    try:
        write_atomically(tmp_path / "default", lambda f: f.write("x"))
        write_atomically(tmp_path / "shared", lambda f: f.write("x"), permissions=0o644)
        write_atomically(tmp_path / "own", lambda f: f.write("x"), permissions=0o600)
        with open(tmp_path / "plain", "w") as f:
            f.write("x")
    finally:
        os.umask(old)
    mode = {p.name: p.stat().st_mode & 0o777 for p in tmp_path.iterdir()}
    assert mode["plain"] == 0o666 & ~umask and mode["default"] == mode["plain"]
    assert (mode["shared"], mode["own"]) == (0o644, 0o600)


def test_a_failed_write_leaves_the_old_file_and_no_temp_file(tmp_path):
    path = tmp_path / "out"
    write_atomically(path, lambda f: f.write("old"))

    def fails(f) -> None:
        f.write("half")
        raise OSError("No space left on device")

    with pytest.raises(OSError, match="No space left"):
        write_atomically(path, fails)
    assert path.read_text() == "old" and os.listdir(tmp_path) == ["out"]


def test_the_temp_file_is_hidden_beside_the_target(tmp_path):
    seen = []
    write_atomically(tmp_path / "trees.csv", lambda f: seen.extend(os.listdir(tmp_path)))
    (name,) = seen
    assert name.startswith(".trees.csv.") and name.endswith(".tmp")


def test_utc_stamp_is_sortable_and_safe_in_a_path():
    moment = datetime(2026, 11, 23, 16, 18, 0, 999_999, tzinfo=timezone.utc)
    assert utc_stamp(moment) == "20261123T161800Z"
    assert len(utc_stamp()) == len("20261123T161800Z") and utc_stamp().endswith("Z")
