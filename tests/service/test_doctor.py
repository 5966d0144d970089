"""`treetraits doctor`: serial ports are real pseudo-terminals, the UDP check binds a real
loopback port, holders are real child processes, permissions and groups are checked as a
real unprivileged user (a child dropped to `nobody` when the tests run as root). Only USB
and video devices, which CI lacks, come from a fake sysfs tree."""

from __future__ import annotations

import argparse
import grp
import json
import os
import pwd
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.helpers.net import free_udp_port
from tests.helpers.paths import REPO
from tests.helpers.sysfs import make_sysfs
from treetraits.cli.doctor import register
from treetraits.service.config import load_config
from treetraits.service.doctor import (
    Roots,
    Status,
    check_camera,
    check_disk,
    check_groups,
    check_modemmanager,
    check_rmem,
    check_serial_port,
    check_udp,
    check_usb,
)

NOBODY = 65534


@pytest.fixture
def pty_port():
    master, slave = os.openpty()
    path = os.ttyname(slave)
    yield path
    os.close(master)
    os.close(slave)


def _holder(code: str) -> subprocess.Popen:
    """A child that runs `code`, prints 'ready' and waits to be killed."""
    child = subprocess.Popen(
        [sys.executable, "-c", code + "\nprint('ready', flush=True)\nimport time; time.sleep(60)"],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert child.stdout.readline().strip() == "ready"
    return child


def test_serial_port_pty_ok_and_held_by_another_process(pty_port):
    checks = check_serial_port("gnss", pty_port)
    assert [(c.name, c.status) for c in checks] == [("gnss port", Status.OK)]
    child = _holder(f"f = open({pty_port!r}, 'rb', buffering=0)")
    try:
        checks = check_serial_port("gnss", pty_port)
    finally:
        child.kill()
        child.wait()
    held = checks[1]
    assert held.status is Status.WARN and f"pid {child.pid}" in held.detail
    assert "ModemManager" in held.fix


def test_serial_port_missing_and_not_a_device(tmp_path):
    (missing,) = check_serial_port("wheels", str(tmp_path / "jackal"))
    assert missing.status is Status.FAIL and "does not exist" in missing.detail
    assert "udev" in missing.fix
    plain = tmp_path / "plain"
    plain.write_text("")
    (check,) = check_serial_port("gnss", str(plain))
    assert check.status is Status.FAIL and "not a character device" in check.detail


_AS_NOBODY = """
import json, os, sys
from treetraits.service.doctor import check_serial_port, check_groups  # before /root is closed
os.setgroups([]); os.setgid(65534); os.setuid(65534)
print(json.dumps([c.as_dict() for c in check_serial_port("gnss", sys.argv[1])]
                 + [check_groups().as_dict()]))
"""


def test_permission_and_groups_as_an_unprivileged_user(pty_port):
    os.chmod(pty_port, 0o600)
    if os.geteuid() == 0:
        out = subprocess.run(
            [sys.executable, "-c", _AS_NOBODY, pty_port],
            capture_output=True,
            text=True,
            check=True,
            cwd=REPO,
        ).stdout
        port, groups = json.loads(out)
        user = pwd.getpwuid(NOBODY).pw_name
    else:
        port, groups = (c.as_dict() for c in [*check_serial_port("gnss", pty_port), check_groups()])
        user = pwd.getpwuid(os.geteuid()).pw_name
    assert port["status"] == "fail" and "no read/write permission" in port["detail"]
    assert f"usermod -aG dialout {user}" in port["fix"]
    in_dialout = user in grp.getgrnam("dialout").gr_mem
    if not in_dialout:
        assert groups["status"] == "fail" and "dialout" in groups["fix"]


def test_groups_of_a_named_user():
    me = pwd.getpwuid(os.getuid())
    own_group = grp.getgrgid(me.pw_gid).gr_name
    assert check_groups(me.pw_name, required=[own_group]).status is Status.OK
    nobody = pwd.getpwuid(NOBODY).pw_name
    check = check_groups(nobody, required=["dialout", "video"])
    assert check.status is Status.FAIL
    assert check.fix == f"sudo usermod -aG dialout,video {nobody}"
    assert check_groups("no-such-user-xyz").status is Status.FAIL


def test_udp_receives_on_loopback():
    port = free_udp_port()

    def send():
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _ in range(5):
                time.sleep(0.05)
                s.sendto(b"\0" * 1206, ("127.0.0.1", port))

    sender = threading.Thread(target=send)
    sender.start()
    check = check_udp("127.0.0.1", port, 3.0)
    sender.join()
    assert check.status is Status.OK, check
    assert "from 127.0.0.1" in check.detail and "1206" in check.detail


def test_udp_silent_and_busy():
    port = free_udp_port()
    start = time.monotonic()
    silent = check_udp("127.0.0.1", port, 0.3)
    assert silent.status is Status.FAIL and "nothing received" in silent.detail
    assert time.monotonic() - start < 3
    child = _holder(
        f"import socket; s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); "
        f"s.bind(('127.0.0.1', {port}))"
    )
    try:
        busy = check_udp("127.0.0.1", port, 0.3)
    finally:
        child.kill()
        child.wait()
    assert busy.status is Status.FAIL
    assert f"pid {child.pid}" in busy.detail


def _proc_with(tmp_path: Path, rmem_max: int | None = None, comms=()) -> Path:
    proc = tmp_path / "proc"
    if rmem_max is not None:
        core = proc / "sys" / "net" / "core"
        core.mkdir(parents=True)
        (core / "rmem_max").write_text(f"{rmem_max}\n")
    for pid, comm in comms:
        (proc / str(pid)).mkdir(parents=True)
        (proc / str(pid) / "comm").write_text(comm + "\n")
    return proc


def test_rmem(tmp_path):
    low = check_rmem(8388608, _proc_with(tmp_path / "a", 212992))
    assert low.status is Status.WARN and "212992 < lidar.rcvbuf_bytes 8388608" in low.detail
    assert "60-treetraits.conf" in low.fix and "sysctl --system" in low.fix
    assert check_rmem(8388608, _proc_with(tmp_path / "b", 16777216)).status is Status.OK


def test_modemmanager(tmp_path):
    proc = _proc_with(tmp_path, comms=[(812, "ModemManager"), (1, "init")])
    rules = tmp_path / "99-treetraits.rules"
    check = check_modemmanager(proc, rules)
    assert check.status is Status.WARN and "pid 812" in check.detail
    rules.write_text("")
    assert check_modemmanager(proc, rules).status is Status.OK
    assert (
        check_modemmanager(_proc_with(tmp_path / "none", comms=[(1, "init")]), rules).status
        is Status.OK
    )


def _usb_tree(root: Path, devices) -> Path:
    sysfs = root / "sys"
    for port, vid, pid, product in devices:
        d = sysfs / "bus" / "usb" / "devices" / port
        d.mkdir(parents=True)
        (d / "idVendor").write_text(vid + "\n")
        (d / "idProduct").write_text(pid + "\n")
        (d / "product").write_text(product + "\n")
    return sysfs


def test_usb_ids(tmp_path):
    config = load_config(None)
    sysfs = _usb_tree(
        tmp_path / "all",
        [
            ("1-1", "0483", "5740", "STM32 Virtual ComPort"),
            ("1-2", "1546", "01a9", "u-blox GNSS receiver"),
            ("1-3", "1a2b", "3c4d", "MAPIR Survey3N"),
            ("1-4", "046d", "c52b", "USB Receiver"),
        ],
    )
    check = check_usb(config, sysfs)
    assert check.status is Status.OK
    assert "Jackal MCU (STM32 virtual COM port) 0483:5740 at 1-1" in check.detail
    assert "u-blox F9/M9 GNSS 1546:01a9 at 1-2" in check.detail
    assert "MAPIR Survey3N 1a2b:3c4d at 1-3" in check.detail
    assert "046d" not in check.detail
    none = check_usb(config, _usb_tree(tmp_path / "none", [("1-4", "046d", "c52b", "Mouse")]))
    assert none.status is Status.WARN
    assert "Jackal MCU (0483:5740)" in none.detail and "GNSS" in none.detail


def test_camera_found_in_fake_sysfs(tmp_path):
    sysfs, dev = make_sysfs(
        tmp_path,
        [
            (0, "Integrated Camera", "04f2", "b6dd", "1-5"),
            (2, "MAPIR Survey3N", "1a2b", "3c4d", "3-1"),
        ],
    )
    roots = Roots(sys=sysfs, proc=Path("/proc"), dev=dev)
    config = load_config(None)
    listing, camera = check_camera(config, roots)
    assert listing.status is Status.OK and "'MAPIR Survey3N'" in listing.detail
    # auto resolves to the capture node; the node is not in the fake /dev
    assert camera.status is Status.FAIL and str(dev / "video2") in camera.detail
    (dev / "video2").write_text("")
    _, camera = check_camera(config, roots)
    assert camera.status is Status.OK


def test_disk(tmp_path):
    ok = check_disk(str(tmp_path / "not" / "yet"))
    assert "not created yet" in ok.detail and "GiB free" in ok.detail
    assert check_disk(str(tmp_path), min_free_bytes=1 << 62).status in (Status.WARN, Status.FAIL)


def _run_cli(argv):
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["doctor", *argv])
    return args.run(args)


