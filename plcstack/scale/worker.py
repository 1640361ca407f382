"""The worker loop: poll the PLCs this worker owns, and only while it may.

Ownership is rendezvous hashing over the live workers (:mod:`plcstack.scale.presence`); for an
exclusive PLC it is additionally a lease (:mod:`plcstack.scale.lease`). The rules, in the order
they matter:

1. An exclusive PLC is polled only between a successful acquire and its ``fence_at``; every
   successful renew moves ``fence_at`` on. A timer stops polling at ``fence_at`` (the connection
   is aborted at once: the socket closes in the next loop pass), so a worker that cannot renew
   stops ``guard`` seconds before anyone else could take the lease; a renew that finds the lease
   taken stops it at once.
2. A PLC that moves away (a worker joined or came back) is stopped first and released after, so
   the new owner's ``create`` succeeds only once the old connection is closed.
3. A PLC is started only after its lease was acquired, so after a crash the new owner waits for
   the old lease to expire (``ttl`` after its last renew) and polls at most ``retry`` later.

Each owned PLC runs in its own :class:`~plcstack.poll.Poller` (one PLC each, so starting and
stopping one never touches another); their scans are merged into one bounded buffer that this
object hands out like a Poller does (``scans``, ``async for``, ``drain``, ``pending``, ``stats``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import fnmatch
import time
from collections.abc import AsyncIterator, Callable, Coroutine, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self

from plcstack.clients.base import Client
from plcstack.errors import AddressError, LocalProtocolError
from plcstack.north.write_values import WriteValueError
from plcstack.north.writes import UNKNOWN_PLC
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.diff import PlcChanges
from plcstack.poll.engine import (
    Applied,
    ClientFactory,
    PlcStats,
    Poller,
    Sample,
    Scan,
    ScanQueue,
    new_connect_turns,
)
from plcstack.resource import cancel_until_done
from plcstack.scale.hrw import owner
from plcstack.scale.lease import Lease, LeaseStore
from plcstack.scale.presence import Presence

__all__ = ["Worker", "WorkerOptions"]


@dataclass(frozen=True)
class WorkerOptions:
    """How a worker finds the others and guards its PLCs (``plcstack poll --mqtt ...``)."""

    #: this worker's name, unique in the cluster (a host name, a StatefulSet pod name)
    worker: str
    #: the MQTT broker for presence, ``mqtt://host:port``
    mqtt: str
    #: the NATS server for leases, ``nats://host:port``; None: no leases (no exclusivity)
    nats: str | None = None
    #: prefix of the MQTT topics and name part of the lease bucket
    cluster: str = "plcstack"
    #: lease time in seconds: a dead worker's PLCs are polled again at most this (+ retry) later
    lease_ttl: float = 10.0
    #: seconds before the ttl at which a holder that could not renew stops (default ttl/4)
    guard: float | None = None
    #: how often a worker tries to take a lease it wants (default min(ttl/4, 1 s))
    retry: float | None = None
    #: MQTT keepalive in seconds (a silent worker's Will fires after 1.5 of these)
    keepalive: int = 5
    #: fnmatch patterns of the PLC names that need a lease (default: all)
    exclusive: tuple[str, ...] = ("*",)
    #: seconds between closing a moved PLC's connection and releasing its lease, so the PLC
    #: (a real module, or a busy simulator) has handled the close before the next owner connects
    handover: float = 0.2

    def __post_init__(self) -> None:
        if not self.worker or "/" in self.worker or "+" in self.worker or "#" in self.worker:
            raise ValueError(f"worker name {self.worker!r} must be non-empty without / + #")
        if not self.lease_ttl > 0:
            raise ValueError("lease ttl must be greater than 0")
        if self.retry is not None and not self.retry > 0:
            raise ValueError("retry must be greater than 0")
        if self.keepalive < 1:
            raise ValueError("keepalive must be at least 1 s")


class _Run:
    """One PLC being polled: a Poller of just that PLC, scanning into the worker's queue."""

    def __init__(self, poller: Poller, name: str) -> None:
        self.poller = poller
        self.name = name
        self.stopping: asyncio.Task[None] | None = None

    def abort(self) -> None:
        """Close the PLC connection now, synchronously (the fencing deadline may be near).

        ``aclose`` is started first: its first step cancels the polling task before any
        reconnect could run.
        """
        if self.stopping is None:
            self.stopping = asyncio.get_running_loop().create_task(self.poller.aclose())
        self.poller.client(self.name).transport.abort()

    async def stop(self) -> None:
        self.abort()
        assert self.stopping is not None
        await asyncio.gather(self.stopping, return_exceptions=True)


