"""Systems: offer data and command services, written as Python callbacks."""

from __future__ import annotations

import asyncio
import heapq
import itertools
import threading
import traceback
from typing import Any, Callable, Dict, List, Optional, Tuple

from . import _native
from ._errors import MusterError
from ._payloads import Value, from_wire, to_wire


class SystemSession:
    """A session a user holds on one of this system's services."""

    def __init__(self, system: "System", session: int, user: str, service: str):
        self._system = system
        self.id = session
        self.user = user
        self.service = service
        #: Why it ended, once it has.
        self.ended: Optional[str] = None

    def __repr__(self) -> str:
        return f"<muster.SystemSession {self.id} of {self.user} on {self.service}>"

    def status(self, state: str, detail: str = "") -> None:
        """Sends task status: `idle`, `working`, `done` or `rejected`, with a note.
        Raises PayloadError if it is too large for the user's path."""
        self._system._act(lambda core: core.status(self.id, state, detail))

    def working(self, detail: str = "") -> None:
        """`status("working", detail)`."""
        self.status("working", detail)

    def done(self, detail: str = "") -> None:
        """`status("done", detail)`."""
        self.status("done", detail)

    def rejected(self, detail: str = "") -> None:
        """`status("rejected", detail)`."""
        self.status("rejected", detail)

    def end(self, reason: str = "done") -> None:
        """Ends the session; its user is told `reason`."""
        self._system._act(lambda core: core.end(self.id, reason))


class Service:
    """A declared service: `publish` to its sessions (data), hear its sessions start
    and end (`on_start`, `on_end` decorators)."""

    def __init__(self, system: "System", name: str, kind: str, payload: str,
                 handler: Optional[Callable[..., Any]], rate: Optional[float],
                 latched: bool = False):
        self._system = system
        self.name = name
        self.kind = kind
        self.payload = payload
        #: Whether the broker keeps its newest value for each new session (data).
        self.latched = latched
        self._handler = handler
        self._rate = rate
        self._on_start: Optional[Callable[[SystemSession], Any]] = None
        self._on_end: Optional[Callable[[SystemSession, str], Any]] = None

    def __repr__(self) -> str:
        return f"<muster.Service {self._system.name}/{self.name} ({self.kind}, {self.payload})>"

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if self._handler is None:
            raise TypeError(f"service {self.name} has no function")
        return self._handler(*args, **kwargs)

    def on_start(self, fn: Callable[[SystemSession], Any]) -> Callable[[SystemSession], Any]:
        """Decorator: `fn(session)` when a session of this service starts."""
        self._on_start = fn
        return fn

    def on_end(self, fn: Callable[[SystemSession, str], Any]) -> Callable[[SystemSession, str], Any]:
        """Decorator: `fn(session, reason)` when a session of this service ends."""
        self._on_end = fn
        return fn

    def publish(self, value: Value) -> int:
        """Sends `value` to every session of this data service; returns how many users
        got it (from another thread: queued for the runtime, returns None)."""
        return self._system.publish(self.name, value)

    @property
    def sessions(self) -> List[SystemSession]:
        """Its open sessions."""
        return [s for s in self._system._sessions.values() if s.service == self.name]


