"""Payload values: the built-in types as dataclasses, open types as `Open`.

On the wire between Python and Rust a payload is its JSON form, the one
`muster user --json` prints and `muster user request --input` reads:
``{"type": "goal2d", "x": 1.0, "y": 2.0}``, a string for `text`, a number for
`scalar`, and ``{"type": NAME, "value": {...}}`` for an open type.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Optional, Tuple, Union


@dataclass(frozen=True)
class Pose2d:
    """A position and heading in the world frame (metres, radians)."""

    x: float
    y: float
    theta: float = 0.0


@dataclass(frozen=True)
class Goal2d:
    """A goal position in the world frame (metres)."""

    x: float
    y: float


@dataclass(frozen=True)
class Twist:
    """A velocity command: forward speed (m/s) and turn rate (rad/s)."""

    v: float
    w: float


@dataclass(frozen=True)
class Track2d:
    """A tracked target: position, velocity, uncertainty, who sees it, whether lost."""

    x: float
    y: float
    vx: float = 0.0
    vy: float = 0.0
    sigma: float = 0.0
    age: float = 0.0
    seen_by: Tuple[str, ...] = ()
    lost: bool = False


@dataclass(frozen=True)
class Open:
    """A sample of an open payload type (a ROS 2 message, a JSON document).

    ``value`` is the sample decoded by the service's schema (dicts and lists);
    ``data`` holds the raw bytes when it could not be decoded (``error`` says why).
    """

    type: str
    value: Any = None
    encoding: Optional[str] = None
    data: Optional[bytes] = None
    error: Optional[str] = None


Value = Union[Pose2d, Goal2d, Twist, Track2d, Open, float, int, str, dict]

_BUILTIN = {"pose2d": Pose2d, "goal2d": Goal2d, "twist": Twist}


def to_wire(value: Value) -> Any:
    """A value's JSON form. Raises TypeError for what is no payload."""
    if isinstance(value, bool):
        raise TypeError("a bool is no payload (scalar takes a number)")
    if isinstance(value, (int, float, str)):
        return value
    if isinstance(value, Open):
        return {"type": value.type, "value": value.value}
    if isinstance(value, Track2d):
        raise TypeError("track2d is data, not task input")
    for name, cls in _BUILTIN.items():
        if isinstance(value, cls):
            d = dataclasses.asdict(value)
            d["type"] = name
            return d
    if isinstance(value, dict):
        return value
    raise TypeError(f"{type(value).__name__} is no payload: give a muster payload class, "
                    "a number, a string, or a dict naming its 'type'")


def from_wire(j: Any) -> Value:
    """A value from its JSON form, as the Rust side gives it."""
    t = j.get("type") if isinstance(j, dict) else None
    if t == "scalar":
        return float(j["value"])
    if t == "text":
        return j["text"]
    if t in _BUILTIN:
        cls = _BUILTIN[t]
        return cls(**{f.name: j[f.name] for f in dataclasses.fields(cls)})
    if t == "track2d":
        return Track2d(x=j["x"], y=j["y"], vx=j["vx"], vy=j["vy"], sigma=j["sigma"],
                       age=j["age"], seen_by=tuple(j.get("seen_by") or ()), lost=j["lost"])
    if t is not None:
        data = bytes.fromhex(j["hex"]) if "hex" in j else None
        return Open(type=t, value=j.get("value"), encoding=j.get("encoding"), data=data,
                    error=j.get("error"))
    return j


__all__ = ["Pose2d", "Goal2d", "Twist", "Track2d", "Open", "Value", "to_wire", "from_wire"]
