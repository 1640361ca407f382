"""The native faces (``[[gateway]]``) of a ``plcstack poll`` or ``plcstack gateway`` run, and the
write record they share: each face write goes to the run's one write path (log and audit, ``source``
``gateway``)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

from plcstack.clients.base import Client
from plcstack.gateway.faces import FaceSettings, GatewayFaces
from plcstack.gateway.record import FaceWrite
from plcstack.north.writes import WritePath, WriteResult

__all__ = ["face_written", "gateway_faces"]


def face_written(writes: WritePath, plc: str, write: FaceWrite) -> None:
    """Log and audit one face write through the run's write path (``source`` ``gateway``, the
    face client's address, the address and value, the value before where known)."""
    result = WriteResult(write.ok, write.result, write.message, write.may_have_executed)
    writes.record(
        "gateway",
        None,
        plc,
        write.address,
        write.value,
        result,
        peer=write.peer,
        previous=write.previous,
    )


def gateway_faces(
    faces: Sequence[FaceSettings],
    client_of: Callable[[str], Client],
    writes: WritePath,
    *,
    cache_max_age: float | None = None,
) -> GatewayFaces:
    """The faces of a run on the PLCs' clients (``client_of``: the poller's, or the one
    ``plcstack gateway`` holds), each write through ``writes``; the value before a write is
    read in its turn when the run keeps an audit."""
    return GatewayFaces(
        faces,
        client_of,
        cache_max_age=cache_max_age,
        read_previous=writes.audit is not None,
        on_write=functools.partial(face_written, writes),
    )