class System:
    """A robot system. Declare services with the `data_service` and
    `command_service` decorators, then `run()` (or `await serve()`).

    Callbacks run one at a time on the runtime's thread; from another thread, use
    `call_soon(fn)` or `publish`, which hand the work over."""

    def __init__(self, name: str, instance: str = "default", *, udp: Optional[str] = None):
        self._native = _native.NativeSystem(name, instance, udp)
        self._services: Dict[str, Service] = {}
        self._sessions: Dict[int, SystemSession] = {}
        self._timers: List[Tuple[float, int, Callable[[], Any], Optional[float]]] = []
        self._seq = itertools.count()
        self._core: Optional[Any] = None
        self._now = 0.0
        self._thread: Optional[int] = None
        self._streaming = False
        #: Set while registered with a broker.
        self.registered = False
        #: Updates published but lost on the way to a user whose inbox was full (or
        #: who was gone); the user sees the gap.
        self.undelivered = 0

    @property
    def name(self) -> str:
        return self._native.name

    def __repr__(self) -> str:
        return f"<muster.System {self.name} ({len(self._services)} services)>"

    # Declaring.
    def _declare(self, name: str, kind: str, payload: str, quota: int, queue: bool,
                 description: str, schema: Optional[str], encoding: Optional[str],
                 handler: Optional[Callable[..., Any]], rate: Optional[float],
                 latched: bool = False) -> Service:
        if rate is not None and not rate > 0:
            raise MusterError("rate is updates a second, > 0")
        self._native.add_service(name, kind, payload, quota, queue, description,
                                 encoding, schema, latched)
        s = Service(self, name, kind, payload, handler, rate, latched)
        self._services[name] = s
        return s

    def data_service(self, name: str, *, payload: str = "pose2d", quota: int = 10,
                     queue: bool = False, description: str = "", rate: Optional[float] = None,
                     schema: Optional[str] = None, encoding: Optional[str] = None,
                     latched: bool = False) -> Callable[[Callable[[], Any]], Service]:
        """Decorator: a data service. With `rate` (Hz), the function is called that
        often while the service has sessions and what it returns is published (None
        publishes nothing); without, publish with `service.publish(value)`.

        `latched=True` (ROS 2's transient-local durability): every update published
        also goes to the broker, which keeps the newest and gives it to each new
        session with its grant, as its update 0, so a user has the value at once. With
        `rate`, a latched service's function is called at that rate with no session
        too, so the broker's value stays fresh."""
        def wrap(fn: Callable[[], Any]) -> Service:
            return self._declare(name, "data", payload, quota, queue, description, schema,
                                 encoding, fn, rate, latched)
        return wrap

    def command_service(self, name: str, *, payload: str = "goal2d", quota: int = 1,
                        queue: bool = False, description: str = "",
                        schema: Optional[str] = None, encoding: Optional[str] = None
                        ) -> Callable[[Callable[[SystemSession, Value], Any]], Service]:
        """Decorator: a command service; the function is called `fn(session, value)`
        for each task input. A callback that raises ends that session only (its
        traceback is printed), never the system."""
        def wrap(fn: Callable[[SystemSession, Value], Any]) -> Service:
            return self._declare(name, "command", payload, quota, queue, description, schema,
                                 encoding, fn, None)
        return wrap

    # Acting.
    def _act(self, f: Callable[[Any], Any]) -> Any:
        """Runs `f(core)` now if on the runtime's thread in a callback, else hands it
        to the runtime (and returns None)."""
        if self._core is not None and threading.get_ident() == self._thread:
            return f(self._core)
        if not self._native.running:
            raise MusterError("the system is not running")
        self._native.call_soon(f)
        return None

    def publish(self, service: str, value: Value) -> Any:
        """Sends `value` to every session of data service `service`; returns how many
        users got it (None when handed over from another thread). Raises PayloadError
        for a value not of the service's type, or too large for a user's path."""
        wire = to_wire(value)
        return self._act(lambda core: core.publish(service, wire))

    def withdraw(self, service: str) -> None:
        """Withdraws `service` for now: its sessions end, requests are refused."""
        self._act(lambda core: core.withdraw(service))

    def restore(self, service: str) -> None:
        """Offers a withdrawn service again."""
        self._act(lambda core: core.restore(service))

    def call_soon(self, fn: Callable[[], Any]) -> None:
        """Runs `fn()` on the runtime's thread soon (safe from any thread)."""
        self._native.call_soon(lambda core: fn())

    def after(self, delay: float, fn: Callable[[], Any]) -> None:
        """Runs `fn()` once, `delay` seconds from now, on the runtime's thread."""
        self._timer(delay, fn, None)

    def every(self, period: float, fn: Callable[[], Any]) -> None:
        """Runs `fn()` every `period` seconds on the runtime's thread."""
        if not period > 0:
            raise MusterError("period is seconds, > 0")
        self._timer(period, fn, period)

    def _timer(self, delay: float, fn: Callable[[], Any], period: Optional[float]) -> None:
        def add() -> None:
            heapq.heappush(self._timers, (self._now + max(0.0, delay), next(self._seq), fn, period))
        if self._native.running and threading.get_ident() != self._thread:
            self._native.call_soon(lambda core: add())
        else:
            add()

    @property
    def sessions(self) -> List[SystemSession]:
        """The open sessions, of every service."""
        return list(self._sessions.values())

    # Running.
    def run(self) -> Dict[str, Any]:
        """Registers and serves until Ctrl-C, SIGTERM or `stop()`; returns each
        service's report (grants, refusals, most sessions at once)."""
        self._now = 0.0  # the runtime's clock starts at 0 with each run
        if not self._streaming:
            self._streaming = True
            for s in self._services.values():
                if s._rate is not None:
                    self.every(1.0 / s._rate, self._streamer(s))
        self._thread = threading.get_ident()
        try:
            return self._native.run(_Handler(self))
        finally:
            self._thread = None
            self._sessions.clear()
            self.registered = False

    async def serve(self) -> Dict[str, Any]:
        """`run` for asyncio: serves on a thread of its own until `stop()` (or the
        task is cancelled)."""
        loop = asyncio.get_running_loop()
        fut = loop.run_in_executor(None, self.run)
        try:
            return await asyncio.shield(fut)
        except asyncio.CancelledError:
            self.stop()
            await fut
            raise

    def stop(self) -> None:
        """Stops a running system (from any thread or a callback)."""
        self._native.stop()

    def _streamer(self, s: Service) -> Callable[[], None]:
        def tick() -> None:
            if s._handler is None or not (s.latched or s.sessions):
                return
            value = s._handler()
            if value is not None:
                self.publish(s.name, value)
        return tick


