"""The test servers helper: mosquitto and influxd really start, stop and restart on loopback."""

from __future__ import annotations

import asyncio
import json
import socket
import urllib.request

import aiomqtt

from tests.servers import Influxd, Mosquitto


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


async def _roundtrip(broker: Mosquitto, topic: str, payload: bytes) -> bytes:
    async with aiomqtt.Client(broker.host, broker.port) as client:
        await client.subscribe(topic, qos=1)
        await client.publish(topic, payload, qos=1)
        async with asyncio.timeout(5):
            async for message in client.messages:
                assert isinstance(message.payload, bytes)
                return message.payload
    raise AssertionError("no message")


async def test_mosquitto_stop_and_restart_on_the_same_port(mosquitto: Mosquitto) -> None:
    assert mosquitto.host == "127.0.0.1"
    port = mosquitto.port
    assert await _roundtrip(mosquitto, "t/a", b"one") == b"one"
    mosquitto.stop()
    assert not _listening(mosquitto.host, port)
    mosquitto.start()
    assert mosquitto.port == port
    assert await _roundtrip(mosquitto, "t/b", b"two") == b"two"
    mosquitto.restart()
    assert await _roundtrip(mosquitto, "t/c", b"three") == b"three"


def test_influxd_takes_a_write_and_answers_a_query(influxd: Influxd) -> None:
    influxd.create_database("t")
    assert influxd.request("POST", "/write?db=t&precision=ns", b"m,plc=a v=1i 1000000000\n") == (
        204,
        "",
    )
    with urllib.request.urlopen(f"{influxd.url}/query?db=t&q=SELECT+v+FROM+m", timeout=5) as r:
        result = json.loads(r.read())
    assert result["results"][0]["series"][0]["values"] == [["1970-01-01T00:00:01Z", 1]]
