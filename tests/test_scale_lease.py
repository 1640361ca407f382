"""Leases in NATS JetStream KV against a real nats-server (started on a free loopback port)."""

from __future__ import annotations

import asyncio
import contextlib

import nats.js.errors
import pytest

from plcstack.scale.lease import CoordinationError, LeaseStore, lease_key
from tests.robust_helpers import record_loop_errors
from tests.scale_helpers import CutProxy
from tests.servers import NatsServer, free_port


def test_lease_keys_are_valid_and_distinct() -> None:
    assert lease_key("press1") == "plc.press1"
    assert lease_key("line 1/press") == "plc.=" + b"line 1/press".hex()
    assert lease_key("=41") != lease_key("A")  # an encoded name never equals a plain one


async def test_one_holder_renew_release(nats_server: NatsServer) -> None:
    a = LeaseStore(nats_server.url, worker="a", ttl=2.0)
    b = LeaseStore(nats_server.url, worker="b", ttl=2.0)
    await a.connect()
    await b.connect()
    try:
        lease = await a.acquire("press1")
        assert lease is not None and lease.revision > 0
        assert await b.acquire("press1") is None  # held: the second create is refused
        old = (lease.revision, lease.fence_at)
        await asyncio.sleep(0.05)
        assert await a.renew(lease) is True
        assert lease.revision > old[0] and lease.fence_at > old[1]  # a new fencing revision
        assert await a.holders() == {"plc.press1": "a"}
        assert await a.release(lease)
        taken = await b.acquire("press1")  # free at once after a release
        assert taken is not None and taken.revision > lease.revision
        assert await a.renew(lease) is False  # the old holder learns it lost the lease
        assert not await a.release(lease)  # and cannot delete the new owner's lease
        assert await b.holders() == {"plc.press1": "b"}
    finally:
        await a.close()
        await b.close()


async def test_an_unrenewed_lease_expires_after_the_ttl(nats_server: NatsServer) -> None:
    a = LeaseStore(nats_server.url, worker="a", ttl=0.5)
    b = LeaseStore(nats_server.url, worker="b", ttl=0.5)
    await a.connect()
    await b.connect()
    try:
        loop = asyncio.get_running_loop()
        sent = loop.time()
        lease = await a.acquire("oven2")
        assert lease is not None
        # the holder must stop at ttl - guard after sending its last write
        assert lease.fence_at == pytest.approx(sent + 0.5 - 0.125, abs=0.05)
        taken = None
        for _ in range(200):  # polling is the point: expiry sends no event
            taken = await b.acquire("oven2")
            if taken is not None:
                break
            await asyncio.sleep(0.02)
        assert taken is not None
        assert loop.time() - sent >= 0.5  # never before the ttl
        assert taken.revision > lease.revision
        assert await a.renew(lease) is False
    finally:
        await a.close()
        await b.close()


async def test_a_write_whose_answer_was_lost_is_adopted(nats_server: NatsServer) -> None:
    a = LeaseStore(nats_server.url, worker="a", ttl=5.0)
    await a.connect()
    try:
        lease = await a.acquire("press1")
        assert lease is not None
        # as if an acquire had timed out after the server wrote it: create now fails, but the
        # key holds this incarnation, so it is taken over with a compare-and-set renew
        a._maybe_ours.add(lease.key)
        again = await a.acquire("press1")
        assert again is not None and again.revision > lease.revision
        other = LeaseStore(nats_server.url, worker="a", ttl=5.0)  # same name, new incarnation
        await other.connect()
        try:
            other._maybe_ours.add(lease.key)
            assert await other.acquire("press1") is None  # a restarted worker must wait
        finally:
            await other.close()
    finally:
        await a.close()


async def test_every_worker_must_use_the_bucket_ttl(nats_server: NatsServer) -> None:
    a = LeaseStore(nats_server.url, worker="a", ttl=2.0)
    await a.connect()
    await a.close()
    b = LeaseStore(nats_server.url, worker="b", ttl=3.0)
    with pytest.raises(CoordinationError, match="same --lease-ttl"):
        await b.connect()


async def test_no_server_is_a_coordination_error() -> None:
    store = LeaseStore(f"nats://127.0.0.1:{free_port()}", worker="a", ttl=2.0, connect_timeout=0.5)
    with pytest.raises(CoordinationError, match="connect to NATS"):
        await store.connect()


async def test_a_renew_without_the_server_gives_no_answer(nats_server: NatsServer) -> None:
    proxy = CutProxy(nats_server.host, nats_server.port)
    await proxy.start()
    changes: list[bool] = []
    a = LeaseStore(
        f"nats://127.0.0.1:{proxy.port}", worker="a", ttl=1.0, on_connection=changes.append
    )
    await a.connect()
    try:
        lease = await a.acquire("press1")
        assert lease is not None
        fence_at = lease.fence_at
        proxy.cut()
        assert await a.renew(lease) is None  # unknown: the holder keeps it until fence_at
        assert lease.fence_at == fence_at
        assert changes[:1] == [False]
    finally:
        await a.close()
        await proxy.aclose()


async def test_a_refusal_that_meets_the_stop_of_its_worker_is_read(
    nats_server: NatsServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker stops (a cancel) just as NATS refuses a create: the stop wins, and the
    refusal is read, not left for asyncio to report as "Task exception was never retrieved"
    (as Python 3.11's wait_for leaves it)."""
    store = LeaseStore(nats_server.url, worker="a", ttl=2.0)
    await store.connect()
    started = asyncio.Event()

    async def refused_as_the_stop_comes(key: str, value: bytes) -> int:
        started.set()
        try:
            await asyncio.sleep(10)
        except asyncio.CancelledError:
            refused = nats.js.errors.KeyWrongLastSequenceError(description="wrong last sequence: 4")
            raise refused from None
        raise AssertionError("not cancelled")

    try:
        monkeypatch.setattr(store._kv, "create", refused_as_the_stop_comes)
        async with record_loop_errors() as errors:
            acquiring = asyncio.create_task(store.acquire("press1"))
            await started.wait()
            acquiring.cancel()
            with pytest.raises(asyncio.CancelledError):
                await acquiring
        assert errors.describe() == []
    finally:
        await store.close()


async def test_a_store_closed_while_reconnecting_leaves_no_task(nats_server: NatsServer) -> None:
    """nats-py's reconnecting task ends with the store, also when it drops the cancel of
    nats-py's close (as a wait_for inside it can on Python 3.11)."""
    store = LeaseStore(nats_server.url, worker="a", ttl=2.0)
    await store.connect()

    async def reconnecting_that_drops_a_cancel() -> None:
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.sleep(10)
        await asyncio.sleep(10)  # goes on reconnecting

    task = asyncio.create_task(reconnecting_that_drops_a_cancel())
    await asyncio.sleep(0)
    store._nc._reconnection_task = task  # type: ignore[union-attr]
    await store.close()
    assert task.done()
