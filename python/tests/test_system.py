"""A Python system, served to muster's own (Rust) users and to Python users."""

from __future__ import annotations

import json
import sys
import textwrap
import time

import muster
import pytest
from conftest import EXAMPLES, services, wait_until


def test_the_door_example_serves_a_rust_user(fed):
    fed.broker()
    door = fed.python(str(EXAMPLES / "door_system.py"), fed.inst)
    wait_until(lambda: len(json.loads(fed.run("user", "list", "--json").stdout or "[]")) == 2,
               what="the door's services")
    r = fed.run("user", "request", "door/open", "--input", '"open"', "--duration", "4s", "--json")
    assert r.returncode == 0, r.stderr
    lines = [json.loads(l) for l in r.stdout.splitlines()]
    states = [(l["state"], l["detail"]) for l in lines if l.get("state")]
    assert states == [("working", "opening"), ("done", "open")], lines
    r = fed.run("user", "request", "door/state", "--duration", "1s", "--json")
    values = [l["payload"] for l in map(json.loads, r.stdout.splitlines()) if "seq" in l]
    assert len(values) >= 3 and all(v == {"type": "text", "text": "open"} for v in values), values
    assert door.poll() is None, "the system runs on"


def test_the_door_examples_together(fed):
    fed.broker()
    fed.python(str(EXAMPLES / "door_system.py"), fed.inst)
    with muster.User(fed.inst) as me:
        services(me, 2)
    user = fed.python(str(EXAMPLES / "door_user.py"), fed.inst)
    out, err = user.communicate(timeout=60)
    assert user.returncode == 0, err
    lines = out.splitlines()
    assert lines[0] == "['door/open', 'door/state']"
    assert lines[1] == "open"
    assert lines[2:] == [f"{i} open" for i in range(1, 6)], lines


SYSTEM = textwrap.dedent('''
    import sys, muster
    s = muster.System("py1", instance=sys.argv[1])

    @s.command_service("echo", payload="text", quota=2)
    def echo(session, value):
        if value == "boom":
            raise RuntimeError("boom asked")
        session.done(value.upper())

    @echo.on_start
    def started(session):
        print("start", session.user == "" or session.service, flush=True)

    @echo.on_end
    def ended(session, reason):
        print("end", reason, flush=True)

    @s.data_service("n", payload="scalar", rate=50)
    def n():
        return 42.5

    @s.data_service("battery", payload="battery", encoding="jsonschema", rate=20,
                    schema='{"type": "object", "properties": {"pct": {"type": "number"}}}')
    def battery():
        return muster.Open("battery", {"pct": 80.5})

    @s.data_service("big", payload="text")
    def big():
        pass

    @s.command_service("ctl", payload="text")
    def ctl(session, value):
        if value == "withdraw":
            s.withdraw("n")
        elif value == "restore":
            s.restore("n")
        elif value == "big":
            try:
                big.publish("x" * 5000)
            except muster.PayloadError as e:
                session.done("refused: " + str(e))
                return
            session.done("sent")
        elif value == "stop":
            session.done("stopping")
            s.stop()

    print(s.run(), flush=True)
''')


def listed(me, sid):
    return next(s for s in me.list() if s.id == sid)


def test_callbacks_errors_withdrawal_and_stop(fed, tmp_path):
    fed.broker()
    script = tmp_path / "sys.py"
    script.write_text(SYSTEM)
    proc = fed.python(str(script), fed.inst)
    with muster.User(fed.inst) as me:
        services(me, 5)
        # An open payload type with its JSON schema: listed with its encoding, decoded.
        assert listed(me, "py1/battery").payload == "battery"
        assert listed(me, "py1/battery").encoding == "json"
        with me.request("py1/battery") as b:
            assert b.encoding == "json" and '"pct"' in b.schema
            u = next(b.updates(timeout=5))
            assert u.value == muster.Open("battery", {"pct": 80.5}, encoding="json"), u
        # Input, status, the start and end callbacks.
        with me.request("py1/echo") as s:
            s.send("hi")
            assert s.wait_status("done", timeout=10).detail == "HI"
        # A callback that raises ends its session only, with the reason.
        s = me.request("py1/echo")
        s.send("boom")
        with pytest.raises(muster.SessionEnded) as e:
            while True:
                s.next(timeout=10)
        assert "raised" in e.value.reason and "boom asked" in e.value.reason, e.value
        with me.request("py1/echo") as s:
            s.send("again")
            assert s.wait_status("done", timeout=10).detail == "AGAIN"
        # A data service at 50 Hz: scalars.
        with me.request("py1/n") as n:
            vals = [u.value for u, _ in zip(n.updates(timeout=5), range(5))]
            assert vals == [42.5] * 5
        # Withdraw and restore from a callback.
        ctl = me.request("py1/ctl")
        n = me.request("py1/n")
        ctl.send("withdraw")
        with pytest.raises(muster.SessionEnded) as e:
            while True:
                n.next(timeout=10)
        assert e.value.code == "withdrawn"
        wait_until(lambda: listed(me, "py1/n").withdrawn, what="withdrawn in the list")
        with pytest.raises(muster.Refused) as e:
            me.request("py1/n")
        assert e.value.code == "withdrawn"
        ctl.send("restore")
        wait_until(lambda: not listed(me, "py1/n").withdrawn, what="restored")
        # An update too large for a user's path raises in the system, and is said.
        with me.request("py1/big") as big:
            ctl.send("big")
            st = ctl.wait_status("done", timeout=10)
            assert "refused" in st.detail and "4096" in st.detail, st
        # stop() from a callback: run() returns its report.
        ctl.send("stop")
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        report = out.strip().splitlines()[-1]
        assert "'echo': {'quota': 2" in report and "'grants': 3" in report, out
        assert "start echo" in out and "end ended by the user" in out, out
        assert "RuntimeError: boom asked" in err, err


