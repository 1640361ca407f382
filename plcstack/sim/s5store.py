"""The async memory interface behind the S5-LAN and FETCH/WRITE servers, and its in-memory form.

The S5-LAN module of the seed documents is, in hardware, an AS511 gateway: it answers network
requests from the CPU's memory, which it reaches over the programming port. plcstack has one
server implementation per protocol (``plcstack.sim.s5lan``, ``plcstack.sim.fetchwrite``), and
each executes its requests on an :class:`S5Store`:

* :class:`MemoryStore` - the simulated CPU image (:class:`~plcstack.sim.s5memory.S5Memory`);
* ``plcstack.gateway.As511Store`` - a real CPU behind one AS511 link.

So the simulators and the gateway cannot drift apart: the same codec, the same request checks
and the same error mapping answer both.

A store refuses an access with :class:`S5Fault`, whose :class:`FaultKind` says *what* went wrong
in protocol-neutral terms; each protocol maps the kind onto its own error value (``FAULT_CODES``,
documented in ``docs/gateway.md``).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import Final, Literal, Protocol

from plcstack.sim.s5memory import Area, BlockType, S5AccessError, S5Memory

__all__ = [
    "ABSOLUTE",
    "FAULT_CODES",
    "PERIPHERAL",
    "BlockRef",
    "FaultKind",
    "MemoryStore",
    "S5Fault",
    "S5Store",
    "Target",
    "describe_target",
    "memory_of",
    "resolve_store",
]

#: a data block: (DB or DX, number)
BlockRef = tuple[BlockType, int]
#: the whole 64 KiB address space (FETCH/WRITE ORG 'AS')
ABSOLUTE: Final = "absolute"
#: the peripheral bytes (FETCH/WRITE ORG 'PB'): input modules read, output modules written. [R]
#: Where only the process images can be reached (a memory image, an AS511 port, an S5-LAN
#: module), a read sees the input image and a write goes to the output image.
PERIPHERAL: Final = "peripheral"
#: what a request touches: a block, a byte area (I/Q/M/T/C/BS), the peripheral bytes or
#: absolute memory
Target = BlockRef | Area | Literal["absolute", "peripheral"]


class FaultKind(enum.Enum):
    """Why a store refused an access, independent of the network protocol that asked."""

    #: the block or area does not exist in the PLC (missing DB, DB 0)
    NO_AREA = "no_area"
    #: the block or area is shorter than the request
    TOO_SMALL = "too_small"
    #: the PLC did not answer: dead line, no reply, connection lost, or the request waited in
    #: the gateway's queue past its deadline and was therefore not executed
    PLC_TIMEOUT = "plc_timeout"
    #: the PLC refused the operation (DLE NAK other than "block missing")
    PLC_REFUSED = "plc_refused"
    #: the gateway's write allow-list does not include this area or block
    WRITE_DENIED = "write_denied"
    #: the gateway's request queue is full
    BUSY = "busy"


#: kind -> (S5-LAN ``Err`` (A.7), FETCH/WRITE error field (C.6.4)); see ``docs/gateway.md``
FAULT_CODES: Final[dict[FaultKind, tuple[int, int]]] = {
    FaultKind.NO_AREA: (2, 0x02),
    FaultKind.TOO_SMALL: (3, 0x03),
    FaultKind.PLC_TIMEOUT: (9, 0x04),
    # A.7 has no "refused" value; 9 (module<->PLC communication failed) is the closest truth:
    # the request did not complete in the PLC. FETCH/WRITE 01: area cannot be read/written.
    FaultKind.PLC_REFUSED: (9, 0x01),
    # A.7 has no access error either; 6 (the module refused the request) is what the module
    # does, without asking the PLC. FETCH/WRITE 01: area cannot be written.
    FaultKind.WRITE_DENIED: (6, 0x01),
    FaultKind.BUSY: (9, 0x04),
}


class S5Fault(Exception):
    """An access a store refused; ``kind`` chooses the protocol's error value.

    ``may_have_executed``: for a write, whether it may have reached the PLC all the same (a
    timeout after it was sent); false when it certainly did not (refused before sending, or
    answered with an error code)."""

    def __init__(self, kind: FaultKind, message: str, *, may_have_executed: bool = False) -> None:
        self.kind = kind
        self.may_have_executed = may_have_executed
        super().__init__(message)

    @property
    def s5lan_err(self) -> int:
        return FAULT_CODES[self.kind][0]

    @property
    def fetchwrite_error(self) -> int:
        return FAULT_CODES[self.kind][1]


def describe_target(target: Target) -> str:
    """``DB10``, ``M``, ``absolute``: for messages and logs."""
    if isinstance(target, tuple):
        return f"{target[0].name}{target[1]}"
    if isinstance(target, Area):
        return target.value
    return "PB" if target == PERIPHERAL else "absolute"


class S5Store(Protocol):
    """What a server needs of a CPU: byte spans of blocks, areas and absolute memory.

    Offsets and sizes are bytes; block offsets count from data word 0 (the body, after the
    10-byte header); T and C hold 2 bytes per timer/counter. Data are in PLC byte order
    (big-endian words). A refused access raises :class:`S5Fault`; nothing else may escape.
    ``write`` returns only once the CPU has taken the data. ``peer`` is the network client that
    asked (``host:port``: a gateway queues each client's requests in a line of its own and
    audits its writes; None: unknown).
    """

    async def read(
        self, target: Target, offset: int, size: int, *, peer: str | None = None
    ) -> bytes: ...

    async def write(
        self, target: Target, offset: int, data: bytes, *, peer: str | None = None
    ) -> None: ...


_ACCESS_KINDS: Final = {2: FaultKind.NO_AREA, 3: FaultKind.TOO_SMALL}


class MemoryStore:
    """:class:`S5Store` over the simulated CPU image; ``memory`` is live for tests."""

    def __init__(self, memory: S5Memory) -> None:
        self.memory = memory

    async def read(
        self, target: Target, offset: int, size: int, *, peer: str | None = None
    ) -> bytes:
        try:
            if isinstance(target, tuple):
                return self.memory.read_block(target[0], target[1], offset, size)
            if isinstance(target, Area):
                return self.memory.read_area(target, offset, size)
            if target == PERIPHERAL:
                return self.memory.read_area(Area.INPUTS, offset, size)
            return self.memory.read_absolute(offset, size)
        except S5AccessError as exc:
            raise S5Fault(_ACCESS_KINDS.get(exc.code, FaultKind.NO_AREA), str(exc)) from None

    async def write(
        self, target: Target, offset: int, data: bytes, *, peer: str | None = None
    ) -> None:
        """Into the image; ``peer`` (who asked) is not kept: a simulator audits nothing."""
        try:
            if isinstance(target, tuple):
                self.memory.write_block(target[0], target[1], offset, data)
            elif isinstance(target, Area):
                self.memory.write_area(target, offset, data)
            elif target == PERIPHERAL:
                self.memory.write_area(Area.OUTPUTS, offset, data)
            else:
                self.memory.write_absolute(offset, data)
        except S5AccessError as exc:
            raise S5Fault(_ACCESS_KINDS.get(exc.code, FaultKind.NO_AREA), str(exc)) from None


def resolve_store(
    memory: S5Memory | None, store: S5Store | None, default: Callable[[], S5Memory]
) -> S5Store:
    """What a server's ``start(memory=, store=)`` executes on: the given store (the gateway's
    real CPU), else the given or the default memory image."""
    if store is not None and memory is not None:
        raise ValueError("give a memory image or a store, not both")
    if store is not None:
        return store
    return MemoryStore(memory if memory is not None else default())


def memory_of(store: S5Store, server: str) -> S5Memory:
    """The simulated CPU image behind ``store``; a gateway's store has none."""
    if not isinstance(store, MemoryStore):
        raise TypeError(f"this {server} server executes on a gateway store, not a memory image")
    return store.memory