class Worker:
    """One worker of a sharded fleet: :meth:`scans` (or ``async for``: samples) of the PLCs it
    owns.

    ``config`` is the whole fleet (every worker reads the same file); ``on_event`` gets one line
    per ownership change (the CLI prints them on stderr).
    """

    def __init__(
        self,
        config: PollConfig,
        options: WorkerOptions,
        *,
        client_factory: ClientFactory | None = None,
        on_event: Callable[[str], None] | None = None,
    ) -> None:
        self.config = config
        self.options = options
        self.worker = options.worker
        self._factory = client_factory
        self._on_event = on_event
        # every URL and address checked now, before anything is sent (the Poller builds them)
        check = Poller(config, client_factory=client_factory)
        for name in check.plcs:
            check.client(name).transport.abort()
        #: every PLC's tags with the widths of their points (what the north side asks of any)
        self._tags = {name: check.tags(name) for name in check.plcs}
        self._plcs: dict[str, PlcConfig] = {p.name: p for p in config.plcs}
        #: one poller per PLC, one set of connect turns for all of them (a worker that takes
        #: over thousands of PLCs at once connects them as one poller would)
        self._connects = new_connect_turns()
        ttl = options.lease_ttl
        self.retry = options.retry if options.retry is not None else min(ttl / 4, 1.0)
        self.renew_every = ttl / 4
        self.leases: LeaseStore | None = None
        incarnation = options.worker
        if options.nats is not None:
            self.leases = LeaseStore(
                options.nats,
                worker=options.worker,
                ttl=ttl,
                guard=options.guard,
                bucket=f"{options.cluster}-leases",
                on_connection=self._lease_server,
            )
            incarnation = self.leases.incarnation
        self.presence = Presence(
            options.mqtt,
            worker=options.worker,
            incarnation=incarnation,
            cluster=options.cluster,
            keepalive=options.keepalive,
            on_change=lambda live: self._kick(),
            on_event=self._event,
        )
        #: the one buffer every PLC's poller scans into (drops counted there, per PLC)
        self.queue = ScanQueue(config.queue)
        self._runs: dict[str, _Run] = {}
        self._held: dict[str, Lease] = {}
        self._timers: dict[str, asyncio.TimerHandle] = {}
        self._stats: dict[str, PlcStats] = {}
        self._cleanup: set[asyncio.Task[None]] = set()
        self._tasks: list[asyncio.Task[None]] = []
        self._dirty = asyncio.Event()
        self._standby_timer: asyncio.TimerHandle | None = None
        self._wanted_cache: tuple[frozenset[str], frozenset[str]] | None = None
        self._running = False
        self._closed = False
        #: ownership changes so far (for tests and figures)
        self.starts = 0
        self.stops = 0
        self.fences = 0

    # -- life cycle -----------------------------------------------------------------------------
    async def start(self) -> None:
        """Connect to the lease server (:class:`CoordinationError` if it fails), then run."""
        if self._running or self._closed:
            return
        self._running = True
        if self.leases is not None:
            await self.leases.connect()
        loop = asyncio.get_running_loop()
        self._tasks = [
            loop.create_task(self.presence.run(), name=f"presence {self.worker}"),
            loop.create_task(self._reconcile_loop(), name=f"reconcile {self.worker}"),
        ]
        if self.leases is not None:
            self._tasks.append(loop.create_task(self._renew_loop(), name=f"renew {self.worker}"))

    async def aclose(self) -> None:
        """Hand over: announce ``offline``, stop polling, release every lease, disconnect."""
        if self._closed:
            return
        self._closed = True
        if self._running:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.presence.aclose(), timeout=2.0)
        await cancel_until_done(self._tasks)
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._standby_timer is not None:
            self._standby_timer.cancel()
        await asyncio.gather(*(self._stop(p) for p in list(self._runs.keys() | self._held.keys())))
        if self._cleanup:
            await asyncio.gather(*self._cleanup, return_exceptions=True)
        if self.leases is not None:
            await self.leases.close()
        self.queue.wake()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    # -- scans (the Poller's interface, so the CLI can run either) --------------------------------
    def scans(self, wait: float = 0.0) -> AsyncIterator[list[Scan]]:
        """Every scan of every owned PLC, as lists (see :meth:`Poller.scans`)."""
        return self.queue.batches(wait, self._ended)

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> Sample:
        return await self.queue.next_sample(self._ended)

    def _ended(self) -> bool:
        return self._closed

    def pending(self) -> int:
        return len(self.queue)

    def drain(self) -> list[Scan]:
        return self.queue.drain()

    @property
    def dropped(self) -> int:
        """Samples dropped because the buffer was full."""
        return self.queue.dropped

    @property
    def stats(self) -> dict[str, PlcStats]:
        """Per-PLC statistics of the PLCs this worker polls or polled (latest run of each)."""
        for name, run in self._runs.items():
            self._stats[name] = run.poller.stats[name]
        return dict(self._stats)

    @property
    def owned(self) -> frozenset[str]:
        """The PLCs being polled now."""
        return frozenset(self._runs)

    # -- the poller's read view and writes, for the PLCs this worker holds ----------------------
    @property
    def plcs(self) -> list[str]:
        """The PLCs this worker polls now (the whole fleet is ``config.plcs``)."""
        return list(self._runs)

    def tags(self, plc: str) -> dict[str, tuple[TagConfig, int]]:
        """Each tag of any PLC of the fleet with the width of its points (see
        :meth:`Poller.tags`)."""
        try:
            return dict(self._tags[plc])
        except KeyError:
            raise AddressError(f"no PLC named {plc!r} in this poller", plc=plc) from None

    def _poller_of(self, plc: str, request: str) -> Poller:
        """The poller of a PLC this worker holds; for another PLC of the fleet an
        :class:`AddressError` saying which worker polls it (nothing is sent)."""
        run = self._runs.get(plc)
        if run is not None:
            return run.poller
        if plc not in self._plcs:
            raise AddressError(f"no PLC named {plc!r} in this poller", plc=plc, request=request)
        live = self.presence.live
        holder = owner(plc, live) if live else None
        where = f"worker {holder}" if holder and holder != self.worker else "no worker yet"
        raise WriteValueError(
            f"this worker ({self.worker}) does not poll it now ({where} does); write through"
            " that worker; not attempted",
            code=UNKNOWN_PLC,
            plc=plc,
            request=request,
        )

    def client(self, plc: str) -> Client:
        return self._poller_of(plc, "client").client(plc)

    async def write(self, plc: str, address: str, values: Sequence[int] | Sequence[bool]) -> None:
        """A write through the PLC's polling connection, if this worker holds the PLC."""
        await self._poller_of(plc, f"write {address}").write(plc, address, values)

    async def write_tag(self, plc: str, tag: str, value: object) -> None:
        """A tag write through the PLC's polling connection, if this worker holds the PLC (the
        same single-flight path as a Poller's); another PLC's is refused, nothing sent."""
        await self._poller_of(plc, f"write {tag}").write_tag(plc, tag, value)

    # -- reconfigured while it runs (a reload) --------------------------------------------------
    async def apply(self, changes: PlcChanges) -> Applied:
        """The fleet's file changed (SIGHUP): the difference applied to the PLCs this worker
        polls, as a :class:`~plcstack.poll.engine.Poller` applies it. A removed PLC stops (its
        lease released); a changed one it polls is reconnected or planned again on its open
        connection (:meth:`Poller.apply`); an added one starts where rendezvous hashing gives
        it to this worker (every worker reads the same file). Every new URL and address is
        checked before anything changes."""
        if changes.old != self.config:
            raise LocalProtocolError(
                "these changes were made from another configuration than the worker's:"
                " make them with plc_changes(worker.config, new)"
            )
        started = time.perf_counter()
        new = changes.new
        touched = (*changes.added, *changes.reconnected, *changes.replanned)
        check = Poller(dataclasses.replace(new, plcs=touched), client_factory=self._factory)
        for name in check.plcs:
            check.client(name).transport.abort()
        self.config = new
        self._plcs = {p.name: p for p in new.plcs}
        self._tags = {name: self._tags[name] for name in self._plcs if name in self._tags}
        self._tags.update({name: check.tags(name) for name in check.plcs})
        self._wanted_cache = None
        removed: dict[str, PlcStats] = {}
        for plc in changes.removed:
            await self._stop(plc.name)
            removed[plc.name] = self._stats.pop(plc.name, PlcStats())
        for plc in (*changes.reconnected, *changes.replanned):
            run = self._runs.get(plc.name)
            if run is not None:
                await run.poller.reconfigure(dataclasses.replace(new, plcs=(plc,)))
        self._kick()  # the added PLCs this worker is given start in its next reconcile
        return Applied(
            added=tuple(p.name for p in changes.added),
            removed=removed,
            reconnected=tuple(p.name for p in changes.reconnected),
            replanned=tuple(p.name for p in changes.replanned),
            not_applied=changes.poller,
            seconds=time.perf_counter() - started,
        )

    # -- events -----------------------------------------------------------------------------------
    def _event(self, text: str) -> None:
        if self._on_event is not None:
            self._on_event(text)

    def _kick(self) -> None:
        self._dirty.set()

    def _lease_server(self, connected: bool) -> None:
        """The NATS connection went down or came back. A worker without its lease server cannot
        keep exclusive PLCs: after ``guard`` seconds down it withdraws (``standby``) so the others
        take its PLCs once the leases expire, instead of leaving them unpolled."""
        if self._closed:
            return
        loop = asyncio.get_running_loop()
        if self._standby_timer is not None:
            self._standby_timer.cancel()
            self._standby_timer = None
        if connected:
            self._event("lease server back")
            self._spawn(self.presence.set_online(True))
        else:
            assert self.leases is not None
            self._event("lost the lease server")
            self._standby_timer = loop.call_later(
                self.leases.guard, lambda: self._spawn(self.presence.set_online(False))
            )

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._cleanup.add(task)
        task.add_done_callback(self._cleanup.discard)

    # -- ownership --------------------------------------------------------------------------------
    def wanted(self) -> set[str]:
        """The PLCs rendezvous hashing gives this worker over the current live set."""
        live = self.presence.live
        if not self.presence.synced or self.worker not in live:
            return set()
        cached = self._wanted_cache
        if cached is None or cached[0] != live:
            # hashing every PLC against every worker: only when the live set changed
            mine = {name for name in self._plcs if owner(name, live) == self.worker}
            cached = self._wanted_cache = (live, frozenset(mine))
        return set(cached[1])

    def exclusive(self, plc: str) -> bool:
        return self.leases is not None and any(
            fnmatch.fnmatchcase(plc, pattern) for pattern in self.options.exclusive
        )

    async def _reconcile_loop(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._dirty.wait(), timeout=self.retry)
            self._dirty.clear()
            await self._reconcile()

    async def _reconcile(self) -> None:
        wanted = self.wanted()
        leaving = [p for p in self._runs.keys() | self._held.keys() if p not in wanted]
        if leaving:
            live = self.presence.live
            for plc in leaving:
                self._event(f"stop {plc}: moves to {owner(plc, live) or 'nobody'}")
            await asyncio.gather(*(self._stop(p) for p in leaving))
        todo = [p for p in wanted if p not in self._runs]
        free = [p for p in todo if not self.exclusive(p)]
        for plc in free:
            await self._start(plc, None)
        guarded = [p for p in todo if self.exclusive(p)]
        if not guarded or self.leases is None or not self.leases.connected:
            return
        leases = await asyncio.gather(*(self.leases.acquire(p) for p in guarded))
        loop = asyncio.get_running_loop()
        for plc, lease in zip(guarded, leases, strict=True):
            if lease is None:
                continue
            if plc not in self.wanted() or loop.time() >= lease.fence_at or self._closed:
                await self.leases.release(lease)
                continue
            await self._start(plc, lease)

    async def _start(self, plc: str, lease: Lease | None) -> None:
        config = dataclasses.replace(self.config, plcs=(self._plcs[plc],))
        poller = Poller(
            config, client_factory=self._factory, queue=self.queue, connect_turns=self._connects
        )
        run = _Run(poller, plc)
        if lease is not None:
            self._held[plc] = lease
            self._arm(lease)
        self._runs[plc] = run
        await run.poller.start()
        self.starts += 1
        rev = f" (lease revision {lease.revision})" if lease is not None else ""
        self._event(f"start {plc}{rev}")

    async def _stop(self, plc: str) -> None:
        """Stop polling ``plc``, then release its lease (in that order: rule 2)."""
        lease = self._held.pop(plc, None)
        timer = self._timers.pop(plc, None)
        if timer is not None:
            timer.cancel()
        run = self._runs.pop(plc, None)
        if run is not None:
            await run.stop()
            self._stats[plc] = run.poller.stats[plc]
            self.stops += 1
            if lease is not None and self.options.handover > 0:
                await asyncio.sleep(self.options.handover)
        if lease is not None and self.leases is not None:
            await self.leases.release(lease)

    # -- fencing ----------------------------------------------------------------------------------
    def _arm(self, lease: Lease) -> None:
        timer = self._timers.pop(lease.plc, None)
        if timer is not None:
            timer.cancel()
        loop = asyncio.get_running_loop()
        self._timers[lease.plc] = loop.call_at(
            lease.fence_at, self._fence, lease, "lease not renewed in time"
        )

    def _fence(self, lease: Lease, why: str) -> None:
        """Stop polling a PLC whose lease may be gone, now (rule 1). Synchronous: the connection
        is aborted before any other task runs, and the Poller's close, scheduled first, cancels
        the polling task before it could reconnect."""
        if self._held.get(lease.plc) is not lease:
            return
        del self._held[lease.plc]
        timer = self._timers.pop(lease.plc, None)
        if timer is not None:
            timer.cancel()
        run = self._runs.pop(lease.plc, None)
        if run is not None:
            run.abort()
            self._spawn(self._after_fence(run, lease))
        self.fences += 1
        self._event(f"fence {lease.plc}: {why}")
        self._kick()

    async def _after_fence(self, run: _Run, lease: Lease) -> None:
        await run.stop()
        self._stats[run.name] = run.poller.stats[run.name]
        self.stops += 1
        if self.leases is not None:
            await self.leases.release(lease)  # compare-and-set: harmless if it is gone

    async def _renew_loop(self) -> None:
        assert self.leases is not None
        loop = asyncio.get_running_loop()
        due = loop.time()
        while True:
            due += self.renew_every
            await asyncio.sleep(max(0.0, due - loop.time()))
            due = max(due, loop.time() - self.renew_every)  # after a stall, do not burst
            held = list(self._held.values())
            if not held:
                continue
            results = await asyncio.gather(*(self.leases.renew(lease) for lease in held))
            for lease, ok in zip(held, results, strict=True):
                if self._held.get(lease.plc) is not lease:
                    continue  # stopped or fenced meanwhile
                if ok is True:
                    self._arm(lease)
                elif ok is False:
                    self._fence(lease, "lease lost (another worker holds it)")