def test_bad_declarations_are_refused_with_the_reason():
    s = muster.System("okname", instance="nobroker-here")
    with pytest.raises(muster.MusterError, match="kind"):
        s._native.add_service("x", "both", "pose2d", 1, False, "", None, None)
    with pytest.raises(muster.MusterError, match="name"):
        s.data_service("bad name!")(lambda: None)
    with pytest.raises(muster.MusterError, match="twice"):
        s.data_service("a")(lambda: None)
        s.data_service("a")(lambda: None)
    with pytest.raises(muster.MusterError, match="name"):
        muster.System("no/slash")
    with pytest.raises(muster.MusterError, match="rate"):
        s.data_service("b", rate=0)(lambda: None)
    with pytest.raises(muster.MusterError, match="only a data service can be latched"):
        s._native.add_service("c", "command", "goal2d", 1, False, "", None, None, True)
    with pytest.raises(muster.MusterError, match="not running"):
        s.publish("a", muster.Pose2d(0, 0, 0))


LATCHED = textwrap.dedent('''
    import itertools, sys, muster
    s = muster.System("py2", instance=sys.argv[1])
    n = itertools.count(1)
    m = itertools.count(1)

    @s.data_service("pos", rate=5, latched=True)
    def pos():
        return muster.Pose2d(next(n), 0.0)

    @s.data_service("plain", rate=5)
    def plain():
        return muster.Pose2d(next(m), 0.0)

    s.run()
''')


def test_a_latched_python_service_gives_a_new_session_its_newest_value_with_the_grant(
        fed, tmp_path):
    fed.broker()
    script = tmp_path / "latched.py"
    script.write_text(LATCHED)
    fed.python(str(script), fed.inst)
    with muster.User(fed.inst) as me:
        services(me, 2)
        # Nobody holds a session, yet the latched service updates at its rate (5 Hz)
        # and the broker keeps the newest.
        time.sleep(1.0)
        with me.request("py2/pos") as p:
            ups = [u for u, _ in zip(p.updates(timeout=5), range(3))]
        # Update 0 comes from the broker with the grant: a value published with no
        # session (the counter had passed 1), then the system's own stream from 1,
        # newer, nothing lost.
        assert [u.seq for u in ups] == [0, 1, 2], ups
        assert ups[0].value.x >= 3, ups
        assert ups[1].value.x > ups[0].value.x and ups[2].value.x == ups[1].value.x + 1, ups
        assert p.lost == 0
        # A service not latched starts at update 1, its function not called before.
        with me.request("py2/plain") as q:
            u = next(q.updates(timeout=5))
        assert (u.seq, u.value.x) == (1, 1), u


def test_a_python_system_keeps_its_sessions_across_a_broker_restart(fed):
    import signal
    b = fed.broker()
    fed.python(str(EXAMPLES / "door_system.py"), fed.inst)
    with muster.User(fed.inst) as me:
        services(me, 2)
        state = me.request("door/state")
        before = state.next(timeout=5).seq
        fed.stop(b, signal.SIGKILL)
        fed.broker()
        # The system registers again by itself: listed, and the session streams on.
        wait_until(lambda: (me.poll(0.1), me.broker_connected and len(me.list()) == 2)[1],
                   what="the door listed by the new broker")
        seqs = [u.seq for u, _ in zip(state.updates(timeout=5), range(10))]
        assert len(seqs) == 10 and seqs[0] > before, seqs
        assert state.ended is None and state.lost == 0
        # And it serves new requests.
        with me.request("door/open", timeout=10) as d:
            d.send("open")
            assert d.wait_status("done", timeout=10).detail == "open"


