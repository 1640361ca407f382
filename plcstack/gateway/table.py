"""``[[gateway]]``: the native faces of a configuration file, read and checked.

:func:`parse_gateway` reads one table into a :class:`~plcstack.gateway.faces.FaceSettings`
(errors at the key's line); :func:`check_faces` checks them against the file's PLCs once those
are read (a face names a PLC of the file that it can stand in front of, no two faces listen on
one address, the faces of one PLC agree on its queue).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final, Literal

from plcstack.checks import Listen, Table
from plcstack.errors import AddressError, ConfigError
from plcstack.gateway.faces import DEFAULT_CONNECTIONS, PROTOCOLS, FaceSettings, Protocol
from plcstack.sim.base import DEFAULT_IDLE_TIMEOUT, Limits
from plcstack.transports.guard import parse_limits

__all__ = ["check_faces", "parse_gateway"]

#: the URL schemes of the PLCs each face can stand in front of
_SCHEMES: Final[dict[Protocol, tuple[str, ...]]] = {
    "s5lan": ("as511", "as511+tcp", "s5lan", "fetchwrite"),
    "fetchwrite": ("as511", "as511+tcp", "s5lan", "fetchwrite"),
    "as511": ("as511", "as511+tcp"),
    "e71": ("e71+tcp", "e71+udp"),
}
_TRANSPORTS: Final[tuple[Literal["tcp", "udp"], ...]] = ("tcp", "udp")
_TCP: Final[Literal["tcp", "udp"]] = "tcp"
_CODES: Final[tuple[Literal["binary", "ascii"], ...]] = ("binary", "ascii")
_BINARY: Final[Literal["binary", "ascii"]] = "binary"
_KEYS: Final = (
    "protocol",
    "listen",
    "plc",
    "writable",
    "mk",
    "transport",
    "code",
    "max_connections",
    "max_clients_per_host",
    "first_request_timeout",
    "idle_timeout",
    "queue",
    "max_wait",
)


def parse_gateway(table: Table) -> FaceSettings:
    """One ``[[gateway]]`` table: a native face of a PLC of the same file (which PLC exists,
    and that the face fits it, :func:`check_faces` says once the PLCs are read)::

        [[gateway]]
        protocol = "s5lan"           # "s5lan" | "fetchwrite" | "e71" | "as511"
        listen = "0.0.0.0:2000"
        plc = "kiln1"                # a [[plc]] of this file
        writable = "DB10-20, M"      # nothing writable by default
        # max_connections, max_clients_per_host, first_request_timeout, idle_timeout: the
        # face guard's limits (plcstack.transports.guard)
    """
    table.keys(_KEYS)
    if "protocol" not in table:
        raise table.error(None, f"needs protocol = one of {', '.join(PROTOCOLS)}")
    protocol = table.choice("protocol", PROTOCOLS[0], PROTOCOLS)
    if "listen" not in table:
        raise table.error(None, 'needs listen = "HOST:PORT" (where the face listens)')
    listen = table.listen(Listen("127.0.0.1", 0))
    writable = table.raw("writable", "")
    if not isinstance(writable, str):
        raise table.error("writable", f'must be a string such as "DB10-20, M", not {writable!r}')
    mk = table.boolean("mk", False)
    transport = table.choice("transport", _TCP, _TRANSPORTS)
    code = table.choice("code", _BINARY, _CODES)
    connections = (
        table.integer("max_connections", 1, 1, 4096) if "max_connections" in table else None
    )
    limits = None
    if any(k in table for k in ("max_clients_per_host", "first_request_timeout", "idle_timeout")):
        # the guard's keys; the face's clients at once are its max_connections
        total = connections or DEFAULT_CONNECTIONS[protocol]
        defaults = Limits(total, idle_timeout=DEFAULT_IDLE_TIMEOUT)
        limits = parse_limits(table, defaults, total_key="max_connections")
    queue = table.integer("queue", 1, 1, 65536) if "queue" in table else None
    max_wait = table.seconds("max_wait", 2.0, hi=3600.0) if "max_wait" in table else None
    plc = table.text("plc", "")
    try:  # what FaceSettings itself checks: writable's grammar, options of the wrong face
        return FaceSettings(
            protocol,
            listen.host,
            listen.port,
            plc,
            writable,
            mk=mk,
            transport=transport,
            code=code,
            max_connections=connections,
            limits=limits,
            queue=queue,
            max_wait=max_wait,
        )
    except AddressError as exc:
        key = next((k for k in ("writable", "mk", "transport", "code") if k in exc.message), None)
        message = exc.message
        if key is not None:  # said after the key: "[[gateway]] #2 mk ... is a FETCH/WRITE ..."
            message = message.removeprefix(f"{key}: ").removeprefix(f"{key} ")
        raise table.error(key, message) from None


def check_faces(faces: Sequence[FaceSettings], plcs: Sequence[tuple[str, str]]) -> None:
    """Every face names a PLC of the file (``(name, url)`` pairs) that it can stand in front
    of, no two faces listen on one address, and the faces of one PLC agree on its queue.
    :class:`ConfigError` naming the ``[[gateway]]`` (its key, for the line) otherwise."""
    urls = dict(plcs)
    listening: dict[tuple[str, str, int], int] = {}
    #: (PLC, key) -> (the value, the index of the face that gave it first)
    shared: dict[tuple[str, str], tuple[float, int]] = {}
    for index, face in enumerate(faces):
        where, path = f"[[gateway]] #{index + 1}", f"gateway[{index}]"
        url = urls.get(face.plc)
        if url is None:
            known = ", ".join(urls) or "none"
            raise ConfigError(
                f"{where} plc {face.plc!r} is no [[plc]] of this file (PLCs: {known})",
                key=f"{path}.plc",
            )
        scheme = url.partition("://")[0].lower()
        if scheme not in _SCHEMES[face.protocol]:
            raise ConfigError(
                f"{where}: a {face.protocol} face stands in front of "
                f"{' or '.join(_SCHEMES[face.protocol])} PLCs, and {face.plc} is {scheme}:",
                key=f"{path}.protocol",
            )
        at = (face.transport, face.host, face.port)
        if face.port and at in listening:
            raise ConfigError(
                f"{where} listens on {face.host}:{face.port} ({face.transport}) as "
                f"[[gateway]] #{listening[at] + 1} does",
                key=f"{path}.listen",
            )
        listening[at] = index
        for key, mine in (("queue", face.queue), ("max_wait", face.max_wait)):
            if mine is None:
                continue
            theirs, first = shared.setdefault((face.plc, key), (mine, index))
            if mine != theirs:
                raise ConfigError(
                    f"{where} {key} {mine:g} differs from [[gateway]] #{first + 1}'s "
                    f"({theirs:g}): the faces of {face.plc} share one queue",
                    key=f"{path}.{key}",
                )
