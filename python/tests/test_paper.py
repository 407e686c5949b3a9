"""A Python user with the paper's robots (the simulator, the tracking system, the
delivery robot D1), sped up 5 times."""

from __future__ import annotations

import math
import time

import muster
from conftest import services, wait_until

SPEED = "5"


def test_a_python_user_tracks_red_links_it_into_d1_and_reads_d1s_status(fed):
    fed.broker("--time-scale", SPEED)
    fed.muster("sim", "--time-scale", SPEED)
    fed.muster("system", "tracking", "--time-scale", SPEED)
    fed.muster("system", "delivery", "--time-scale", SPEED)
    with muster.User(fed.inst) as me:
        listed = {s.id: s for s in services(me, 4, timeout=60)}
        assert listed["delivery/D1"].kind == "command"
        assert listed["delivery/D1"].payload == "goal2d"
        assert listed["tracking/red"].payload == "track2d"
        # The red person's track: Track2d values, lost until a camera sees them.
        with me.request("tracking/red") as red:
            seen = None
            deadline = time.monotonic() + 90
            while seen is None and time.monotonic() < deadline:
                u = red.next(timeout=5)
                if u is not None:
                    assert isinstance(u.value, muster.Track2d), u
                    if not u.value.lost:
                        seen = u.value
            assert seen is not None, "red was never tracked"
            assert math.isfinite(seen.x) and math.isfinite(seen.y) and seen.seen_by
        # Red into D1: D1 is told the person's position as its goal.
        with me.link("tracking/red", "delivery/D1", timeout=30) as link:
            wait_until(lambda: (me.poll(0.2), link.forwarded >= 1)[1], timeout=90,
                       what="a goal forwarded to D1")
        wait_until(lambda: next(s for s in me.list() if s.id == "delivery/D1").in_use == 0,
                   what="D1 free again")
        # D1 itself: a goal, and its status as it comes.
        with me.request("delivery/D1", timeout=30) as d1:
            d1.send(muster.Goal2d(seen.x, seen.y))
            st = d1.wait_status("working", timeout=30)
            while "m to go" not in st.detail:
                st = d1.wait_status("working", timeout=30)
            assert st.detail.startswith("driving: at ("), st
