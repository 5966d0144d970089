"""Deployment files: the unit passes `systemd-analyze verify` and `security` (Debian's
systemd package), `make install` stages the right tree into DESTDIR idempotently and
never overwrites a config, the udev rules and the sysctl file parse, and under
MemoryDenyWriteExecute the libraries import while the compiled kernels refuse to start
with a message that says why.

`systemd-analyze verify` insists that ExecStart's binary exists, and /opt/treetraits is not
installed here: the test verifies a copy whose ExecStart names this checkout's venv entry
point (the same console script). udev is not installed here and `udevadm verify` needs
systemd >= 254 (Debian 12 has 252), so the rules are checked by a parser of the rule
syntax restricted to the keys we use.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.paths import REPO
from treetraits.service.config import load_config

SYSTEMD = REPO / "systemd"
ENTRY_POINT = Path(sys.executable).parent / "treetraits"
ANALYZE = (
    shutil.which("systemd-analyze")
    or "systemd-analyze (missing: `make test` installs Debian's systemd package)"
)


def _unit_copy(tmp_path: Path) -> Path:
    text = (SYSTEMD / "treetraits.service").read_text()
    assert "ExecStart=/opt/treetraits/venv/bin/treetraits run --config " in text
    assert ENTRY_POINT.exists()
    unit = tmp_path / "treetraits.service"
    unit.write_text(text.replace("/opt/treetraits/venv/bin/treetraits", str(ENTRY_POINT)))
    return unit


def test_systemd_analyze_verify(tmp_path):
    unit = _unit_copy(tmp_path)
    result = subprocess.run(
        [ANALYZE, "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    mine = [line for line in result.stderr.splitlines() if "treetraits" in line]
    assert result.returncode == 0 and not mine, result.stderr


def test_systemd_analyze_security_exposure(tmp_path):
    unit = _unit_copy(tmp_path)
    result = subprocess.run(
        [ANALYZE, "security", "--offline=true", "--no-pager", str(unit)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    match = re.search(r"Overall exposure level for treetraits\.service: ([\d.]+)", result.stdout)
    assert match, result.stdout + result.stderr
    # measured 1.6 (docs/deployment.md); systemd calls <= 4.0 'OK'
    assert float(match[1]) <= 2.0, result.stdout


def _unit_settings() -> dict[str, list[str]]:
    settings: dict[str, list[str]] = {}
    for line in (SYSTEMD / "treetraits.service").read_text().splitlines():
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            settings.setdefault(key, []).append(value)
    return settings


def test_unit_keeps_devices_reachable_and_the_contract():
    s = _unit_settings()
    assert s["Type"] == ["notify"] and s["Restart"] == ["on-failure"]
    assert s["User"] == ["treetraits"] and s["SupplementaryGroups"] == ["dialout video"]
    assert "PrivateDevices" not in s and s["DevicePolicy"] == ["closed"]
    assert {"char-ttyUSB rw", "char-ttyACM rw", "char-video4linux rw"} <= set(s["DeviceAllow"])
    assert s["StateDirectory"] == ["treetraits"] and s["ProtectSystem"] == ["strict"]
    assert "AF_UNIX" in s["RestrictAddressFamilies"][0]  # sd_notify
    assert s["ExecStart"] == [
        "/opt/treetraits/venv/bin/treetraits run --config /etc/treetraits/config.toml"
    ]


def _install(destdir: Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(SYSTEMD / "install.sh"), *args],
        env={**os.environ, "DESTDIR": str(destdir), **env},
        capture_output=True,
        text=True,
        timeout=120,
    )


def _tree(root: Path) -> dict[str, tuple[bytes, int, int]]:
    return {
        str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mode, p.stat().st_mtime_ns)
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_make_install_into_destdir_is_idempotent(tmp_path):
    root = tmp_path / "root"
    result = subprocess.run(
        ["make", "-s", "install", f"DESTDIR={root}", "INSTALL_FLAGS=--no-venv"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    first = _tree(root)
    assert sorted(first) == [
        "etc/sysctl.d/60-treetraits.conf",
        "etc/systemd/system/treetraits.service",
        "etc/treetraits/config.toml",
        "etc/udev/rules.d/99-treetraits.rules",
    ]
    for name, source in [
        ("etc/systemd/system/treetraits.service", "treetraits.service"),
        ("etc/udev/rules.d/99-treetraits.rules", "99-treetraits.rules"),
        ("etc/sysctl.d/60-treetraits.conf", "60-treetraits.conf"),
        ("etc/treetraits/config.toml", "config.toml"),
    ]:
        assert first[name][0] == (SYSTEMD / source).read_bytes(), name
        assert first[name][1] & 0o777 == 0o644
    load_config(root / "etc/treetraits/config.toml")  # the installed default loads
    assert "staged into" in result.stdout  # nothing done to the running system

    second = _install(root, "--no-venv")
    assert second.returncode == 0, second.stderr
    assert _tree(root) == first
    assert not re.search(r"^treetraits install: installed", second.stdout, re.MULTILINE)
    assert second.stdout.count("unchanged") == 3


def test_install_keeps_a_users_config_and_follows_prefix(tmp_path):
    root = tmp_path / "root"
    config = root / "etc/treetraits/config.toml"
    config.parent.mkdir(parents=True)
    config.write_text("[gnss]\nport = '/dev/ttyUSB3'\n")
    result = _install(root, "--no-venv", PREFIX="/srv/tt")
    assert result.returncode == 0, result.stderr
    assert config.read_text() == "[gnss]\nport = '/dev/ttyUSB3'\n"
    assert "kept existing" in result.stdout
    unit = (root / "etc/systemd/system/treetraits.service").read_text()
    assert "ExecStart=/srv/tt/venv/bin/treetraits run" in unit and "/opt/treetraits" not in unit

    removed = _install(root, "--uninstall", PREFIX="/srv/tt")
    assert removed.returncode == 0, removed.stderr
    assert sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()) == [
        "etc/treetraits/config.toml"
    ]


def test_install_refuses_unknown_options_and_needs_root_without_destdir(tmp_path):
    bad = _install(tmp_path, "--frobnicate")
    assert bad.returncode == 2 and "unknown option" in bad.stderr
    if os.geteuid() != 0:
        live = subprocess.run(
            [str(SYSTEMD / "install.sh"), "--no-venv"],
            env={k: v for k, v in os.environ.items() if k != "DESTDIR"},
            capture_output=True,
            text=True,
        )
        assert live.returncode == 1 and "run as root" in live.stderr


# --- udev rules: the syntax of udev(7), limited to the keys these rules use ----------

_MATCH_KEYS = {"SUBSYSTEM", "ACTION", "DRIVER", "KERNELS", "ATTRS", "ATTR", "ENV"}
_ASSIGN_KEYS = {"SYMLINK", "GROUP", "MODE", "ENV", "TAG", "ATTR"}
_PAIR = re.compile(r'\s*([A-Z_]+)(?:\{([A-Za-z0-9_/]+)\})?\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"\s*')


def _udev_rules(text: str) -> list[list[tuple[str, str | None, str, str]]]:
    rules = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        pairs, pos = [], 0
        while pos < len(line):
            match = _PAIR.match(line, pos)
            assert match, f"line {number}: cannot parse at {line[pos:]!r}"
            key, attr, op, value = match.groups()
            if op in ("==", "!="):
                assert key in _MATCH_KEYS, f"line {number}: {key} is not a match key"
            else:
                assert key in _ASSIGN_KEYS, f"line {number}: {key} cannot be assigned"
            assert (attr is not None) == (key in {"ATTRS", "ATTR", "ENV"}), f"line {number}"
            pairs.append((key, attr, op, value))
            pos = match.end()
            if pos < len(line):
                assert line[pos] == ",", f"line {number}: expected ',' at {line[pos:]!r}"
                pos += 1
        rules.append(pairs)
    return rules


def test_udev_rules_parse_and_name_the_devices():
    rules = _udev_rules((SYSTEMD / "99-treetraits.rules").read_text())
    by_link: dict[str, list[dict]] = {}
    for rule in rules:
        fields = {(k, a, op): v for k, a, op, v in rule}
        link = fields.get(("SYMLINK", None, "+="))
        if link:
            by_link.setdefault(link, []).append(fields)
    assert set(by_link) == {"jackal", "gnss", "survey3n"}
    (jackal,) = by_link["jackal"]
    assert jackal[("ATTRS", "idVendor", "==")] == "0483"
    assert jackal[("ATTRS", "idProduct", "==")] == "5740"
    for fields in by_link["jackal"] + by_link["gnss"]:
        assert fields[("SUBSYSTEM", None, "==")] == "tty"
        assert fields[("ENV", "ID_MM_DEVICE_IGNORE", "=")] == "1"
        assert fields[("GROUP", None, "=")] == "dialout"
    for fields in [f for group in by_link.values() for f in group]:
        assert fields[("TAG", None, "+=")] == "systemd"
        assert fields[("MODE", None, "=")] == "0660"
    assert all(f[("GROUP", None, "=")] == "video" for f in by_link["survey3n"])
    assert all(f[("ATTR", "index", "==")] == "0" for f in by_link["survey3n"])
    # the commented templates parse too once uncommented
    templates = [
        line.lstrip("#")
        for line in (SYSTEMD / "99-treetraits.rules").read_text().splitlines()
        if line.startswith("#SUBSYSTEM")
    ]
    assert len(_udev_rules("\n".join(templates))) == 2


def test_udev_parser_rejects_mistakes():
    for bad in [
        'SUBSYSTEM="tty", SYMLINK+="gnss"',  # assignment to a match-only key
        'SUBSYSTEM=="tty" SYMLINK+="gnss"',  # missing comma
        'ATTRS{idVendor}=="0483", SYMLINK+=gnss',  # unquoted value
    ]:
        with pytest.raises(AssertionError):
            _udev_rules(bad)


def test_sysctl_raises_rmem_max_enough_for_the_default_rcvbuf():
    values = {}
    for line in (SYSTEMD / "60-treetraits.conf").read_text().splitlines():
        if line.strip() and not line.startswith(("#", ";")):
            key, value = (part.strip() for part in line.split("=", 1))
            values[key] = int(value)
    assert set(values) == {"net.core.rmem_max"}  # rmem_default left alone
    assert values["net.core.rmem_max"] >= load_config(None).lidar.rcvbuf_bytes


# --- MemoryDenyWriteExecute -----------------------------------------------------------

_MDWE = """
import ctypes, mmap, sys
libc = ctypes.CDLL(None, use_errno=True)
if libc.prctl(65, 1, 0, 0, 0) != 0:  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN
    print("unsupported", ctypes.get_errno()); sys.exit(0)
