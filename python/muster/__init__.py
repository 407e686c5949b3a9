"""muster for Python: ask robots for services, or offer them, in a few lines.

A user::

    import muster
    with muster.User() as me:                       # the broker of instance "default"
        for s in me.list():
            print(s.id, s.kind, s.payload, f"{s.in_use}/{s.quota}")
        with me.request("T1/target") as session:    # a tracker's target
            for update in session.updates(timeout=5):
                print(update.seq, update.value)

A system::

    door = muster.System("door")

    @door.command_service("open", payload="text")
    def open_door(session, value):
        session.working("opening")
        door.after(2.0, lambda: session.done("open"))

    door.run()

Everything underneath is muster's Rust client and runtime (`muster._native`): the
same protocol, liveness, re-registration and broker takeovers as a Rust program.
"""

from __future__ import annotations

from ._errors import (Closed, InternalError, MusterError, NoBroker, PayloadError, Refused,
                      SessionEnded, UnknownService)
from ._payloads import Goal2d, Open, Pose2d, Track2d, Twist, Value
from ._system import Service as SystemService
from ._system import System, SystemSession
from ._user import Link, Service, Session, Status, Update, User

__version__ = "0.1.0"

__all__ = [
    "User", "Session", "Service", "Update", "Status", "Link",
    "System", "SystemSession", "SystemService",
    "Pose2d", "Goal2d", "Twist", "Track2d", "Open", "Value",
    "MusterError", "NoBroker", "UnknownService", "PayloadError", "InternalError", "Closed",
    "Refused", "SessionEnded",
]
