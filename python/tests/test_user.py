"""A Python user against muster's own (Rust) broker and systems."""

from __future__ import annotations

import asyncio
import signal
import time

import muster
import pytest
from conftest import services, wait_until


def test_lists_requests_streams_and_ends(fed):
    fed.broker()
    fed.muster("system", "synthetic", "--name", "t1", "--services", "2", "--rate", "50")
    with muster.User(fed.inst) as me:
        listed = services(me, 2)
        assert [s.id for s in listed] == ["t1/s0", "t1/s1"]
        s0 = listed[0]
        assert (s0.system, s0.name, s0.kind, s0.payload, s0.quota, s0.in_use) == \
            ("t1", "s0", "data", "pose2d", 10, 0)
        assert (s0.withdrawn, s0.queue, s0.remote) == (False, False, False)
        with me.request("t1/s0", timeout=10) as session:
            assert (session.service, session.kind, session.payload) == ("t1/s0", "data", "pose2d")
            got = []
            for u in session.updates(timeout=5):
                got.append(u)
                if len(got) == 20:
                    break
            assert len(got) == 20
            assert all(isinstance(u.value, muster.Pose2d) for u in got)
            seqs = [u.seq for u in got]
            assert seqs == list(range(seqs[0], seqs[0] + 20)), seqs
            assert session.lost == 0
            # The broker counts it in use.
            wait_until(lambda: me.list()[0].in_use == 1, what="in_use 1")
        # Ended on leaving the block: the quota is free again.
        wait_until(lambda: me.list()[0].in_use == 0, what="in_use 0")
        assert session.ended == "ended by the user"


def test_refusals_carry_the_reason_and_code_and_queue_positions_are_seen(fed):
    fed.broker()
    fed.muster("system", "synthetic", "--name", "d1", "--kind", "command", "--quota", "1",
               "--queue")
    fed.muster("system", "synthetic", "--name", "d2", "--kind", "command", "--quota", "1")
    with muster.User(fed.inst) as a, muster.User(fed.inst) as b:
        services(a, 2)
        with pytest.raises(muster.Refused) as e:
            a.request("nope/s0")
        assert e.value.code == "unknown" and "unknown service" in e.value.reason
        held = a.request("d2/s0")
        with pytest.raises(muster.Refused) as e:
            b.request("d2/s0")
        assert e.value.code == "quota_full", e.value
        held.end()
        # A queue: b waits at position 1 and is granted once a ends.
        first = a.request("d1/s0")
        positions = []
        with pytest.raises(TimeoutError):
            b.request("d1/s0", timeout=1.0, on_queued=positions.append)
        assert positions == [1]
        first.end()
        # The timed-out request was cancelled: once the quota is free, a new one is
        # granted at once.
        wait_until(lambda: a.list()[0].in_use == 0 and a.list()[0].queued == 0,
                   what="the quota free and the queue empty")
        s = b.request("d1/s0", timeout=10)
        assert s.queue_positions == []
        s.end()


def test_a_command_session_takes_goals_and_reports_status_and_bad_input_is_refused(fed):
    fed.broker()
    fed.muster("system", "synthetic", "--name", "d1", "--kind", "command", "--quota", "1")
    with muster.User(fed.inst) as me:
        services(me, 1)
        with me.request("d1/s0") as s:
            s.send(muster.Goal2d(3.0, 4.0))
            st = s.wait_status("done", timeout=15)
            assert st.state == "done" and "3" in st.text, st
            with pytest.raises(muster.PayloadError, match="takes goal2d, not text"):
                s.send("open")
            with pytest.raises(TypeError):
                s.send(object())
            with pytest.raises(muster.PayloadError):
                s.send({"type": "goal2d", "x": "three"})
        wait_until(lambda: me.list()[0].in_use == 0, what="the quota free")
        with me.request("d1/s0") as s2:
            with pytest.raises(muster.MusterError, match="no session|ended"):
                s2.end()
                s2.send(muster.Goal2d(1, 1))


def test_a_link_forwards_a_tracker_into_a_command_service(fed):
    fed.broker()
    fed.muster("system", "synthetic", "--name", "t1", "--rate", "20")
    fed.muster("system", "synthetic", "--name", "d1", "--kind", "command", "--quota", "1")
    with muster.User(fed.inst) as me:
        services(me, 2)
        with pytest.raises(muster.MusterError, match="d1/s0 is not a data service"):
            me.link("d1/s0", "t1/s0")
        with pytest.raises(muster.UnknownService):
            me.link("zz/s0", "d1/s0")
        with me.link("t1/s0", "d1/s0") as link:
            wait_until(lambda: (me.poll(0.1), link.forwarded >= 3)[1], what="forwards")
            wait_until(lambda: me.list()[1].in_use == 1 and me.list()[1].links == 1,
                       what="the link counted")
        wait_until(lambda: me.list()[1].links == 0, what="the link's end counted")


def test_the_list_is_watched(fed):
    fed.broker()
    with muster.User(fed.inst) as me:
        changes = me.watch(timeout=10)
        assert next(changes) == []
        fed.muster("system", "synthetic", "--name", "t9")
        seen = next(changes)
        while len(seen) != 1:
            seen = next(changes)
        assert seen[0].id == "t9/s0"


