"""Byte spans of an S5 CPU through whichever S5 client reaches it: AS511, S5-LAN, FETCH/WRITE.

The S5-LAN and FETCH/WRITE servers ask their :class:`~plcstack.sim.s5store.S5Store` for byte
spans of a target (a DB/DX body from DW0, an area, the peripheral bytes, absolute memory),
in PLC byte order. A back end turns such a span into requests of the client that reaches the
PLC, and each refusal of the client into an :class:`~plcstack.sim.s5store.S5Fault`:

* AS511 (a programming port): blocks through B_INFO and their addresses, areas through the
  system parameters, absolute memory directly;
* S5-LAN (a module): blocks as data words, M/I/Q as bytes, T and C as words; no absolute or
  system data (answered "area does not exist");
* FETCH/WRITE (a CP): every ORG as it is, DB starts in the CP's unit.

Peripheral bytes exist as such only on FETCH/WRITE; the others read the input image and write
the output image [R] (what the simulators do too). Nothing here queues: the store runs each
span in its turn on the PLC's connection.
"""

from __future__ import annotations

import struct
from abc import ABC, abstractmethod
from typing import Final

from plcstack.clients.as511 import AS511Client
from plcstack.clients.base import Client
from plcstack.clients.fetchwrite import MAX_JOB_BYTES, FetchWriteClient
from plcstack.clients.s5lan import S5LanClient
from plcstack.codecs.fetchwrite import Org
from plcstack.errors import (
    AddressError,
    ConnectFailed,
    PlcError,
    PlcErrorResponse,
)
from plcstack.s5address import S5Area
from plcstack.sim.s5memory import Area, BlockType
from plcstack.sim.s5store import (
    ABSOLUTE,
    PERIPHERAL,
    FaultKind,
    S5Fault,
    Target,
    describe_target,
)

__all__ = ["S5Backend", "backend_for"]

#: the areas every S5 client names, by the store's area
_S5_AREAS: Final[dict[Area, S5Area]] = {
    Area.INPUTS: S5Area.INPUTS,
    Area.OUTPUTS: S5Area.OUTPUTS,
    Area.FLAGS: S5Area.FLAGS,
    Area.TIMERS: S5Area.TIMERS,
    Area.COUNTERS: S5Area.COUNTERS,
}


class S5Backend(ABC):
    """Spans of one S5 CPU through ``client``; a refusal is an :class:`S5Fault`."""

    #: what the PLC's module answers, by its error code (the rest: refused)
    CODES: dict[int, FaultKind] = {}

    def __init__(self, client: Client) -> None:
        self.client = client

    @property
    def name(self) -> str:
        return self.client.name

    async def read(self, target: Target, offset: int, size: int) -> bytes:
        try:
            return await self._read(target, offset, size)
        except PlcError as exc:
            raise self.fault(exc, target, write=False) from None

    async def write(self, target: Target, offset: int, data: bytes) -> None:
        try:
            await self._write(target, offset, data)
        except PlcError as exc:
            raise self.fault(exc, target, write=True) from None

    @abstractmethod
    async def _read(self, target: Target, offset: int, size: int) -> bytes: ...

    @abstractmethod
    async def _write(self, target: Target, offset: int, data: bytes) -> None: ...

    def fault(self, exc: PlcError, target: Target, *, write: bool) -> S5Fault:
        """The fault a failure of the client stands for, with the client's own words."""
        text = str(exc)
        if isinstance(exc, AddressError):  # beyond the block's length or the area's size
            return S5Fault(FaultKind.TOO_SMALL, text)
        if isinstance(exc, PlcErrorResponse):
            kind = self.CODES.get(exc.code, FaultKind.PLC_REFUSED)
            # only a module's "timeout towards the PLC" leaves a write's fate open
            return S5Fault(kind, text, may_have_executed=write and kind is FaultKind.PLC_TIMEOUT)
        # no (valid) answer: a dead line or connection, a timeout, garbage. A write that was
        # sent may have executed; one refused by the client's backoff was not sent.
        sent = not isinstance(exc, ConnectFailed)
        return S5Fault(FaultKind.PLC_TIMEOUT, text, may_have_executed=write and sent)


def _no_area(target: Target, why: str) -> S5Fault:
    return S5Fault(FaultKind.NO_AREA, f"{describe_target(target)} {why}")


def _words(data: bytes) -> list[int]:
    """Big-endian words of PLC memory as ints."""
    return list(struct.unpack(f">{len(data) // 2}H", data))


def _pack(words: list[int]) -> bytes:
    return struct.pack(f">{len(words)}H", *words)


class As511Backend(S5Backend):
    """A CPU on its programming port: blocks by B_INFO, areas by the system parameters."""

    client: AS511Client

    async def _block(self, target: tuple[BlockType, int]) -> None:
        """Make sure a block's address is known; a NAK to B_INFO means the block is missing."""
        code, number = int(target[0]), target[1]
        if (code, number) in self.client.block_cache:
            return
        try:
            await self.client.block_info(code, number)
        except PlcErrorResponse as exc:
            raise S5Fault(FaultKind.NO_AREA, str(exc)) from None

    async def _read(self, target: Target, offset: int, size: int) -> bytes:
        client = self.client
        if isinstance(target, tuple):
            await self._block(target)
            return await client.read_block_bytes(int(target[0]), target[1], offset, size)
        if target == PERIPHERAL:
            target = Area.INPUTS
        if isinstance(target, Area):
            return await client.read_bytes(_area(target), offset, size)
        return await client.read_absolute(offset, size)

    async def _write(self, target: Target, offset: int, data: bytes) -> None:
        client = self.client
        if isinstance(target, tuple):
            await self._block(target)
            await client.write_block_bytes(int(target[0]), target[1], offset, data)
            return
        if target == PERIPHERAL:
            target = Area.OUTPUTS
        if isinstance(target, Area):
            await client.write_bytes(_area(target), offset, data)
        else:
            await client.write_absolute(offset, data)


