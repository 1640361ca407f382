"""An in-memory Client for poller tests: deterministic, no sockets, failure modes on demand.

Addresses are ``LETTERS`` + decimal index: ``D100`` (16-bit words), ``M5`` (bits), ``B10`` (bytes).
It goes through the real :class:`Client` base for locking, reconnect and backoff, with a transport
that "connects" unless the fake PLC is switched off.
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import Hashable, Sequence
from typing import Any, Self

from plcstack.clients.base import Client
from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    LocalProtocolError,
    PlcErrorResponse,
    PlcTimeout,
)
from plcstack.transports.backoff import Backoff
from plcstack.transports.base import Transport
from plcstack.url import PlcUrl

_ADDRESS = re.compile(r"([A-Z]+)(\d+)$")
BITS = {"D": 16, "M": 1, "B": 8, "W": 16}
SIZE = {"D": 1000, "M": 2048, "B": 256, "W": 1000}


class FakeTransport(Transport):
    def __init__(self, owner: FakeClient) -> None:
        self.owner = owner
        self.peer = "fake"
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    async def open(self, timeout: float | None) -> None:
        if not self.owner.up:
            raise ConnectFailed("cannot connect to fake: connection refused")
        self._open = True

    def write(self, data: bytes) -> None:
        raise NotImplementedError

    async def read(self) -> bytes:
        raise NotImplementedError

    def abort(self) -> None:
        self._open = False


class FakeClient(Client):
    def __init__(
        self,
        name: str = "fake://plc",
        *,
        max_points: dict[str, int] | None = None,
        timeout: float = 0.5,
        merge: bool = True,
        backoff: Backoff | None = None,
    ) -> None:
        super().__init__(
            name,
            FakeTransport(self),
            timeout=timeout,
            connect_timeout=timeout,
            backoff=backoff or Backoff(initial=0.01, maximum=0.02, jitter=0.0),
        )
        self.memory: dict[str, dict[int, int | bool]] = {a: {} for a in BITS}
        self.limits = {"D": 64, "M": 256, "B": 200, "W": 64, **(max_points or {})}
        self.merge = merge
        self.up = True
        self.delay = 0.0
        self.gate: asyncio.Event | None = None  # when set, reads wait for it
        self.reads: list[tuple[str, int]] = []
        self.writes: list[tuple[str, list[int | bool]]] = []
        self.in_flight = 0
        self.max_in_flight = 0
        self.reject_above: dict[str, int] = {}  # area -> first index that answers an error code

    @classmethod
    def from_url(cls, url: PlcUrl, **options: Any) -> Self:
        return cls(url.raw)

    # -- addresses ----------------------------------------------------------------------------
    def _parse(self, address: str) -> tuple[str, int]:
        m = _ADDRESS.match(address)
        if m is None or m.group(1) not in BITS:
            raise AddressError(f"bad address {address!r}")
        area, index = m.group(1), int(m.group(2))
        if index >= SIZE[area]:
            raise AddressError(f"{address} is beyond {area}{SIZE[area] - 1}")
        return area, index

    def locate(self, address: str, count: int = 1) -> tuple[Hashable, int]:
        if not self.merge:
            raise NotImplementedError
        return self._parse(address)

    def address_at(self, area: Hashable, index: int) -> str:
        if not self.merge:
            raise NotImplementedError
        return f"{area}{index}"

    def max_points(self, area: Hashable) -> int:
        if not self.merge:
            raise NotImplementedError
        return self.limits[str(area)]

    def point_bits(self, area: Hashable) -> int:
        return BITS[str(area)]

    # -- switches -----------------------------------------------------------------------------
    def kill(self) -> None:
        """Power off: the open connection drops, connects are refused."""
        self.up = False
        self.transport.abort()

    def revive(self) -> None:
        self.up = True

    # -- I/O ----------------------------------------------------------------------------------
    async def _io(self, what: str) -> None:
        await self._ensure_open(what)
        self.stats.requests += 1
        self.in_flight += 1
        self.max_in_flight = max(self.max_in_flight, self.in_flight)
        try:
            async with asyncio.timeout(self.timeout):
                if self.delay:
                    await asyncio.sleep(self.delay)
                if self.gate is not None:
                    await self.gate.wait()
                else:
                    await asyncio.sleep(0)
        except TimeoutError:
            self.stats.errors += 1
            self.drop()
            raise PlcTimeout(
                f"no answer within {self.timeout:g} s", plc=self.name, request=what
            ) from None
        finally:
            self.in_flight -= 1
        if not self.up or not self.transport.is_open:
            self.stats.errors += 1
            self.drop()
            raise ConnectionLost("connection reset by peer", plc=self.name, request=what)

    async def read(self, address: str, count: int = 1) -> list[int] | list[bool]:
        area, index = self._parse(address)
        what = f"read {address} x{count}"
        if count > self.limits[area]:
            raise LocalProtocolError(f"count {count} over the frame limit", plc=self.name)
        async with self._lock:
            await self._io(what)
            self.reads.append((address, count))
            first_bad = self.reject_above.get(area)
            if first_bad is not None and index + count > first_bad:
                self.stats.errors += 1
                raise PlcErrorResponse(0x57, "points beyond the device range", plc=self.name)
            mem = self.memory[area]
            if BITS[area] == 1:
                return [bool(mem.get(index + k, False)) for k in range(count)]
            return [int(mem.get(index + k, 0)) for k in range(count)]

    async def write(self, address: str, values: Sequence[int] | Sequence[bool]) -> None:
        area, index = self._parse(address)
        async with self._lock:
            await self._io(f"write {address}")
            self.writes.append((address, list(values)))
            for k, v in enumerate(values):
                self.memory[area][index + k] = v
