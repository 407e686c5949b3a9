"""Fixtures: the muster binary, a unique instance per test, brokers and systems
started as processes (killed by PID at the end), keys for remote users."""

from __future__ import annotations

import itertools
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator, List

import pytest

REPO = Path(__file__).resolve().parents[2]
BIN = os.environ.get("MUSTER_BIN", str(REPO / "target" / "debug" / "muster"))
EXAMPLES = REPO / "python" / "examples"
_counter = itertools.count()


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(pred, timeout: float = 15.0, what: str = "the condition"):
    deadline = time.monotonic() + timeout
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} did not happen within {timeout} s")
        time.sleep(0.05)


class Fed:
    """One test's instance: its processes, started here and ended by PID."""

    def __init__(self, name: str):
        self.inst = f"py{os.getpid() % 100000}-{name[:10]}-{next(_counter)}"
        self.procs: List[subprocess.Popen] = []
        self.dir = Path(tempfile.mkdtemp(prefix=f"muster-py-{self.inst}-"))

    def spawn(self, args: List[str], stdin=subprocess.DEVNULL, **kw) -> subprocess.Popen:
        p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             stdin=stdin, text=True, **kw)
        self.procs.append(p)
        return p

    def muster(self, *args: str, stdin=subprocess.DEVNULL) -> subprocess.Popen:
        return self.spawn([BIN, *args, "--instance", self.inst], stdin=stdin)

    def run(self, *args: str, timeout: float = 30.0) -> subprocess.CompletedProcess:
        return subprocess.run([BIN, *args, "--instance", self.inst], capture_output=True,
                              text=True, timeout=timeout, stdin=subprocess.DEVNULL)

    def broker(self, *extra: str) -> subprocess.Popen:
        p = self.muster("broker", *extra)
        wait_until(lambda: self.run("user", "list", "--json").returncode == 0,
                   what="the broker")
        return p

    def python(self, script: str, *args: str) -> subprocess.Popen:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        return self.spawn([sys.executable, script, *args], env=env)

    def keys(self, *users: str) -> Path:
        """Keys for `users` (allowed everything) and the broker's access file."""
        lines = []
        for u in users:
            r = subprocess.run([BIN, "keygen", "--user", u, "--out", str(self.dir),
                                "--allow", "*"], capture_output=True, text=True, timeout=30)
            assert r.returncode == 0, r.stderr
            lines.append(r.stdout)
        access = self.dir / "access"
        access.write_text("".join(lines))
        return access

    def stop(self, p: subprocess.Popen, sig: int = signal.SIGTERM) -> str:
        if p.poll() is None:
            p.send_signal(sig)
        try:
            _, err = p.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()
            _, err = p.communicate()
        return err

    def close(self) -> None:
        # Systems and users first, the broker last (it cleans the instance up).
        for p in reversed(self.procs):
            self.stop(p)
        for f in self.dir.iterdir():
            f.unlink()
        self.dir.rmdir()


@pytest.fixture
def fed(request) -> Iterator[Fed]:
    f = Fed(request.node.name.replace("test_", ""))
    try:
        yield f
    finally:
        f.close()


def services(user, n: int, timeout: float = 15.0):
    """Waits until `user` lists `n` services; returns them."""
    return wait_until(lambda: (lambda l: l if len(l) == n else None)(user.list()),
                      timeout, f"{n} services in the list")


__all__ = ["Fed", "BIN", "EXAMPLES", "free_udp_port", "wait_until", "services"]
