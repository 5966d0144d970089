"""The robot's install has none of the offline tools' extras: the commands that need one
name it, the others work without it. The extras are hidden from a child interpreter by a
`sitecustomize` that refuses to import them, as a machine without them would."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.net import free_udp_port
from tests.helpers.service import Service
from treetraits.errors import EXIT_USAGE
from treetraits.extras import EXTRA_MODULES

BLOCKER = """
import sys

HIDDEN = {hidden!r}
TRIED = {tried!r}


class _Hidden:
    def find_spec(self, name, path=None, target=None):
        if any(name == h or name.startswith(h + ".") for h in HIDDEN):
            with open(TRIED, "a") as log:  # an import caught and ignored shows here too
                log.write(name + "\\n")
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None


sys.meta_path.insert(0, _Hidden())
"""
HIDDEN = tuple(sorted({m for modules in EXTRA_MODULES.values() for m in modules}))


def without_extras(tmp_path: Path) -> dict[str, str]:
    """An environment whose interpreters cannot import any extra's module; the names they
    tried are in `site/tried.txt`."""
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    tried = site / "tried.txt"
    (site / "sitecustomize.py").write_text(BLOCKER.format(hidden=HIDDEN, tried=str(tried)))
    return dict(os.environ, PYTHONPATH=str(site))


def treetraits(env: dict[str, str], *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "treetraits", *args],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_the_blocker_hides_every_extra(tmp_path):
    probe = (
        "import importlib, sys\n"
        f"for m in {HIDDEN!r}:\n"
        "    try:\n"
        "        importlib.import_module(m)\n"
        "    except ImportError:\n"
        "        continue\n"
        "    sys.exit(f'{m} was imported')\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], env=without_extras(tmp_path), capture_output=True
    )
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize(
    ("args", "extra", "missing"),
    [
        (("batch", "survey.mcap", "--season", "season.sqlite"), "season", "dask"),
        (("report", "season.sqlite", "--out", "report.html"), "season", "matplotlib"),
        (("export", "foxglove", "survey.mcap", "--out", "f.mcap"), "export", "foxglove"),
        (("eval", "--out", "eval"), "eval", "matplotlib"),
    ],
)
def test_an_offline_command_without_its_extra_names_it(tmp_path, args, extra, missing):
    result = treetraits(without_extras(tmp_path), *args, cwd=tmp_path)
    assert result.returncode == EXIT_USAGE, result.stderr
    assert "Traceback" not in result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith(f"treetraits: error: treetraits {args[0]}"), line
    assert f"pip install 'treetraits[{extra}]'" in line and missing in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["site"]  # nothing written


def test_the_service_commands_work_without_the_extras(tmp_path):
    env = without_extras(tmp_path)
    helped = treetraits(env, "run", "--help", cwd=tmp_path)
    assert helped.returncode == 0 and "usage: treetraits run" in helped.stdout, helped.stderr
    config = tmp_path / "config.toml"
    config.write_text('[output]\ndir = "out"\n[camera]\nenabled = false\n')
    checked = treetraits(env, "config", "check", str(config), cwd=tmp_path)
    assert checked.returncode == 0, checked.stderr
    assert checked.stdout.startswith(f"{config}: ok")


def tried_imports(tmp_path: Path) -> list[str]:
    tried = tmp_path / "site" / "tried.txt"
    return tried.read_text().split() if tried.exists() else []


def test_the_service_starts_and_stops_without_the_extras(tmp_path):
    """The robot's install: `run` gets to READY=1 and stops cleanly on SIGTERM, and no
    extra's module was so much as tried."""
    config = tmp_path / "config.toml"
    config.write_text(
        f'[output]\ndir = "{tmp_path / "out"}"\n'
        f'[lidar]\nbind = "127.0.0.1"\ndata_port = {free_udp_port()}\n'
        f"telemetry_port = {free_udp_port()}\n"
        "[camera]\nenabled = false\n[gnss]\nenabled = false\n[wheels]\nenabled = false\n"
    )
    service = Service(tmp_path, config, env=without_extras(tmp_path))
    try:
        service.wait_ready()
        code, _ = service.terminate()
    finally:
        service.close()
    assert code == 0, service.stderr()
    assert tried_imports(tmp_path) == []
    assert (tmp_path / "out" / "runs" / "latest" / "traits.sqlite").exists()