class _Handler:
    """What the native runtime calls: events, ticks, handed-over work."""

    def __init__(self, system: System):
        self.s = system

    def _enter(self, core: Any, now: float) -> None:
        self.s._core, self.s._now = core, now

    def _leave(self) -> None:
        self.s._core = None

    def on_event(self, core: Any, now: float, ev: dict) -> None:
        self._enter(core, now)
        try:
            self._event(ev)
        finally:
            self._leave()

    def _event(self, ev: dict) -> None:
        s = self.s
        e = ev["event"]
        if e == "registered":
            s.registered = True
        elif e in ("broker_lost", "delinquent"):
            s.registered = False
        elif e == "undelivered":
            s.undelivered += 1
        elif e == "session_started":
            sess = SystemSession(s, ev["session"], ev["user"], ev["service"])
            s._sessions[sess.id] = sess
            svc = s._services.get(sess.service)
            if svc is not None and svc._on_start is not None:
                svc._on_start(sess)
        elif e == "input":
            sess = s._sessions.get(ev["session"])
            svc = s._services.get(ev["service"])
            if sess is not None and svc is not None and svc._handler is not None:
                svc._handler(sess, from_wire(ev["value"]))
        elif e == "session_ended":
            sess = s._sessions.pop(ev["session"], None)
            if sess is not None:
                sess.ended = ev["reason"]
                svc = s._services.get(sess.service)
                if svc is not None and svc._on_end is not None:
                    try:
                        svc._on_end(sess, ev["reason"])
                    except Exception:
                        traceback.print_exc()

    def on_tick(self, core: Any, now: float) -> None:
        self._enter(core, now)
        try:
            timers = self.s._timers
            while timers and timers[0][0] <= now:
                due, seq, fn, period = heapq.heappop(timers)
                if period is not None:
                    # The next one on the grid, not after a late one: no drift.
                    nxt = due + period
                    if nxt <= now:
                        nxt = now + period
                    heapq.heappush(timers, (nxt, seq, fn, period))
                try:
                    fn()
                except Exception:
                    traceback.print_exc()
        finally:
            self._leave()

    def next_tick(self) -> Optional[float]:
        return self.s._timers[0][0] if self.s._timers else None

    def on_call(self, core: Any, now: float, fn: Callable[[Any], Any]) -> None:
        self._enter(core, now)
        try:
            fn(core)
        except Exception:
            traceback.print_exc()
        finally:
            self._leave()