def test_the_list_is_read_filtered_and_in_pages_and_a_part_of_it_watched(fed):
    fed.broker()
    fed.muster("system", "synthetic", "--name", "t1", "--services", "12")
    fed.muster("system", "synthetic", "--name", "d1", "--kind", "command")
    with muster.User(fed.inst) as me:
        services(me, 13)
        assert [s.id for s in me.list(kind="command")] == ["d1/s0"]
        # t1's s1, s10, s11 by a glob; the second and third of them as a page.
        assert [s.id for s in me.list(system="t1", name="s1*")] == ["t1/s1", "t1/s10", "t1/s11"]
        matching, page = me.page(system="t1", name="s1*", offset=1, limit=2)
        assert (matching, [s.id for s in page]) == (3, ["t1/s10", "t1/s11"])
        assert [s.id for s in me.list(offset=12, limit=5)] == ["t1/s9"]
        with pytest.raises(ValueError):
            me.list(name="s[1")
        with pytest.raises(ValueError):
            me.list(kind="neither")
        # Watching t2 only: t9 coming is not told; t2 coming is.
        changes = me.watch(timeout=10, system="t2")
        assert next(changes) == []
        fed.muster("system", "synthetic", "--name", "t9")
        wait_until(lambda: len(me.list()) == 14, what="t9 listed")
        fed.muster("system", "synthetic", "--name", "t2")
        assert [s.id for s in next(changes)] == ["t2/s0"]


def test_asyncio_requests_and_iterates(fed):
    fed.broker()
    fed.muster("system", "synthetic", "--name", "t1", "--rate", "50")

    async def main():
        async with muster.User(fed.inst) as me:
            services(me, 1)
            session = await me.arequest("t1/s0")
            got = []
            async for u in session:
                got.append(u.seq)
                if len(got) == 10:
                    break
            session.end()
            assert got == list(range(got[0], got[0] + 10))
            # anext with a timeout that passes: None, while the loop stays free.
            ticks = 0

            async def ticker():
                nonlocal ticks
                while True:
                    await asyncio.sleep(0.01)
                    ticks += 1
            t = asyncio.ensure_future(ticker())
            with pytest.raises(muster.SessionEnded):
                while True:
                    await session.anext(timeout=0.3)
            t.cancel()
    asyncio.run(main())


def test_sessions_go_on_across_a_broker_restart_and_a_dead_system_is_said(fed):
    b = fed.broker()
    fed.muster("system", "synthetic", "--name", "t1", "--rate", "20")
    sys2 = fed.muster("system", "synthetic", "--name", "t2", "--rate", "20")
    with muster.User(fed.inst) as me:
        services(me, 2)
        s1 = me.request("t1/s0")
        s2 = me.request("t2/s0")
        first = s1.next(timeout=5)
        fed.stop(b, signal.SIGKILL)
        # Updates keep coming with no broker.
        later = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.0:
            u = s1.next(timeout=1)
            if u is not None:
                later.append(u)
        assert later and later[-1].seq > first.seq
        wait_until(lambda: (me.poll(0.1), not me.broker_connected)[1], what="broker lost")
        fed.broker()
        wait_until(lambda: (me.poll(0.1), me.broker_connected)[1], what="reconnected")
        assert s1.ended is None
        # The system dies: its session ends, said.
        fed.stop(sys2, signal.SIGKILL)
        with pytest.raises(muster.SessionEnded) as e:
            while True:
                s2.next(timeout=10)
        assert e.value.code == "peer_gone", e.value


def test_a_remote_user_over_udp_with_a_key(fed):
    from conftest import free_udp_port
    access = fed.keys("alice")
    addr = f"127.0.0.1:{free_udp_port()}"
    fed.broker("--udp", addr, "--access", str(access))
    fed.muster("system", "synthetic", "--name", "t1", "--rate", "50", "--udp", "127.0.0.1:0")
    key = str(fed.dir / "alice.key")
    with muster.User(remote=addr, key=key) as me:
        assert me.id.startswith("alice")
        services(me, 1)
        with me.request("t1/s0") as s:
            seqs = [u.seq for u, _ in zip(s.updates(timeout=5), range(10))]
            assert len(seqs) == 10
    with pytest.raises(muster.MusterError, match="key"):
        muster.User(remote=addr)
    with pytest.raises(muster.NoBroker):
        muster.User(remote=f"127.0.0.1:{free_udp_port()}", key=key, wait=0.5)


def test_no_broker_is_a_clear_error(fed):
    with pytest.raises(muster.NoBroker, match=fed.inst):
        muster.User(fed.inst, wait=0.3)


def test_a_panic_in_musters_rust_code_is_an_internal_error_and_the_process_lives():
    from muster import _native
    for _ in range(2):
        with pytest.raises(muster.InternalError, match="the panic guard's self-check"):
            _native._check_panic_guard()
    assert issubclass(muster.InternalError, muster.MusterError)
