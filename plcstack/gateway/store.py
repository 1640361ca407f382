"""An S5 PLC's one connection as the :class:`~plcstack.sim.s5store.S5Store` that the S5-LAN and
FETCH/WRITE servers execute their requests on: the S5 faces of any S5 PLC.

The PLC is reached by whichever S5 client the poller (or the gateway command) holds: an AS511
port, an S5-LAN module, a FETCH/WRITE CP (:mod:`plcstack.gateway.s5backends` translates). Its
connection is shared with the poll through one
:class:`~plcstack.clients.share.SharedConnection`, which queues the requests fairly, refuses
them when too many wait, and never sends one that waited past its limit. This store adds what
the S5 faces need on top:

* the write allow-list (nothing writable until configured), checked before anything queues;
* every write attempt told to ``on_write`` (:class:`~plcstack.gateway.record.FaceWrite`)
  before its client is answered, with the value that was there before when ``read_previous``
  asks for it (read in the same turn of the connection, so nothing comes between);
* a write acknowledged only once the PLC acknowledged it;
* an optional read cache (``cache_max_age``, default off): a read is served from a cached span
  of the same block or area that covers it and is younger than ``cache_max_age``; every write
  through the store drops what it may have changed. The cache does not see changes made by
  the PLC program itself: that is what the age limit is for, and why it is off by default.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Final, TypeVar

from plcstack.clients.share import QueueFull, SharedConnection, TurnRefused
from plcstack.errors import AddressError
from plcstack.gateway.allow import WriteAllowList
from plcstack.gateway.record import FaceWrite, WriteHook
from plcstack.gateway.s5backends import S5Backend, backend_for
from plcstack.sim.s5store import PERIPHERAL, FaultKind, S5Fault, Target, describe_target

__all__ = ["ClientStore", "GatewayStats"]

log = logging.getLogger("plcstack.gateway")

T = TypeVar("T")

#: cached spans kept per block or area (most recent first); bounds the cache's memory
CACHE_SPANS_PER_TARGET: Final = 8


@dataclass
class GatewayStats:
    """Counters of one store; ``line_reads``/``line_writes`` are operations on the PLC's
    connection (its AS511 line, S5-LAN or FETCH/WRITE connection)."""

    reads: int = 0
    writes: int = 0
    line_reads: int = 0
    line_writes: int = 0
    cache_hits: int = 0
    busy: int = 0
    expired: int = 0
    denied: int = 0
    failed: int = 0


@dataclass
class _Span:
    offset: int
    data: bytes
    at: float


class ClientStore:
    """:class:`S5Store` on the PLC behind ``share`` (see the module docstring)."""

    def __init__(
        self,
        share: SharedConnection,
        *,
        writable: WriteAllowList | None = None,
        cache_max_age: float | None = None,
        read_previous: bool = False,
        on_write: WriteHook | None = None,
    ) -> None:
        if cache_max_age is not None and not 0 < cache_max_age < float("inf"):
            raise AddressError(f"cache_max_age {cache_max_age} must be positive seconds or off")
        self.share = share
        self.backend: S5Backend = backend_for(share.client)
        self.writable = writable if writable is not None else WriteAllowList()
        self.cache_max_age = cache_max_age
        self.read_previous = read_previous
        #: told of every write attempt once its outcome is known, before its client is answered
        self.on_write = on_write
        self.stats = GatewayStats()
        self._cache: dict[Target, list[_Span]] = {}

    @property
    def name(self) -> str:
        """The PLC, as the log names it."""
        return self.share.name

    # -- S5Store ------------------------------------------------------------------------------
    async def read(
        self, target: Target, offset: int, size: int, *, peer: str | None = None
    ) -> bytes:
        self.stats.reads += 1
        cached = self._cached(target, offset, size)
        if cached is not None:
            self.stats.cache_hits += 1
            return cached

        async def job() -> bytes:
            again = self._cached(target, offset, size)  # queued behind an identical read
            if again is not None:
                self.stats.cache_hits += 1
                return again
            self.stats.line_reads += 1
            try:
                data = await self.backend.read(target, offset, size)
            except S5Fault:
                self.stats.failed += 1
                raise
            self._remember(target, offset, data)
            return data

        return await self._run(peer, job)

    async def write(
        self, target: Target, offset: int, data: bytes, *, peer: str | None = None
    ) -> None:
        self.stats.writes += 1
        data = bytes(data)
        where = f"{describe_target(target)}+{offset}"
        if not self.writable.allows(target):
            self.stats.denied += 1
            fault = S5Fault(
                FaultKind.WRITE_DENIED,
                f"writing {describe_target(target)} is not allowed (writable: {self.writable})",
            )
            self._record(where, data, None, peer, fault)
            raise fault
        started = False

        async def job() -> None:
            nonlocal started
            started = True
            previous: bytes | None = None
            try:
                if self.read_previous and target != PERIPHERAL:
                    previous = await self._previous(target, offset, len(data))
                self.stats.line_writes += 1
                try:
                    await self.backend.write(target, offset, data)
                finally:
                    # even a failed write may have changed memory ("may or may not")
                    self._forget(target)
            except S5Fault as fault:
                self.stats.failed += 1
                if fault.may_have_executed:
                    log.warning("%s: write %s not confirmed: %s", self.name, where, fault)
                self._record(where, data, previous, peer, fault)
                raise
            except BaseException:  # stopped while it ran: its outcome is unknown
                self._record(where, data, previous, peer, None, "cancelled", sent=True)
                raise
            self._record(where, data, previous, peer, None)

        try:
            await self._run(peer, job)
        except S5Fault as fault:
            if not started:  # refused before its turn: nothing was sent
                self._record(where, data, None, peer, fault)
            raise
        except asyncio.CancelledError:
            if not started:  # its client went away while it waited: skipped, never sent
                self._record(where, data, None, peer, None, "cancelled", sent=False)
            raise

    async def _previous(self, target: Target, offset: int, size: int) -> bytes:
        """What the write is about to replace (its turn's first request)."""
        try:
            return await self.backend.read(target, offset, size)
        except S5Fault as fault:
            raise S5Fault(
                fault.kind,
                f"reading the value before the write failed, so the write was not sent: {fault}",
            ) from None

    async def _run(self, peer: str | None, job: Callable[[], Awaitable[T]]) -> T:
        """``job`` in its turn on the PLC's connection; a refusal of the queue as a fault."""
        source: object = peer if peer is not None else asyncio.current_task()
        try:
            return await self.share.run(source, job)
        except TurnRefused as exc:
            if isinstance(exc, QueueFull):
                self.stats.busy += 1
                raise S5Fault(FaultKind.BUSY, str(exc)) from None
            self.stats.expired += 1
            raise S5Fault(FaultKind.PLC_TIMEOUT, str(exc)) from None

    def _record(
        self,
        where: str,
        data: bytes,
        previous: bytes | None,
        peer: str | None,
        fault: S5Fault | None,
        result: str | None = None,
        *,
        sent: bool = True,
    ) -> None:
        hook = self.on_write
        if hook is None:
            return
        if fault is not None:
            code, may, message = (
                fault.kind.value,
                fault.may_have_executed,
                f"write {where}: {fault}",
            )
        elif result is None:
            code, may = "ok", True
            message = f"write {where} ({len(data)} bytes): confirmed by the PLC"
        else:
            code, may = result, sent
            message = f"write {where} ({len(data)} bytes): the client went away" + (
                "; the write was under way, its outcome is unknown" if sent else "; not sent"
            )
        hook(
            FaceWrite(
                "s5",
                peer,
                where,
                list(data),
                None if previous is None else list(previous),
                code,
                may,
                message,
            )
        )

    # -- cache --------------------------------------------------------------------------------
    def _cached(self, target: Target, offset: int, size: int) -> bytes | None:
        if self.cache_max_age is None:
            return None
        oldest = time.monotonic() - self.cache_max_age
        for span in self._cache.get(target, ()):
            if span.at >= oldest and span.offset <= offset:
                start = offset - span.offset
                if start + size <= len(span.data):
                    return span.data[start : start + size]
        return None

    def _remember(self, target: Target, offset: int, data: bytes) -> None:
        if self.cache_max_age is None:
            return
        spans = self._cache.setdefault(target, [])
        spans.insert(0, _Span(offset, data, time.monotonic()))
        del spans[CACHE_SPANS_PER_TARGET:]

    def _forget(self, target: Target) -> None:
        """Drop what a write to ``target`` may have changed (absolute memory: everything; the
        peripheral bytes: the image behind them too)."""
        if isinstance(target, str):
            self._cache.clear()
        else:
            self._cache.pop(target, None)
            self._cache.pop("absolute", None)
