"""`treetraits run` as a subprocess, the way systemd runs it: a bound AF_UNIX datagram
socket stands in for systemd's NOTIFY_SOCKET and keeps what the service sent to it."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from tests.helpers.paths import REPO

START_S = 90  # imports (open3d, OpenCV) on a loaded 2-core machine


class Service:
    """The service subprocess and what it sent to its NOTIFY_SOCKET."""

    def __init__(
        self,
        folder: Path,
        config: Path,
        *args: str,
        preexec_fn=None,
        env: dict[str, str] | None = None,
    ):
        self.socket_path = folder / f"notify-{time.monotonic_ns()}.sock"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(self.socket_path))
        self.sock.settimeout(0.2)
        self.messages: list[str] = []
        self._lock = threading.Lock()
        self._done = threading.Event()
        env = dict(env or os.environ, NOTIFY_SOCKET=str(self.socket_path), WATCHDOG_USEC="2000000")
        env.pop("INVOCATION_ID", None)
        env.pop("JOURNAL_STREAM", None)
        self.stderr_path = folder / f"stderr-{time.monotonic_ns()}.log"
        self._stderr = open(self.stderr_path, "wb")  # noqa: SIM115 - closed in close()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "treetraits", "run", "--config", str(config), *args],
            cwd=REPO,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=self._stderr,
            preexec_fn=preexec_fn,
        )
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        while not self._done.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            with self._lock:
                self.messages.append(data.decode())

    def sent(self) -> list[str]:
        with self._lock:
            return list(self.messages)

    def statuses(self) -> list[str]:
        return [
            line[len("STATUS=") :]
            for m in self.sent()
            for line in m.splitlines()
            if line.startswith("STATUS=")
        ]

    def wait_for(self, predicate, timeout: float, what: str) -> str:
        """The first STATUS line matching `predicate`, waiting up to `timeout` s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for status in self.statuses():
                if predicate(status):
                    return status
            if self.proc.poll() is not None:
                break
            time.sleep(0.1)
        raise AssertionError(f"no STATUS {what}; got {self.statuses()[-3:]}; {self.stderr()}")

    def wait_ready(self) -> None:
        deadline = time.monotonic() + START_S
        while not any("READY=1" in m for m in self.sent()):
            assert self.proc.poll() is None, self.stderr()
            assert time.monotonic() < deadline, "no READY=1"
            time.sleep(0.05)

    def stderr(self) -> str:
        return self.stderr_path.read_text(errors="replace")[-3000:]

    def terminate(self) -> tuple[int, float]:
        start = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(timeout=30)
        return code, time.monotonic() - start

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._done.set()
        self._thread.join(2.0)
        self.sock.close()
        self._stderr.close()
