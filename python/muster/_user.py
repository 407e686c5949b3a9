"""Users: list services, ask for them, work with sessions, link them."""

from __future__ import annotations

import asyncio
import collections
import time
from dataclasses import dataclass
from typing import Any, Callable, Deque, Dict, Iterator, List, Optional, Tuple, Union, cast

from . import _native
from ._errors import MusterError, Refused, SessionEnded
from ._payloads import Value, from_wire, to_wire

#: How many events of sessions not made yet (their grant still being taken) a user keeps.
_EARLY_EVENTS = 1024


@dataclass(frozen=True)
class Service:
    """One entry of the service list."""

    id: str
    system: str
    name: str
    description: str
    kind: str
    payload: str
    encoding: str
    quota: int
    in_use: int
    queued: int
    queue: bool
    links: int
    withdrawn: bool
    host: str
    remote: bool

    @classmethod
    def _of(cls, d: dict) -> "Service":
        return cls(**{k: d[k] for k in cls.__dataclass_fields__})


@dataclass(frozen=True)
class Update:
    """A data session's update (`value` is a payload object)."""

    seq: int
    gap: int
    value: Value
    sent_ns: int


@dataclass(frozen=True)
class Status:
    """A command session's status: `state` is idle, working, done or rejected."""

    seq: int
    state: str
    detail: Optional[str]
    text: str


