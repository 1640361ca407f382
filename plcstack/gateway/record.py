"""What a face tells of each write attempt of its network clients, for the log and the audit.

Every native face (S5-LAN, FETCH/WRITE, E71) writes through the PLC's one connection on its
own path, by address rather than by tag; whoever runs the faces hands each :class:`FaceWrite`
to the one write path of the north side (``WritePath.record``), which logs and audits it like
any other write (``source`` ``gateway``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["FaceWrite", "WriteHook"]


@dataclass(frozen=True, slots=True)
class FaceWrite:
    """One write attempt, once its outcome is known and before its client is answered.

    ``address`` is where it went, in the face's terms (``DB4+2``: byte 2 of DB4's body;
    ``D100``); ``value`` what was written (bytes of an S5 area as ints, E71 words as ints, E71
    bits as bools), ``previous`` what was there just before (read in the same turn of the
    connection, when the runner asks for it; None: not known). ``result`` is ``ok`` or why not
    (``write_denied``, ``busy``, ``plc_timeout``, ...); ``may_have_executed`` is false only
    when the PLC certainly did not execute it; ``peer`` is the client's ``host:port``.
    """

    face: str
    peer: str | None
    address: str
    value: list[int] | list[bool]
    previous: list[int] | list[bool] | None
    result: str
    may_have_executed: bool
    message: str

    @property
    def ok(self) -> bool:
        return self.result == "ok"


#: told of every write attempt (see :class:`FaceWrite`)
WriteHook = Callable[[FaceWrite], None]
