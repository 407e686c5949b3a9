"""WebSocket clients of `muster web` for `muster bench web`, on the `websockets`
package (a client nobody here wrote). Each client signs in as a user of its own,
opens the socket (which shows it the list and every change of it), requests one data
service and times every update from the system's send (`sent_ns`, CLOCK_MONOTONIC) to
its own receive (time.monotonic_ns(), the same clock on Linux), and the part of it
up to the web process's handling (`hub_ns`).

Prints JSON lines: {"event": "ready", ...} once every client holds its session,
then {"event": "done", ...} after the measuring window: latencies (µs), updates,
sequence gaps, resynchronisations (a client that fell behind is sent the whole state
again: updates skipped), errors.
"""

import argparse
import asyncio
import json
import os
import sys
import time
import urllib.request

from websockets.asyncio.client import connect


def sign_in(base: str, user: str, token: str) -> str:
    req = urllib.request.Request(
        base + "api/login", data=json.dumps({"user": user, "token": token}).encode(),
        headers={"Content-Type": "application/json", "Origin": base.rstrip("/")})
    with urllib.request.urlopen(req, timeout=30) as r:
        return r.headers["Set-Cookie"].split(";")[0]


class Stats:
    def __init__(self):
        self.latencies = []
        self.to_hub = []
        self.updates = 0
        self.gaps = 0
        self.resyncs = 0
        self.lists = 0
        self.errors = []
        self.measuring = False


async def client(base, cookie, service, stats: Stats, granted: asyncio.Event, stop: asyncio.Event):
    ws_url = base.replace("http", "ws", 1) + "ws"
    async with connect(ws_url, additional_headers={"Cookie": cookie}, origin=base.rstrip("/"),
                       max_size=None, ping_interval=None) as ws:
        last = None
        session = None
        async for raw in ws:
            now = time.monotonic_ns()
            f = json.loads(raw)
            t = f["t"]
            if t == "state":
                if session is None:
                    await ws.send(json.dumps({"op": "request", "service": service}))
                else:
                    stats.resyncs += 1
            elif t == "granted":
                session = f["session"]
                granted.set()
            elif t == "refused":
                stats.errors.append(f"{service}: refused: {f['reason']}")
                granted.set()
                return
            elif t == "update" and f["session"] == session:
                if stats.measuring:
                    stats.updates += 1
                    stats.latencies.append((now - f["sent_ns"]) // 1000)
                    stats.to_hub.append((f["hub_ns"] - f["sent_ns"]) // 1000)
                    if last is not None and f["seq"] != last + 1:
                        stats.gaps += max(0, f["seq"] - last - 1)
                    stats.gaps += f["gap"]
                last = f["seq"]
            elif t == "list":
                stats.lists += 1
            elif t in ("error", "closed", "ended"):
                stats.errors.append(f"{service}: {t}: {f}")
            if stop.is_set():
                return


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("url")
    ap.add_argument("tokens", help="JSON: [[user, token, service], ...]")
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--go", help="measure once this file exists (every process's clients are in)")
    args = ap.parse_args()
    users = json.load(open(args.tokens))
    cookies = [sign_in(args.url, u, t) for u, t, _ in users]
    stats = Stats()
    stop = asyncio.Event()
    events = [asyncio.Event() for _ in users]
    t0 = time.monotonic()
    tasks = [asyncio.create_task(client(args.url, c, s, stats, e, stop))
             for c, (_, _, s), e in zip(cookies, users, events)]
    waiting = asyncio.ensure_future(asyncio.gather(*(e.wait() for e in events)))
    await asyncio.wait([waiting, *tasks], return_when=asyncio.FIRST_COMPLETED, timeout=120)
    if not waiting.done():
        waiting.cancel()
    await asyncio.gather(waiting, return_exceptions=True)
    failed = [t for t in tasks if t.done() and not t.cancelled() and t.exception()]
    failed += [t for t, e in zip(tasks, events) if not e.is_set() and t not in failed]
    print(json.dumps({"event": "ready", "clients": len(users), "setup_s": time.monotonic() - t0,
                      "failed": [str(t.exception() if t.done() and not t.cancelled() else "no grant")
                                 for t in failed][:5], "failed_count": len(failed)}), flush=True)
    if args.go:
        deadline = time.monotonic() + 180
        while not os.path.exists(args.go) and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
    stats.measuring = True
    await asyncio.sleep(args.duration)
    stats.measuring = False
    stop.set()
    print(json.dumps({"event": "done", "latencies_us": stats.latencies, "to_hub_us": stats.to_hub, "updates": stats.updates,
                      "gaps": stats.gaps, "resyncs": stats.resyncs, "lists": stats.lists,
                      "errors": stats.errors[:10], "error_count": len(stats.errors)}), flush=True)
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


if __name__ == "__main__":
    asyncio.run(main())
