"""The real CPU behind one AS511 link, as the :class:`~plcstack.sim.s5store.S5Store` that the
S5-LAN and FETCH/WRITE servers execute their requests on.

Why a queue of its own (and not just the client's single flight): the programming port serves
one transaction at a time at 9600 baud, and many network clients share it. So

* every request waits in one bounded FIFO (``queue_size``); a full queue answers "busy" at once
  instead of letting latency grow without limit;
* each network connection has at most one request outstanding (neither protocol pipelines), so
  FIFO order is round-robin between clients: one busy client cannot starve the others;
* a request whose deadline (``max_wait`` after it arrived) passes while it waits is answered with
  the protocol's timeout error and is *not* executed late: its client has given up, and a write
  executed after the client was told "failed" would be a lie;
* a write is acknowledged to the network client only after the PLC acknowledged it.

An optional read cache (``cache_max_age``, default off) lets many clients polling the same data
cost one AS511 read: a read is served from a cached span of the same block or area that covers it
and is younger than ``cache_max_age``; every write through the gateway invalidates what it may
have changed. The cache does not see changes made by the PLC program itself: that is what the
age limit is for, and why the cache is off by default.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from plcstack.clients.as511 import AS511Client
from plcstack.errors import (
    AddressError,
    ConnectionLost,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
)
from plcstack.gateway.allow import WriteAllowList
from plcstack.s5address import S5Area
from plcstack.sim.s5memory import Area
from plcstack.sim.s5store import BlockRef, FaultKind, S5Fault, Target, describe_target

__all__ = ["As511Store", "GatewayStats"]

log = logging.getLogger("plcstack.gateway")

#: cached spans kept per block or area (most recent first); bounds the cache's memory
CACHE_SPANS_PER_TARGET: Final = 8

_CLIENT_AREAS: Final[dict[Area, S5Area]] = {
    Area.INPUTS: S5Area.INPUTS,
    Area.OUTPUTS: S5Area.OUTPUTS,
    Area.FLAGS: S5Area.FLAGS,
    Area.TIMERS: S5Area.TIMERS,
    Area.COUNTERS: S5Area.COUNTERS,
}


@dataclass
class GatewayStats:
    """Counters of one gateway; ``line_reads``/``line_writes`` are operations on the AS511 link."""

    reads: int = 0
    writes: int = 0
    line_reads: int = 0
    line_writes: int = 0
    cache_hits: int = 0
    busy: int = 0
    expired: int = 0
    denied: int = 0
    failed: int = 0
    queue_peak: int = 0


@dataclass
class _Job:
    target: Target
    offset: int
    size: int
    data: bytes | None  # None = read
    deadline: float
    future: asyncio.Future[bytes] = field(repr=False)


@dataclass
class _Span:
    offset: int
    data: bytes
    at: float


class As511Store:
    """:class:`S5Store` on an :class:`AS511Client`; start it with ``async with`` or ``aopen``."""

    def __init__(
        self,
        client: AS511Client,
        *,
        writable: WriteAllowList | None = None,
        queue_size: int = 32,
        max_wait: float = 2.0,
        cache_max_age: float | None = None,
    ) -> None:
        if queue_size < 1:
            raise AddressError(f"queue_size {queue_size} must be at least 1")
        if not 0 < max_wait < float("inf"):
            raise AddressError(f"max_wait {max_wait} must be a positive number of seconds")
        if cache_max_age is not None and not 0 < cache_max_age < float("inf"):
            raise AddressError(f"cache_max_age {cache_max_age} must be positive seconds or off")
        self.client = client
        self.writable = writable if writable is not None else WriteAllowList()
        self.queue_size = queue_size
        self.max_wait = max_wait
        self.cache_max_age = cache_max_age
        self.stats = GatewayStats()
        self._queue: collections.deque[_Job] = collections.deque()
        self._wakeup = asyncio.Event()
        self._worker: asyncio.Task[None] | None = None
        self._cache: dict[Target, list[_Span]] = {}
        #: told of every write attempt once its outcome is known, before the client is
        #: answered: ``(address, data, result, may_have_executed, message, peer)`` with
        #: ``result`` ``ok`` or the fault kind (``write_denied``, ``plc_timeout``, ...) and
        #: ``peer`` the network client's ``host:port``; the command line logs refusals and
        #: writes the audit line from it
        self.on_write: Callable[[str, bytes, str, bool, str, str | None], None] | None = None

    @property
    def worker(self) -> asyncio.Task[None] | None:
        """The one task that talks to the PLC (None before ``aopen``): a caller that runs the
        gateway watches it, so its failure ends the run instead of leaving requests waiting."""
        return self._worker

    # -- life cycle ---------------------------------------------------------------------------
    async def aopen(self) -> None:
        """Start the one task that talks to the PLC (the AS511 link connects on first use)."""
        if self._worker is None:
            self._worker = asyncio.create_task(self._work(), name="as511-gateway")

    async def aclose(self) -> None:
        worker, self._worker = self._worker, None
        if worker is not None:
            worker.cancel()
            await asyncio.gather(worker, return_exceptions=True)
        while self._queue:
            job = self._queue.popleft()
            if not job.future.done():
                job.future.set_exception(S5Fault(FaultKind.PLC_TIMEOUT, "gateway closed"))
        await self.client.aclose()

    # -- S5Store ------------------------------------------------------------------------------
    async def read(self, target: Target, offset: int, size: int) -> bytes:
        self.stats.reads += 1
        cached = self._cached(target, offset, size)
        if cached is not None:
            self.stats.cache_hits += 1
            return cached
        return await self._submit(target, offset, size, None)

    async def write(
        self, target: Target, offset: int, data: bytes, *, peer: str | None = None
    ) -> None:
        self.stats.writes += 1
        where = f"{describe_target(target)}+{offset}"
        if not self.writable.allows(target):
            self.stats.denied += 1
            fault = S5Fault(
                FaultKind.WRITE_DENIED,
                f"writing {describe_target(target)} is not allowed (writable: {self.writable})",
            )
            self._written(where, data, peer, fault)
            raise fault
        try:
            await self._submit(target, offset, len(data), bytes(data))
        except S5Fault as fault:
            self._written(where, data, peer, fault)
            raise
        except asyncio.CancelledError:
            # the client went away: a queued write is skipped, a running one completes
            self._written(where, data, peer, None, "cancelled")
            raise
        self._written(where, data, peer, None)

    def _written(
        self,
        where: str,
        data: bytes,
        peer: str | None,
        fault: S5Fault | None,
        result: str | None = None,
    ) -> None:
        hook = self.on_write
        if hook is None:
            return
        if fault is None:
            code = result or "ok"
            message = f"write {where} ({len(data)} bytes): " + (
                "confirmed by the PLC" if code == "ok" else "the client went away"
            )
            hook(where, bytes(data), code, True, message, peer)
            return
        text = str(fault)
        # only a timeout after the request went out may have executed; one that waited in the
        # queue past its deadline or met a stopped gateway was never sent
        sent = fault.kind is FaultKind.PLC_TIMEOUT and "not executed" not in text
        sent = sent and "gateway" not in text
        hook(where, bytes(data), fault.kind.value, sent, f"write {where}: {text}", peer)

    # -- queue --------------------------------------------------------------------------------
    async def _submit(self, target: Target, offset: int, size: int, data: bytes | None) -> bytes:
        if self._worker is None:
            raise S5Fault(FaultKind.PLC_TIMEOUT, "the gateway is not running")
        if len(self._queue) >= self.queue_size:
            self.stats.busy += 1
            raise S5Fault(FaultKind.BUSY, f"{self.queue_size} requests already wait for the PLC")
        loop = asyncio.get_running_loop()
        job = _Job(target, offset, size, data, loop.time() + self.max_wait, loop.create_future())
        self._queue.append(job)
        self.stats.queue_peak = max(self.stats.queue_peak, len(self._queue))
        self._wakeup.set()
        # A cancelled caller (its network client went away) cancels the future; the worker then
        # skips the job, so nothing is executed for a client that is no longer there.
        return await job.future

    async def _work(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            if not self._queue:
                self._wakeup.clear()
                await self._wakeup.wait()
                continue
            job = self._queue.popleft()
            if job.future.done():  # cancelled while queued
                continue
            if loop.time() > job.deadline:
                self.stats.expired += 1
                job.future.set_exception(
                    S5Fault(
                        FaultKind.PLC_TIMEOUT,
                        f"waited more than {self.max_wait:g} s for the PLC; not executed",
                    )
                )
                continue
            if job.data is None:
                cached = self._cached(job.target, job.offset, job.size)
                if cached is not None:  # a read queued behind an identical one
                    self.stats.cache_hits += 1
                    job.future.set_result(cached)
                    continue
            try:
                result = await self._execute(job)
            except S5Fault as exc:
                self.stats.failed += 1
                if not job.future.done():
                    job.future.set_exception(exc)
            else:
                if not job.future.done():
                    job.future.set_result(result)

    # -- the AS511 side -----------------------------------------------------------------------
    async def _execute(self, job: _Job) -> bytes:
        target, what = job.target, describe_target(job.target)
        client = self.client
        try:
            if job.data is None:
                self.stats.line_reads += 1
                data = await self._read(target, job.offset, job.size)
                self._remember(target, job.offset, data)
                return data
            self.stats.line_writes += 1
            try:
                await self._write(target, job.offset, job.data)
            finally:
                # even a failed write may have changed memory ("may or may not")
                self._forget(target)
            return b""
        except S5Fault:
            raise
        except AddressError as exc:  # beyond the block's length or the area's size
            raise S5Fault(FaultKind.TOO_SMALL, str(exc)) from None
        except PlcErrorResponse as exc:  # a DLE NAK (not "missing block": see _block)
            raise S5Fault(FaultKind.PLC_REFUSED, str(exc)) from None
        except (PlcTimeout, ConnectionLost) as exc:
            if job.data is not None:
                log.warning("%s: write to %s not confirmed: %s", client.name, what, exc)
            raise S5Fault(FaultKind.PLC_TIMEOUT, str(exc)) from None
        except PlcError as exc:  # malformed answers and the like
            log.warning("%s: %s failed: %s", client.name, what, exc)
            raise S5Fault(FaultKind.PLC_TIMEOUT, str(exc)) from None

    async def _block(self, target: BlockRef) -> None:
        """Make sure a block's address is known; a NAK to B_INFO means the block is missing."""
        btype, number = target
        code = int(btype)
        if (code, number) in self.client.block_cache:
            return
        try:
            await self.client.block_info(code, number)
        except PlcErrorResponse as exc:
            raise S5Fault(FaultKind.NO_AREA, str(exc)) from None

    async def _read(self, target: Target, offset: int, size: int) -> bytes:
        if isinstance(target, tuple):
            await self._block(target)
            return await self.client.read_block_bytes(int(target[0]), target[1], offset, size)
        if isinstance(target, Area):
            return await self.client.read_bytes(self._area(target), offset, size)
        return await self.client.read_absolute(offset, size)

    async def _write(self, target: Target, offset: int, data: bytes) -> None:
        if isinstance(target, tuple):
            await self._block(target)
            await self.client.write_block_bytes(int(target[0]), target[1], offset, data)
        elif isinstance(target, Area):
            await self.client.write_bytes(self._area(target), offset, data)
        else:
            await self.client.write_absolute(offset, data)

    @staticmethod
    def _area(area: Area) -> S5Area:
        try:
            return _CLIENT_AREAS[area]
        except KeyError:
            raise S5Fault(
                FaultKind.NO_AREA, f"area {area.value} is not served through the gateway"
            ) from None

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
        """Drop what a write to ``target`` may have changed (absolute memory: everything)."""
        if isinstance(target, str):
            self._cache.clear()
        else:
            self._cache.pop(target, None)
            self._cache.pop("absolute", None)