def test_a_system_served_from_asyncio_beside_an_asyncio_user(fed):
    import asyncio
    fed.broker()
    s = muster.System("aio", instance=fed.inst)

    @s.command_service("double", payload="scalar", quota=1)
    def double(session, value):
        session.done(str(value * 2))

    async def main():
        serving = asyncio.ensure_future(s.serve())
        async with muster.User(fed.inst) as me:
            deadline = time.monotonic() + 15
            while not me.list():
                assert time.monotonic() < deadline, "the system was never listed"
                await asyncio.sleep(0.05)
            session = await me.arequest("aio/double")
            session.send(21.0)
            status = None
            while status is None or status.state != "done":
                status = await session.anext(timeout=10)
                assert status is not None, "no status"
            assert status.detail == "42.0"
            session.end()
        s.stop()
        return await asyncio.wait_for(serving, 15)

    report = asyncio.run(main())
    assert report["double"]["grants"] == 1, report
    assert not s._native.running


def test_a_python_system_serves_a_remote_python_user_over_udp(fed):
    from conftest import free_udp_port
    access = fed.keys("alice")
    addr = f"127.0.0.1:{free_udp_port()}"
    fed.broker("--udp", addr, "--access", str(access))
    script = textwrap.dedent('''
        import sys, muster
        s = muster.System("far", instance=sys.argv[1], udp="127.0.0.1:0")

        @s.command_service("shout", payload="text")
        def shout(session, value):
            session.done(value.upper())

        @s.data_service("count", payload="scalar", rate=20)
        def count():
            return 7.0

        s.run()
    ''')
    path = fed.dir / "far.py"
    path.write_text(script)
    fed.python(str(path), fed.inst)
    with muster.User(remote=addr, key=str(fed.dir / "alice.key")) as me:
        assert me._native.remote
        services(me, 2)
        with me.request("far/shout") as s:
            s.send("hello")
            assert s.wait_status("done", timeout=10).detail == "HELLO"
        with me.request("far/count") as c:
            got = [u for u, _ in zip(c.updates(timeout=5), range(10))]
            assert [u.value for u in got] == [7.0] * 10
            assert [u.seq for u in got] == list(range(got[0].seq, got[0].seq + 10))


def test_updates_a_full_inbox_refuses_are_counted_by_the_system_and_seen_as_gaps(fed):
    fed.broker()
    script = textwrap.dedent('''
        import sys, muster
        s = muster.System("burst", instance=sys.argv[1])

        @s.data_service("flood", payload="scalar")
        def flood():
            pass

        @s.command_service("ctl", payload="text")
        def ctl(session, value):
            if value == "burst":
                for i in range(3000):
                    flood.publish(float(i))
                session.done("sent")
            elif value == "one":
                flood.publish(-1.0)
                session.done("sent")
            else:
                session.done(str(s.undelivered))

        s.run()
    ''')
    path = fed.dir / "burst.py"
    path.write_text(script)
    fed.python(str(path), fed.inst)
    with muster.User(fed.inst) as me:
        services(me, 2)
        flood = me.request("burst/flood")
        ctl = me.request("burst/ctl")

        def ask(what):
            ctl.send(what)
            return ctl.wait_status("done", timeout=20).detail
        # 3,000 at once into an inbox nobody reads meanwhile: some do not fit.
        assert ask("burst") == "sent"
        lost_by_system = int(ask("count"))
        assert lost_by_system > 0, "the burst fit the inbox: make it larger"
        # One more update after the burst shows the tail's gap to the user.
        assert ask("one") == "sent"
        got = []
        while True:
            u = flood.next(timeout=2)
            if u is None:
                break
            got.append(u)
        assert got[-1].value == -1.0 and got[-1].seq == 3001, got[-1]
        assert len(got) + flood.lost == 3001
        assert flood.lost == lost_by_system, (flood.lost, lost_by_system)


def test_ctrl_c_stops_a_running_system_and_run_returns_its_report(fed):
    import signal as sig
    fed.broker()
    script = textwrap.dedent('''
        import signal, sys, muster
        # As in a terminal (a background job starts with SIGINT ignored).
        signal.signal(signal.SIGINT, signal.default_int_handler)
        s = muster.System("cc", instance=sys.argv[1])

        @s.data_service("n", payload="scalar", rate=10)
        def n():
            return 1.0

        print("running", flush=True)
        print("report", s.run(), flush=True)
        print("after", flush=True)
    ''')
    path = fed.dir / "cc.py"
    path.write_text(script)
    p = fed.python(str(path), fed.inst)
    with muster.User(fed.inst) as me:
        services(me, 1)
    p.send_signal(sig.SIGINT)
    out, err = p.communicate(timeout=20)
    assert p.returncode == 0, err
    assert "report {'n': {'quota': 10" in out and out.rstrip().endswith("after"), out
    assert "KeyboardInterrupt" not in err, err
