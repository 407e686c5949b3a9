"""The Python package's figures, each beside its floor in the same run.

1. Request -> grant from Python (`User.request`, then `end`) against the same loop in
   the Rust client (`_native.rust_request_latencies`, no Python in it): p50, p90, p99
   and the ratio of the p50s (the goal: within 1.3x).
2. A Python user taking a data session's updates at RATE Hz for SECONDS: updates/s
   taken, gaps, and the Python process's CPU per 1,000 updates/s.

Starts its own broker and synthetic systems on a unique instance (release binary
recommended: MUSTER_BIN=target/release/muster) and stops them by PID.

    python python/bench/bench.py [--requests 500] [--rate 10000] [--seconds 10]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import muster
from muster import _native

REPO = Path(__file__).resolve().parents[2]
BIN = os.environ.get("MUSTER_BIN", str(REPO / "target" / "release" / "muster"))


def pct(xs, p):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(p / 100 * (len(xs) - 1))))]


def wait_list(me, n, timeout=15):
    deadline = time.monotonic() + timeout
    while len(me.list()) < n:
        if time.monotonic() > deadline:
            sys.exit(f"bench: {n} services did not come up")
        time.sleep(0.05)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--requests", type=int, default=500)
    ap.add_argument("--rate", type=float, default=10000)
    ap.add_argument("--seconds", type=float, default=10)
    a = ap.parse_args()
    inst = f"pybench-{os.getpid()}"
    procs = []

    def start(*args):
        p = subprocess.Popen([BIN, *args, "--instance", inst], stdin=subprocess.DEVNULL,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(p)
        return p

    try:
        start("broker")
        time.sleep(0.3)
        start("system", "synthetic", "--name", "g1", "--quota", "1000")
        start("system", "synthetic", "--name", "fast", "--rate", str(a.rate))
        me = muster.User(inst)
        wait_list(me, 2)
        print(f"binary {BIN}")
        # 1. Request -> grant, alternating so both see the same machine.
        py, rs = [], []
        for _ in range(10):  # warm both paths
            me.request("g1/s0").end()
        _native.rust_request_latencies(inst, "g1/s0", 10)
        rounds = 5
        for _ in range(rounds):
            for _ in range(a.requests // rounds):
                t0 = time.perf_counter()
                s = me.request("g1/s0")
                py.append((time.perf_counter() - t0) * 1e6)
                s.end()
            rs.extend(_native.rust_request_latencies(inst, "g1/s0", a.requests // rounds))
        for name, xs in (("rust client", rs), ("python", py)):
            print(f"request->grant {name:12} n={len(xs)} p50 {pct(xs, 50):7.1f} us  "
                  f"p90 {pct(xs, 90):7.1f} us  p99 {pct(xs, 99):7.1f} us")
        print(f"request->grant python/rust p50 ratio {pct(py, 50) / pct(rs, 50):.2f}x "
              f"(goal <= 1.3x)")
        # 2. Updates at RATE Hz into Python.
        s = me.request("fast/s0")
        for _ in s.updates(timeout=2):  # the stream has started
            break
        n, first_seq = 0, None
        cpu0, t0 = time.process_time(), time.perf_counter()
        while time.perf_counter() - t0 < a.seconds:
            u = s.next(timeout=1)
            if u is None:
                continue
            first_seq = first_seq if first_seq is not None else u.seq
            n += 1
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        s.end()
        rate = n / wall
        print(f"updates into python: {n} in {wall:.1f} s = {rate:,.0f}/s (asked {a.rate:,.0f} Hz), "
              f"gaps {s.lost}, CPU {100 * cpu / wall:.1f}% of a core = "
              f"{100 * cpu / wall / (rate / 1000):.2f}% per 1,000 updates/s")
        me.close()
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(timeout=15)


if __name__ == "__main__":
    main()
