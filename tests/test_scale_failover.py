"""Failover of real worker processes (``plcstack poll --mqtt --nats``) over a simulator fleet.

Three workers share twelve E71 simulators (each accepts 8 connections, so a second poller would
be let in and counted rather than refused). One worker is killed with SIGKILL: no handover, no
clean disconnect. Every PLC must be polled again within the lease ttl plus one poll interval,
and no simulator may ever see two connections at once, neither during the takeover nor when the
killed worker comes back and its PLCs move home.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from plcstack.scale.hrw import owner
from plcstack.scale.lease import LeaseStore, lease_key
from tests.scale_helpers import Fleet, WorkerProcess
from tests.servers import Mosquitto, NatsServer

TTL = 2.0
INTERVAL = 0.5
RETRY = 0.1
PLCS = 12


async def wait_holders(
    store: LeaseStore,
    plcs: list[str],
    workers: list[str],
    timeout: float,
    procs: list[WorkerProcess],
) -> None:
    """Until every lease is held by the worker rendezvous hashing names among ``workers``."""
    expected = {lease_key(p): owner(p, workers) for p in plcs}
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    holders: dict[str, str] = {}
    while loop.time() < deadline:
        holders = await store.holders()
        if holders == expected:
            return
        await asyncio.sleep(0.1)
    logs = "\n".join(f"--- {p.name}\n{p.text()[-1500:]}" for p in procs)
    raise AssertionError(f"leases {holders} != expected {expected}\n{logs}")


@pytest.mark.slow
async def test_kill_9_takeover_and_return_without_overlap(
    mosquitto: Mosquitto, nats_server: NatsServer, tmp_path: Path
) -> None:
    async with Fleet(PLCS, interval=INTERVAL) as fleet:
        config = fleet.toml(tmp_path / "fleet.toml")
        names = ["w1", "w2", "w3"]
        procs = [
            WorkerProcess(
                n,
                config,
                mqtt=mosquitto.url,
                nats=nats_server.url,
                ttl=TTL,
                retry=RETRY,
                logdir=tmp_path,
            )
            for n in names
        ]
        observer = LeaseStore(nats_server.url, worker="observer", ttl=TTL)
        try:
            for p in procs:
                p.start()
            plcs = list(fleet.watch)
            await asyncio.sleep(1.0)  # the workers import and connect; the bucket exists then
            await observer.connect()
            await wait_holders(observer, plcs, names, 20, procs)
            loop = asyncio.get_running_loop()

            victim = procs[0]
            orphans = [p for p in plcs if owner(p, names) == victim.name]
            assert orphans, "the victim owns no PLC; pick other names"
            killed = loop.time()
            victim.kill()
            await fleet.wait_all_polled(killed, timeout=TTL + INTERVAL + 5)
            deadline = loop.time() + TTL + 5
            while any(fleet.reconnected_after(killed)[p] is None for p in orphans):
                assert loop.time() < deadline, "the orphans were not taken over"
                await asyncio.sleep(0.05)
            # an orphan counts as polled again at the new owner's first request (a request the
            # victim sent just before the kill may be seen by the sampler just after it)
            polled, reconnected = fleet.polled_after(killed), fleet.reconnected_after(killed)
            first = {p: reconnected[p] if p in orphans else polled[p] for p in plcs}
            takeover = {p: t - killed for p, t in first.items() if t is not None}
            assert set(takeover) == set(plcs)
            assert max(takeover.values()) <= TTL + INTERVAL, takeover
            # the orphans waited for the lease: never polled before the ttl had run out since
            # the victim's last renew (at most ttl/4 before the kill)
            assert min(takeover[p] for p in orphans) >= TTL * 3 / 4 - fleet.every, takeover
            await wait_holders(observer, plcs, names[1:], 5, procs)

            victim.start()  # same name, new incarnation: its PLCs move back, one by one
            back = loop.time()
            await wait_holders(observer, plcs, names, 20, procs)
            settled = loop.time()
            await fleet.wait_all_polled(settled, timeout=INTERVAL + 3)
            gaps = fleet.longest_gap(back, settled)
            assert all(g < settled - back + 1 for g in gaps.values())
            peaks = fleet.peaks()
            assert set(peaks.values()) == {1}, peaks  # no PLC ever saw two connections
            for p in procs:
                assert "Traceback" not in p.text(), p.text()
        finally:
            for p in procs:
                p.stop()
            await observer.close()