def _area(area: Area) -> S5Area:
    try:
        return _S5_AREAS[area]
    except KeyError:
        raise _no_area(area, "is not served through this gateway") from None


class S5LanBackend(S5Backend):
    """An S5-LAN-LINK module: blocks as data words, M/I/Q bytes, T and C words."""

    client: S5LanClient
    #: S5-LAN ``Err`` values (A.7)
    CODES = {2: FaultKind.NO_AREA, 3: FaultKind.TOO_SMALL, 9: FaultKind.PLC_TIMEOUT}

    async def _read(self, target: Target, offset: int, size: int) -> bytes:
        client = self.client
        if isinstance(target, tuple):
            # bytes of the body through its data words, in PLC order (DL n = high byte of DW n)
            letters = "DB" if target[0] is BlockType.DB else "DX"
            return bytes(await client.read(f"{letters}{target[1]}.DBB{offset}", size))
        if target == PERIPHERAL:
            target = Area.INPUTS
        if not isinstance(target, Area) or target is Area.SYSTEM:
            raise _no_area(target, "does not exist behind an S5-LAN module")
        if target in (Area.TIMERS, Area.COUNTERS):
            return _pack(await client.read(f"{target.value}{offset // 2}", size // 2))
        return bytes(await client.read(f"{target.value}B{offset}", size))

    async def _write(self, target: Target, offset: int, data: bytes) -> None:
        client = self.client
        if isinstance(target, tuple):
            letters = "DB" if target[0] is BlockType.DB else "DX"
            if offset % 2 or len(data) % 2:
                raise _no_area(target, "is written through S5-LAN in whole data words only")
            await client.write(f"{letters}{target[1]}.DW{offset // 2}", _words(data))
            return
        if target == PERIPHERAL:
            target = Area.OUTPUTS
        if not isinstance(target, Area) or target is Area.SYSTEM:
            raise _no_area(target, "does not exist behind an S5-LAN module")
        if target in (Area.TIMERS, Area.COUNTERS):
            await client.write(f"{target.value}{offset // 2}", _words(data))
        else:
            await client.write(f"{target.value}B{offset}", list(data))


#: FETCH/WRITE ORG of each target kind, and whether its unit is the word
_ORGS: Final[dict[Area | str, tuple[int, bool]]] = {
    Area.FLAGS: (Org.MB, False),
    Area.INPUTS: (Org.EB, False),
    Area.OUTPUTS: (Org.AB, False),
    Area.COUNTERS: (Org.ZB, True),
    Area.TIMERS: (Org.TB, True),
    Area.SYSTEM: (Org.BS, True),
    PERIPHERAL: (Org.PB, False),
    ABSOLUTE: (Org.AS, True),
}


class FetchWriteBackend(S5Backend):
    """A CP with FETCH/WRITE: every span as the ORG it is, in jobs of the client's size."""

    client: FetchWriteClient
    #: FETCH/WRITE error field (C.6.4)
    CODES = {
        1: FaultKind.PLC_REFUSED,
        2: FaultKind.NO_AREA,
        3: FaultKind.TOO_SMALL,
        4: FaultKind.PLC_TIMEOUT,
    }

    def _job(self, target: Target, offset: int) -> tuple[int, int, int, bool]:
        """``(ORG, DBNR, start, word unit)`` of a span at byte ``offset`` of ``target``."""
        if isinstance(target, tuple):
            block = Org.DB if target[0] is BlockType.DB else Org.DX
            if offset % 2:
                raise _no_area(target, "starts at a data word through FETCH/WRITE")
            start = offset if self.client.db_start == "byte" else offset // 2
            return block, target[1], start, True
        org, words = _ORGS[target]
        # absolute memory: the start is a byte address; timers, counters, BS: their number
        start = offset // 2 if words and target != ABSOLUTE else offset
        return org, 0, start, words

    async def _read(self, target: Target, offset: int, size: int) -> bytes:
        out = bytearray()
        while len(out) < size:
            at = offset + len(out)
            n = min(MAX_JOB_BYTES, size - len(out))
            org, db, start, words = self._job(target, at)
            out += await self.client.fetch_org(org, db, start, n // 2 if words else n)
        return bytes(out)

    async def _write(self, target: Target, offset: int, data: bytes) -> None:
        done = 0
        while done < len(data):
            org, db, start, _ = self._job(target, offset + done)
            chunk = data[done : done + MAX_JOB_BYTES]
            try:
                await self.client.write_org(org, db, start, chunk)
            except PlcError as exc:
                if done:
                    exc.message += f" (the first {done} of {len(data)} bytes were written)"
                raise
            done += len(chunk)


def backend_for(client: Client) -> S5Backend:
    """The back end of an S5 client; an :class:`AddressError` for any other PLC."""
    if isinstance(client, AS511Client):
        return As511Backend(client)
    if isinstance(client, S5LanClient):
        return S5LanBackend(client)
    if isinstance(client, FetchWriteClient):
        return FetchWriteBackend(client)
    raise AddressError(
        f"{client.name}: an S5 face needs an S5 PLC (as511:, as511+tcp:, s5lan: or fetchwrite:)"
    )