class Session:
    """A granted session. Iterate it for its updates (and a command session's
    statuses) until it ends; `send` task input on a command session; `end` it, or use
    it as a context manager."""

    def __init__(self, user: "User", ev: dict, queued: List[int]):
        self._user = user
        self.id: int = ev["session"]
        self.service: str = ev["service"]
        self.kind: str = ev["kind"]
        self.payload: str = ev["payload"]
        self.encoding: Optional[str] = ev["encoding"]
        self.schema: Optional[str] = ev["schema"]
        #: The queue positions the request went through before its grant.
        self.queue_positions: List[int] = queued
        #: The last status (command sessions), or None.
        self.status: Optional[Status] = None
        #: Why it ended (the broker's or system's words), once it has.
        self.ended: Optional[str] = None
        #: The end's code: by_user, by_system, withdrawn, peer_gone, duration_over.
        self.end_code: Optional[str] = None
        self.last_seq = 0
        #: Updates lost on the way (gaps in sequence numbers, and at the end).
        self.lost = 0
        self._items: Deque[Union[Update, Status]] = collections.deque()

    def __repr__(self) -> str:
        state = f"ended: {self.ended}" if self.ended else "open"
        return f"<muster.Session {self.id} on {self.service} ({self.kind}, {state})>"

    # Events, from the user's pump.
    def _take(self, ev: dict) -> None:
        e = ev["event"]
        if e == "update":
            self.last_seq = max(self.last_seq, ev["seq"])
            self.lost += ev["gap"]
            self._items.append(Update(ev["seq"], ev["gap"], from_wire(ev["value"]),
                                      ev["sent_ns"]))
        elif e == "status":
            self.last_seq = max(self.last_seq, ev["seq"])
            self.status = Status(ev["seq"], ev["state"], ev["detail"], ev["text"])
            self._items.append(self.status)
        elif e == "ended":
            self.lost += ev["lost_at_end"]
            self.ended, self.end_code = ev["reason"], ev["code"]
        elif e == "end_confirmed":
            self.ended, self.end_code = "ended by the user", "by_user"

    def _ended(self) -> SessionEnded:
        return SessionEnded(self.service, self.end_code or "", self.ended or "")

    def _ready(self) -> Optional[Union[Update, Status]]:
        """What came and was not taken yet; raises SessionEnded once it ended and
        everything it sent was taken."""
        if self._items:
            return self._items.popleft()
        if self.ended is not None:
            raise self._ended()
        return None

    def next(self, timeout: Optional[float] = None) -> Optional[Union[Update, Status]]:
        """The next update or status, waiting up to `timeout` seconds (None: until one
        comes). None if the timeout passed; raises SessionEnded once the session ended
        and everything it sent was taken."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            item = self._ready()
            if item is not None:
                return item
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not self._user._pump(left) and deadline is not None \
                    and time.monotonic() >= deadline:
                return None

    def __iter__(self) -> Iterator[Union[Update, Status]]:
        while True:
            try:
                item = self.next()
            except SessionEnded:
                return
            if item is not None:
                yield item

    def updates(self, timeout: Optional[float] = None) -> Iterator[Update]:
        """The updates alone, until the session ends (or `timeout` passes with none)."""
        while True:
            try:
                item = self.next(timeout)
            except SessionEnded:
                return
            if item is None:
                return
            if isinstance(item, Update):
                yield item

    def send(self, value: Value) -> None:
        """Sends task input (a command session). Raises PayloadError for a value the
        service does not take or one too large for the path."""
        if self.ended is not None:
            raise self._ended()
        if self.kind != "command":
            raise MusterError(f"{self.service} is a data service: it takes no input")
        self._user._native.input(self.id, to_wire(value))

    def wait_status(self, *states: str, timeout: Optional[float] = None) -> Status:
        """Waits for a status in `states` (any status if none given); raises
        TimeoutError, or SessionEnded if the session ends first."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise TimeoutError(f"no status {states or ''} on {self.service} in {timeout} s")
            item = self.next(left)
            if isinstance(item, Status) and (not states or item.state in states):
                return item

    def end(self) -> None:
        """Ends the session (idempotent)."""
        if self.ended is None:
            self._user._native.end(self.id)
            self.ended, self.end_code = "ended by the user", "by_user"

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.end()

    # asyncio
    def __aiter__(self) -> "Session":
        return self

    async def __anext__(self) -> Union[Update, Status]:
        try:
            # Without a timeout, anext returns an item or raises.
            return cast(Union[Update, Status], await self.anext())
        except SessionEnded:
            raise StopAsyncIteration from None

    async def anext(self, timeout: Optional[float] = None) -> Optional[Union[Update, Status]]:
        """`next` for asyncio."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            item = self._ready()
            if item is not None:
                return item
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None
            await self._user._apump(left)


class Link:
    """A link: a data service's updates forwarded as a command service's input."""

    def __init__(self, user: "User", number: int, data: str, command: str):
        self._user = user
        self.number = number
        self.data = data
        self.command = command
        self.up = False
        self.forwarded = 0
        #: Why it ended, once it has.
        self.ended: Optional[str] = None

    def __repr__(self) -> str:
        state = f"ended: {self.ended}" if self.ended else ("up" if self.up else "starting")
        return f"<muster.Link {self.number} {self.data} -> {self.command} ({state})>"

    def end(self) -> None:
        """Ends the link and its two sessions."""
        if self.ended is None:
            self._user._native.unlink(self.number)
            self.ended = "ended by the user"

    def __enter__(self) -> "Link":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.end()


class _Pending:
    """A request waiting for its answer (the part `request` and `arequest` share)."""

    def __init__(self, user: "User", service: str, timeout: Optional[float],
                 on_queued: Optional[Callable[[int], None]]):
        self.user, self.service, self.timeout, self.on_queued = user, service, timeout, on_queued
        self.req = user._native.request(service)
        self.deadline = None if timeout is None else time.monotonic() + timeout
        self.queued: List[int] = []

    def step(self) -> "tuple[Optional[Session], Optional[float]]":
        """The session if granted (raises Refused or TimeoutError), else how long to
        wait for more."""
        for ev in self.user._answers.pop(self.req, []):
            s = self.user._answer(ev, self.queued, self.on_queued)
            if s is not None:
                return s, None
        left = None if self.deadline is None else self.deadline - time.monotonic()
        if left is not None and left <= 0:
            self.user._native.cancel(self.req)
            where = f" (queued at {self.queued[-1]})" if self.queued else ""
            raise TimeoutError(f"{self.service} was not granted within {self.timeout} s{where}")
        return None, left


class User:
    """A user: `User(instance="default")` on this host, or
    `User(remote="HOST:PORT", key="alice.key")` over UDP (a key from `muster keygen`).

    A User belongs to the thread that made it (its client's shared-memory ports do);
    make one per thread. It waits in the kernel with the GIL released."""

    def __init__(self, instance: str = "default", *, remote: Optional[str] = None,
                 key: Optional[str] = None, broker_key: Optional[str] = None,
                 wait: float = 5.0):
        self._native = _native.NativeUser(instance, remote, key, broker_key, wait)
        self._sessions: Dict[int, Session] = {}
        self._answers: Dict[int, List[dict]] = {}
        # A session's events pumped before its Session was made (its grant and its
        # first updates came in one batch): kept for it, oldest dropped past the bound.
        self._early: Deque[dict] = collections.deque(maxlen=_EARLY_EVENTS)
        self._links: Dict[int, Link] = {}
        self._list_changes = 0
        #: Whether a broker is there now (sessions go on without one).
        self.broker_connected = True

    @property
    def id(self) -> str:
        """This user's id, as the broker knows it."""
        return self._native.id

    def __repr__(self) -> str:
        where = "remote" if self._native.remote else "local"
        return f"<muster.User {self.id} ({where})>"

    # The pump: one event, routed to what waits for it.
    def _route(self, ev: dict) -> None:
        e = ev["event"]
        if e in ("update", "status", "ended", "end_confirmed"):
            s = self._sessions.get(ev["session"])
            if s is not None:
                s._take(ev)
                if s.ended is not None and not s._items:
                    self._sessions.pop(s.id, None)
            else:
                self._early.append(ev)
        elif e in ("queued", "granted", "refused"):
            self._answers.setdefault(ev["req"], []).append(ev)
        elif e == "list_changed":
            self._list_changes += 1
        elif e in ("link_up", "link_forwarded", "link_ended"):
            link = self._links.get(ev["link"])
            if link is not None:
                if e == "link_up":
                    link.up = True
                elif e == "link_forwarded":
                    link.forwarded += 1
                else:
                    link.ended = ev["reason"]
                    self._links.pop(link.number, None)
        elif e == "broker_lost":
            self.broker_connected = False
        elif e == "connected":
            self.broker_connected = True
            self._list_changes += 1

    def _pump(self, timeout: Optional[float]) -> bool:
        """Takes one event (waiting up to `timeout`); whether one came."""
        ev = self._native.next_event(timeout)
        if ev is None:
            return False
        self._route(ev)
        # Whatever else is here already, without waiting.
        for _ in range(1024):
            ev = self._native.next_event(0)
            if ev is None:
                break
            self._route(ev)
        return True

    async def _apump(self, timeout: Optional[float]) -> bool:
        """Takes what is here; else waits (without blocking the loop) until the
        client's descriptor has news, `timeout` passes, or a remote user's timers are
        due, and takes what came."""
        if self._pump(0):
            return True
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        fd = self._native.fileno()
        loop.add_reader(fd, lambda: fut.done() or fut.set_result(None))
        try:
            # News may have come between the look above and the reader.
            if self._pump(0):
                return True
            wait = timeout
            timers = self._native.next_deadline()
            if timers is not None:
                wait = timers if wait is None else min(wait, timers)
            try:
                await asyncio.wait_for(fut, wait)
            except asyncio.TimeoutError:
                pass
        finally:
            loop.remove_reader(fd)
        return self._pump(0)

    # The list.
    def list(self, *, host: Optional[str] = None, system: Optional[str] = None,
             kind: Optional[str] = None, payload: Optional[str] = None,
             name: Optional[str] = None, offset: int = 0,
             limit: Optional[int] = None) -> List[Service]:
        """The service list, or the part of it the filters let through (every one
        given must hold; `name` is a glob such as "cam*"), from the `offset`th, at
        most `limit`. A local user reads a page in place in shared memory; a remote
        one is sent only the page. Raises ValueError for a bad filter."""
        if (host, system, kind, payload, name, offset, limit) == (None,) * 5 + (0, None):
            return [Service._of(d) for d in self._native.list()]
        return self.page(host=host, system=system, kind=kind, payload=payload,
                         name=name, offset=offset, limit=limit)[1]

    def page(self, *, host: Optional[str] = None, system: Optional[str] = None,
             kind: Optional[str] = None, payload: Optional[str] = None,
             name: Optional[str] = None, offset: int = 0,
             limit: Optional[int] = None) -> Tuple[int, List[Service]]:
        """`list` with how many services the filters let through in all."""
        matching, page = self._native.list_page(host, system, kind, payload, name,
                                                offset, limit)
        return matching, [Service._of(d) for d in page]

    def watch(self, timeout: Optional[float] = None, *, host: Optional[str] = None,
              system: Optional[str] = None, kind: Optional[str] = None,
              payload: Optional[str] = None,
              name: Optional[str] = None) -> Iterator[List[Service]]:
        """The list (or the part the filters let through) now, then again each time
        it changes (until `timeout` passes without a change, if given). With filters,
        the broker tells this user only of changes in that part."""
        part = dict(host=host, system=system, kind=kind, payload=payload, name=name)
        self._native.watch_part(**part)
        seen = self._list_changes
        shown = self.list(**part)
        yield shown
        while True:
            deadline = None if timeout is None else time.monotonic() + timeout
            while True:
                while self._list_changes == seen:
                    left = None if deadline is None else deadline - time.monotonic()
                    if left is not None and left <= 0:
                        return
                    self._pump(left)
                seen = self._list_changes
                now = self.list(**part)
                if now != shown:
                    break
            shown = now
            yield shown

    # Requests.
    def request(self, service: str, timeout: Optional[float] = 10.0,
                on_queued: Optional[Callable[[int], None]] = None) -> Session:
        """Asks for `service`; returns the Session once granted. Raises Refused (with
        the broker's reason and code), or TimeoutError after `timeout` seconds (the
        request is then cancelled). `on_queued(position)` hears each queue position."""
        pending = _Pending(self, service, timeout, on_queued)
        while True:
            s, left = pending.step()
            if s is not None:
                return s
            self._pump(left)

    async def arequest(self, service: str, timeout: Optional[float] = 10.0,
                       on_queued: Optional[Callable[[int], None]] = None) -> Session:
        """`request` for asyncio."""
        pending = _Pending(self, service, timeout, on_queued)
        while True:
            s, left = pending.step()
            if s is not None:
                return s
            await self._apump(left)

    def _answer(self, ev: dict, queued: List[int],
                on_queued: Optional[Callable[[int], None]]) -> Optional[Session]:
        if ev["event"] == "queued":
            queued.append(ev["position"])
            if on_queued is not None:
                on_queued(ev["position"])
            return None
        if ev["event"] == "refused":
            raise Refused(ev["service"], ev["code"], ev["reason"])
        s = Session(self, ev, queued)
        self._sessions[s.id] = s
        mine = [e for e in self._early if e["session"] == s.id]
        if mine:
            self._early = collections.deque(
                (e for e in self._early if e["session"] != s.id), maxlen=_EARLY_EVENTS)
            for e in mine:
                self._route(e)
        return s

    # Links.
    def link(self, data: str, command: str, timeout: Optional[float] = 10.0) -> Link:
        """Links data service `data` into command service `command`; returns once both
        are granted. Raises MusterError if they cannot be linked (the reason), or
        TimeoutError."""
        link = Link(self, self._native.link(data, command), data, command)
        self._links[link.number] = link
        deadline = None if timeout is None else time.monotonic() + timeout
        while not link.up:
            if link.ended is not None:
                raise MusterError(f"link {data} -> {command} ended: {link.ended}")
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                link.end()
                raise TimeoutError(f"link {data} -> {command} not up within {timeout} s")
            self._pump(left)
        return link

    def poll(self, timeout: float = 0.0) -> None:
        """Takes what arrived (waiting up to `timeout`), so sessions, links and the
        broker's state are up to date without iterating a session."""
        deadline = time.monotonic() + timeout
        while self._pump(max(0.0, deadline - time.monotonic())):
            if time.monotonic() >= deadline:
                break

    def close(self) -> None:
        """Ends every session and link and leaves (idempotent)."""
        self._native.close()

    def __enter__(self) -> "User":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    async def __aenter__(self) -> "User":
        return self

    async def __aexit__(self, *exc: Any) -> None:
        self.close()
