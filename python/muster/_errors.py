"""muster's exceptions: all are `MusterError`s."""

from __future__ import annotations

from ._native import Closed, InternalError, MusterError, NoBroker, PayloadError, UnknownService


class Refused(MusterError):
    """The broker (or the system) refused a request: `code` is stable for programs
    (unknown, withdrawn, quota_full, queue_full, system_gone, system_refused,
    already_pending, bad_request, by_operator), `reason` the broker's words."""

    def __init__(self, service: str, code: str, reason: str):
        super().__init__(f"{service} refused: {reason}")
        self.service = service
        self.code = code
        self.reason = reason


class SessionEnded(MusterError):
    """The session ended: `code` (by_user, by_system, withdrawn, peer_gone,
    duration_over) and `reason`."""

    def __init__(self, service: str, code: str, reason: str):
        super().__init__(f"session on {service} ended: {reason}")
        self.service = service
        self.code = code
        self.reason = reason


__all__ = ["MusterError", "NoBroker", "UnknownService", "PayloadError", "InternalError",
           "Closed", "Refused", "SessionEnded"]
