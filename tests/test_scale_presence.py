"""Worker presence on a real mosquitto broker: retained status, Last Will, reconnects."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable

import aiomqtt
import pytest

from plcstack.scale.presence import Presence, parse_mqtt_url
from tests.scale_helpers import CutProxy
from tests.servers import Mosquitto


async def until(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not predicate():
        assert loop.time() < deadline, "condition not reached in time"
        await asyncio.sleep(0.02)


@contextlib.asynccontextmanager
async def running(presence: Presence) -> AsyncIterator[Presence]:
    task = asyncio.get_running_loop().create_task(presence.run())
    try:
        await asyncio.wait_for(presence.wait_synced(), timeout=5)
        yield presence
    finally:
        await presence.aclose()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def test_parse_mqtt_url() -> None:
    assert parse_mqtt_url("mqtt://127.0.0.1:1884") == ("127.0.0.1", 1884)
    assert parse_mqtt_url("broker") == ("broker", 1883)
    with pytest.raises(ValueError, match="mqtt://HOST:PORT"):
        parse_mqtt_url("http://x")


async def test_workers_see_each_other_and_a_clean_goodbye(mosquitto: Mosquitto) -> None:
    views: list[frozenset[str]] = []
    a = Presence(mosquitto.url, worker="a", incarnation="a/1", keepalive=2, on_change=views.append)
    b = Presence(mosquitto.url, worker="b", incarnation="b/1", keepalive=2)
    async with running(a):
        assert a.live == {"a"}  # alone, and it knows it only after the view is complete
        async with running(b):
            assert b.live == {"a", "b"}  # the retained status of a was there on subscribe
            await until(lambda: a.live == {"a", "b"})
        await until(lambda: a.live == {"a"})  # b said offline before leaving
    assert views[:3] == [frozenset({"a"}), frozenset({"a", "b"}), frozenset({"a"})]


@pytest.mark.slow  # about 4 s: reconnecting through the restored proxy
async def test_the_will_fires_when_a_worker_vanishes(mosquitto: Mosquitto) -> None:
    proxy = CutProxy(mosquitto.host, mosquitto.port)
    await proxy.start()
    a = Presence(mosquitto.url, worker="a", incarnation="a/1", keepalive=2)
    b = Presence(f"mqtt://127.0.0.1:{proxy.port}", worker="b", incarnation="b/1", keepalive=2)
    try:
        async with running(a), running(b):
            await until(lambda: a.live == {"a", "b"})
            proxy.cut()  # b's connection drops without DISCONNECT: the broker sends b's Will
            await until(lambda: a.live == {"a"})
            await until(lambda: not b.connected)
            assert b.live == {"a", "b"}  # b cannot learn anything and keeps its last view
            proxy.restore()
            await until(lambda: b.connected)
            await until(lambda: a.live == {"a", "b"})  # b announced itself again
    finally:
        await proxy.aclose()


async def test_standby_and_stale_or_malformed_status(mosquitto: Mosquitto) -> None:
    a = Presence(mosquitto.url, worker="a", incarnation="a/1", keepalive=2)
    b = Presence(mosquitto.url, worker="b", incarnation="b/2", keepalive=2)
    async with running(a), running(b):
        await until(lambda: a.live == {"a", "b"})
        await b.set_online(False)  # e.g. b lost its lease server
        assert b.live == {"a"}
        await until(lambda: a.live == {"a"})
        await b.set_online(True)
        await until(lambda: a.live == {"a", "b"})
        seen = (a.messages, b.messages)
        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as other:
            await other.publish("plcstack/workers/junk", b"\xff not json", qos=1, retain=True)
            # the late Will of an earlier run of b: b says again that it is online
            stale = b'{"state":"offline","worker":"b","incarnation":"b/1"}'
            await other.publish("plcstack/workers/b", stale, qos=1, retain=True)
        # each has seen the junk, the stale Will and b's record published again
        await until(lambda: a.messages >= seen[0] + 3 and b.messages >= seen[1] + 3)
        assert a.live == {"a", "b"} and b.live == {"a", "b"}
