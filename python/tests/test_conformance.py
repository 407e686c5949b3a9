"""The conformance scenarios of tests/conformance.rs, with a Python user, over both
transports: shared memory on this host, and UDP with a key."""

from __future__ import annotations

import signal
import subprocess
import time

import muster
import pytest
from conftest import free_udp_port, services, wait_until


class Conf:
    def __init__(self, fed, via: str):
        self.fed, self.via = fed, via
        self.access = fed.keys("alice")
        self.addr = f"127.0.0.1:{free_udp_port()}"
        self.broker = self.start_broker()

    def start_broker(self):
        return self.fed.broker("--udp", self.addr, "--access", str(self.access))

    def system(self, name, *extra, stdin=subprocess.DEVNULL):
        return self.fed.muster("system", "synthetic", "--name", name, "--udp", "127.0.0.1:0",
                               *extra, stdin=stdin)

    def user(self) -> muster.User:
        if self.via == "shm":
            return muster.User(self.fed.inst)
        return muster.User(remote=self.addr, key=str(self.fed.dir / "alice.key"))


@pytest.fixture(params=["shm", "udp"])
def conf(fed, request):
    return Conf(fed, request.param)


def take(session, seconds, into):
    """The updates (or statuses) that come in `seconds`, appended to `into`."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        item = session.next(timeout=0.2)
        if item is not None:
            into.append(item)
    return into


def in_use(me, sid):
    """How many sessions the list counts on `sid`; None while it is not listed (a
    restarted broker lists a system once it has registered again)."""
    return next((s.in_use for s in me.list() if s.id == sid), None)


def test_lists_every_service_with_its_fields(conf):
    conf.system("t1", "--services", "2")
    conf.system("d1", "--kind", "command", "--quota", "1", "--queue")
    with conf.user() as me:
        listed = {s.id: s for s in services(me, 3)}
        d = listed["d1/s0"]
        assert (d.kind, d.quota, d.queue) == ("command", 1, True)
        assert listed["t1/s1"].payload == "pose2d"


def test_refusals_name_their_reason(conf):
    conf.system("t1", "--quota", "1")
    with conf.user() as me, conf.user() as other:
        services(me, 1)
        with pytest.raises(muster.Refused) as e:
            me.request("nosuch/s0")
        assert e.value.code == "unknown"
        held = me.request("t1/s0")
        with pytest.raises(muster.Refused) as e:
            other.request("t1/s0")
        assert e.value.code == "quota_full"
        held.end()


def test_a_data_session_streams_in_order_and_frees_its_quota(conf):
    conf.system("t1", "--rate", "20", "--quota", "1")
    with conf.user() as me:
        services(me, 1)
        s = me.request("t1/s0")
        seqs = [u.seq for u in take(s, 2.0, [])]
        s.end()
        assert seqs[0] == 1, "the first update is not lost"
        assert len(seqs) >= 20, seqs
        assert seqs == list(range(1, len(seqs) + 1)), "in order, no gaps"
        assert s.lost == 0
        # The quota is free again: a second user gets the service.
        wait_until(lambda: in_use(me, "t1/s0") == 0, what="the quota free")
        with conf.user() as second:
            second.request("t1/s0").end()


def test_the_system_ends_a_session_and_the_user_is_told(conf):
    t1 = conf.system("t1", stdin=subprocess.PIPE)
    with conf.user() as me:
        services(me, 1)
        s = me.request("t1/s0")
        s.next(timeout=5)
        t1.stdin.write("end all\n")
        t1.stdin.flush()
        with pytest.raises(muster.SessionEnded) as e:
            while True:
                s.next(timeout=15)
        assert "ended by the system" in e.value.reason and e.value.code == "by_system"


def test_a_command_session_takes_a_goal_and_reports_arrival(conf):
    conf.system("d1", "--kind", "command", "--quota", "1", "--rate", "20")
    with conf.user() as me:
        services(me, 1)
        with me.request("d1/s0") as d:
            d.send(muster.Goal2d(1.5, -1.5))
            texts = [st.text for st in take(d, 3.0, []) if isinstance(st, muster.Status)]
        assert texts[0] == "idle", texts
        assert any("goal (1.50, -1.50) accepted" in t for t in texts), texts
        assert sum(t.startswith("done: arrived within 1 m") for t in texts) == 1, texts


def test_a_queued_request_is_granted_at_the_head_of_the_queue(conf):
    conf.system("d1", "--kind", "command", "--quota", "1", "--queue")
    with conf.user() as me, conf.user() as second:
        services(me, 1)
        first = me.request("d1/s0")
        positions = []
        # The first ends while the second waits in the queue.
        me_end_at = time.monotonic() + 1.0

        def on_queued(p):
            positions.append(p)
            while time.monotonic() < me_end_at:
                time.sleep(0.05)
            first.end()
        s = second.request("d1/s0", timeout=20, on_queued=on_queued)
        assert positions == [1] and s.queue_positions == [1]
        s.end()


def test_sessions_survive_a_broker_crash(conf):
    conf.system("t1", "--rate", "20", "--quota", "1")
    with conf.user() as me:
        services(me, 1)
        s = me.request("t1/s0")
        got = take(s, 1.5, [])
        conf.fed.stop(conf.broker, signal.SIGKILL)
        take(s, 1.0, got)
        conf.broker = conf.start_broker()
        # The restarted broker learns the old session from the system.
        wait_until(lambda: in_use(me, "t1/s0") == 1, what="the session relearned")
        take(s, 2.0, got)
        s.end()
        seqs = [u.seq for u in got]
        assert len(seqs) >= 60, len(seqs)
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "no gap"
        assert s.lost == 0


def test_a_link_forwards_data_as_task_input(conf):
    conf.system("t1", "--rate", "20")
    conf.system("d1", "--kind", "command", "--rate", "20")
    with conf.user() as me:
        services(me, 2)
        with me.link("t1/s0", "d1/s0") as link:
            t0 = time.monotonic()
            while time.monotonic() - t0 < 2.0:
                me.poll(0.1)
        assert link.forwarded >= 10, link.forwarded