def test_cli_json_and_exit_codes(tmp_path, pty_port, capsys):
    port = free_udp_port()
    config = tmp_path / "config.toml"
    config.write_text(
        f'[output]\ndir = "{tmp_path}"\n'
        f'[lidar]\nbind = "127.0.0.1"\ndata_port = {port}\ntelemetry_port = 0\n'
        "rcvbuf_bytes = 65536\n"
        "[camera]\nenabled = false\n"
        f'[gnss]\nport = "{pty_port}"\n'
        f'[wheels]\nport = "{tmp_path / "jackal"}"\n'
    )
    code = _run_cli(["--config", str(config), "--json", "--udp-seconds", "0.2"])
    checks = {c["name"]: c for c in json.loads(capsys.readouterr().out)}
    assert code == 1
    assert checks["config"]["status"] == "ok"
    assert checks["gnss port"]["status"] == "ok"
    assert checks["wheels port"]["status"] == "fail"
    assert checks[f"UDP {port}"]["status"] == "fail"
    assert checks["camera"]["detail"] == "disabled in the config"

    config.write_text(
        f'[output]\ndir = "{tmp_path}"\n[lidar]\nenabled = false\n[camera]\nenabled = false\n'
        f'[gnss]\nport = "{pty_port}"\n[wheels]\nenabled = false\n'
    )
    code = _run_cli(["--config", str(config)])
    out = capsys.readouterr().out
    assert ("FAIL" in out) == (code == 1)
    assert "gnss port" in out and "checks:" in out

    config.write_text("[lidar]\nport = 2368\n")
    code = _run_cli(["--config", str(config), "--json", "--udp-seconds", "0.1"])
    checks = {c["name"]: c for c in json.loads(capsys.readouterr().out)}
    assert code == 1 and checks["config"]["status"] == "fail"
    assert "lidar.port" in checks["config"]["detail"]