try:
    mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)
    sys.exit("W+X mapping allowed: MDWE not in force")
except PermissionError:
    pass
import numpy as np, cv2, open3d as o3d
points = np.random.default_rng(0).random((500, 3))
cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
o3d.geometry.KDTreeFlann(cloud).search_knn_vector_3d(points[0], 5)
cloud.voxel_down_sample(0.1)
ok, jpeg = cv2.imencode(".jpg", np.zeros((32, 32, 3), np.uint8))
cv2.imdecode(jpeg, cv2.IMREAD_COLOR)
import systemd.daemon, treetraits.cli
from treetraits.errors import PlatformError
try:
    import treetraits.jit
except PlatformError as exc:
    print(exc)
"""


def test_under_memory_deny_write_execute_only_the_kernels_refuse_and_say_why():
    """The kernel's own MDWE (prctl PR_SET_MDWE, Linux >= 6.3) refuses W+X mappings and
    executable gains as the unit's MemoryDenyWriteExecute=yes would: numpy, OpenCV and
    open3d still work, the compiled kernels cannot, and say what to change. (The unit
    leaves the setting out for them.)"""
    result = subprocess.run(
        [sys.executable, "-c", _MDWE], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    if result.stdout.startswith("unsupported"):
        code = int(result.stdout.split()[1])
        assert code == errno.EINVAL, result.stdout
        pytest.skip("kernel older than 6.3: no PR_SET_MDWE to test MemoryDenyWriteExecute with")
    assert "cannot map executable memory" in result.stdout
    assert "MemoryDenyWriteExecute" in result.stdout


def test_unit_caches_the_compiled_kernels_in_its_cache_directory():
    unit = (SYSTEMD / "treetraits.service").read_text()
    assert "MemoryDenyWriteExecute=yes" not in unit
    assert re.search(r"^CacheDirectory=treetraits$", unit, re.M)
    assert re.search(r"^Environment=NUMBA_CACHE_DIR=%C/treetraits/", unit, re.M)
