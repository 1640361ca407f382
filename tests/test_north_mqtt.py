"""MQTT sink against a real mosquitto: layout, Will, broker restart, backlog, budget, writes."""

from __future__ import annotations

import asyncio
import json
import signal
import socket
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

from plcstack.clients.base import Client
from plcstack.errors import ConnectFailed
from plcstack.north.buffer import StoreAndForward
from plcstack.north.mqtt import MqttSettings, MqttSink, parse_mqtt
from plcstack.north.writes import WritePath
from plcstack.poll.config import ConfigError, PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.values import BOOL, KY, UINT16
from tests.aio_helpers import eventually
from tests.north_certs import Authority
from tests.north_helpers import sample, subscriber
from tests.poll_fakes import FakeClient
from tests.scan_helpers import scan
from tests.servers import Mosquitto


def settings(broker: Mosquitto, **kw: Any) -> MqttSettings:
    kw.setdefault("reconnect_max", 0.2)
    return MqttSettings(host=broker.host, port=broker.port, **kw)


def counts(sub: Any) -> list[int]:
    """Values of tag n in arrival order, duplicates (at-least-once redelivery) removed."""
    seen: list[int] = []
    for record in sub.json():
        n = record["values"]["n"]
        if n not in seen:
            seen.append(n)
    return seen


async def test_data_and_status_layout(mosquitto: Mosquitto) -> None:
    async with subscriber(mosquitto.host, mosquitto.port, "plcstack/#") as sub:
        sink = MqttSink(settings(mosquitto, client_id="gw1"))
        await sink.start()
        await sink.wait_connected(5)
        sink.submit(
            [
                scan(sample("press/1", "t", 21.5), group="fast"),
                scan(
                    sample("press/1", "alarms", [True, False]),
                    sample("press/1", "bad", None, error="press/1: read D9 x1: no answer"),
                    sample("press/1", "nan", float("nan")),
                ),
            ]
        )
        await sub.wait_for(lambda s: len(s.messages) >= 4)
        await sink.aclose()
    by_topic = {t: json.loads(p) for t, p in sub.messages}
    poller_status = [json.loads(p)["status"] for t, p in sub.messages if "_poller" in t]
    assert poller_status == ["online", "offline"]  # offline: said on a graceful close
    assert by_topic["plcstack/press_1/status"]["status"] == "online"
    assert by_topic["plcstack/press_1/data/fast"] == {
        "plc": "press/1",
        "group": "fast",
        "timestamp": 1_800_000_000_000,
        "values": {"t": 21.5},
    }
    default = by_topic["plcstack/press_1/data/default"]
    assert default["values"] == {"alarms": [True, False]}
    assert default["errors"] == {
        "bad": "press/1: read D9 x1: no answer",
        "nan": "non-finite value nan",
    }


async def test_last_will_says_offline_when_the_connection_drops(mosquitto: Mosquitto) -> None:
    sink = MqttSink(settings(mosquitto, client_id="gw2"))
    await sink.start()
    await sink.wait_connected(5)
    async with subscriber(mosquitto.host, mosquitto.port, "plcstack/_poller/#") as sub:
        await sub.wait_for(lambda s: s.json() and s.json()[-1]["status"] == "online")
        # the network goes away under the client (no DISCONNECT): the broker sends the Will
        sink._client._client.socket().shutdown(socket.SHUT_RDWR)
        await sub.wait_for(lambda s: s.json()[-1]["status"] == "offline")
        await sub.wait_for(lambda s: s.json()[-1]["status"] == "online")  # and it came back
    await sink.wait_connected(10)  # the session fully up before closing (see the Sparkplug test)
    await sink.aclose()


async def test_broker_restart_loses_nothing_and_keeps_order(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    # small memory allowance: the outage goes to disk
    buffer = StoreAndForward(tmp_path / "q.sqlite", memory_bytes=4096, max_bytes=1 << 20)
    sink = MqttSink(settings(mosquitto), buffer=buffer)
    async with subscriber(mosquitto.host, mosquitto.port, "plcstack/+/data/#") as sub:
        await sink.start()
        await sink.wait_connected(5)
        n = 0
        for phase in range(3):
            if phase == 1:
                await sub.wait_for(lambda s: len(counts(s)) >= 100)
                mosquitto.stop()
                await eventually(lambda: not sink.connected, "the sink notices the broker left")
            if phase == 2:
                assert not sink.connected
                assert buffer.on_disk > 0
                mosquitto.start()
            for _ in range(100):
                sink.submit([scan(sample("p", "n", n))])
                n += 1
                await asyncio.sleep(0.002)
        await sub.wait_for(lambda s: len(counts(s)) >= 300, timeout=20)
        await sink.aclose()
    assert counts(sub) == list(range(300))
    stats = sink.stats
    assert stats.buffered >= 100 and stats.replayed >= 100
    assert buffer.dropped == 0 and len(buffer) == 0
    print(
        f"broker restart: sent={stats.sent} buffered={stats.buffered} replayed={stats.replayed}"
        f" received={len(sub.messages)} distinct={len(counts(sub))} lost=0"
    )


async def test_disk_backlog_survives_a_poller_restart(mosquitto: Mosquitto, tmp_path: Path) -> None:
    path = tmp_path / "q.sqlite"
    mosquitto.stop()  # first run: no broker at all
    first = MqttSink(settings(mosquitto), buffer=StoreAndForward(path, memory_bytes=1 << 20))
    await first.start()
    for n in range(50):
        first.submit([scan(sample("p", "n", n))])
    await asyncio.sleep(0.05)
    await first.aclose()  # memory part goes to disk
    mosquitto.start()
    async with subscriber(mosquitto.host, mosquitto.port, "plcstack/+/data/#") as sub:
        second = MqttSink(settings(mosquitto), buffer=StoreAndForward(path))
        assert len(second.buffer) == 51  # the PLC's status and 50 data messages
        await second.start()
        second.submit([scan(sample("p", "n", 50))])  # new data goes after the old
        await sub.wait_for(lambda s: len(counts(s)) >= 51)
        await second.aclose()
    assert counts(sub) == list(range(51))


async def test_byte_budget_keeps_the_newest_and_counts_the_rest(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    # the subscriber's persistent session exists before the outage, so the broker keeps what
    # arrives for it while it reconnects
    async with subscriber(mosquitto.host, mosquitto.port, "plcstack/+/data/#") as sub:
        mosquitto.stop()
        buffer = StoreAndForward(tmp_path / "q.sqlite", memory_bytes=2000, max_bytes=6000)
        sink = MqttSink(settings(mosquitto), buffer=buffer)
        await sink.start()
        for n in range(200):
            sink.submit([scan(sample("p", "n", n))])
            assert buffer.backlog_bytes <= 6000
        kept = len(buffer)
        assert buffer.dropped == sink.stats.submitted - kept > 0  # 200 data + 1 status
        mosquitto.start()
        await sub.wait_for(lambda s: len(counts(s)) >= kept)
        await sink.aclose()
    assert counts(sub) == list(range(200 - kept, 200))


def make_poller() -> tuple[Poller, dict[str, FakeClient]]:
    fakes: dict[str, FakeClient] = {}

    def factory(plc: PlcConfig) -> Client:
        fakes[plc.name] = FakeClient(f"fake://{plc.name}", timeout=0.2)
        return fakes[plc.name]

    tags = (
        TagConfig("speed", "D10", UINT16, writable=True),
        TagConfig("on", "M3", BOOL, writable=True),
        TagConfig("locked", "D20", UINT16),
        TagConfig("pair", "D30", KY, writable=True),
    )
    config = PollConfig((PlcConfig("press1", "e71+tcp://127.0.0.1:1", tags),), {"default": 60})
    return Poller(config, client_factory=factory), fakes


async def test_writes_are_confirmed_or_refused_with_the_reason(mosquitto: Mosquitto) -> None:
    poller, fakes = make_poller()
    async with poller:
        sink = MqttSink(settings(mosquitto), writes=WritePath(poller))
        await sink.start()
        await sink.wait_connected(5)
        async with (
            subscriber(mosquitto.host, mosquitto.port, "plcstack/+/write/resp") as sub,
            aiomqtt.Client(mosquitto.host, mosquitto.port) as client,
        ):

            async def ask(payload: bytes | str, plc: str = "press1") -> dict[str, Any]:
                before = len(sub.messages)
                await client.publish(f"plcstack/{plc}/write/req", payload, qos=1)
                await sub.wait_for(lambda s: len(s.messages) > before)
                reply: dict[str, Any] = json.loads(sub.messages[-1][1])
                return reply

            assert await ask('{"id": 1, "tag": "speed", "value": 1234}') == {"id": 1, "ok": True}
            assert fakes["press1"].memory["D"][10] == 1234
            assert await ask('{"id": "b", "tag": "on", "value": true}') == {"id": "b", "ok": True}
            # the one value grammar of every north side: integral floats, KY in both forms
            assert (await ask('{"id": "f", "tag": "speed", "value": 1201.0}'))["ok"] is True
            assert fakes["press1"].memory["D"][10] == 1201
            assert (await ask('{"id": "k", "tag": "pair", "value": "7,8"}'))["ok"] is True
            assert fakes["press1"].memory["D"][30] == 0x0708
            assert (await ask('{"id": "l", "tag": "pair", "value": [9, 10]}'))["ok"] is True
            assert fakes["press1"].memory["D"][30] == 0x090A
            assert (await ask('{"id": 1, "tag": "speed", "value": 1234}'))["ok"] is True
            refused = {
                '{"id": 2, "tag": "nope", "value": 1}': "unknown_tag",
                '{"id": 3, "tag": "speed", "value": 70000}': "wrong_type",
                '{"id": 4, "tag": "speed", "value": "fast"}': "wrong_type",
                '{"id": 4, "tag": "speed", "value": 1201.5}': "wrong_type",
                '{"id": 4, "tag": "pair", "value": "7;8"}': "wrong_type",
                '{"id": 5, "tag": "speed"}': "bad_request",
                '{"id": 9, "tag": "locked", "value": 1}': "not_writable",
                "not json": "bad_request",
            }
            for request, code in refused.items():
                reply = await ask(request)
                assert reply["ok"] is False and reply["error"] == code, (request, reply)
                assert reply["may_have_executed"] is False and reply["message"]
            assert (await ask('{"id": 6, "tag": "speed", "value": 1}', plc="ghost"))[
                "error"
            ] == "unknown_plc"
            fakes["press1"].kill()
            reply = await ask('{"id": 7, "tag": "speed", "value": 5}')
            assert reply["error"] == "plc_error" and reply["may_have_executed"] is False
            assert "press1" in reply["message"] or "fake://press1" in reply["message"]
            fakes["press1"].revive()
            fakes["press1"].delay = 1.0  # longer than its 0.2 s deadline
            reply = await ask('{"id": 8, "tag": "speed", "value": 6}')
            assert reply["error"] == "plc_error" and reply["may_have_executed"] is True
        assert fakes["press1"].memory["D"][10] == 1234  # nothing refused reached the PLC
        await sink.aclose()


def test_mqtt_table_parsing() -> None:
    s = parse_mqtt(
        {"url": "mqtts://broker.example", "username_env": "U", "password_env": "P", "qos": 0}
    )
    assert (s.host, s.port, s.tls, s.username_env, s.password_env, s.qos) == (
        "broker.example", 8883, True, "U", "P", 0,
    )  # fmt: skip
    # the variables are read when the sink connects, not when the table is parsed
    assert s.credentials({"U": "me", "P": "secret"}) == ("me", "secret")
    assert "secret" not in repr(s)
    for bad, text in [
        ({"url": "http://x"}, "url must be"),
        ({"qos": 3}, "qos must be"),
        ({"username_env": ""}, "non-empty string"),
        ({"mode": "xml"}, "mode must be"),
        ({"prefix": "a/#"}, "prefix"),
        ({"colour": 1}, "unknown key"),
        ({"key_file": "k.pem"}, "key_file needs cert_file"),
    ]:
        with pytest.raises(ConfigError, match=text):
            parse_mqtt(bad)


async def test_tls_broker_with_the_configured_ca(tmp_path: Path) -> None:
    from tests.servers import ServerUnavailable, free_port

    authority = Authority.create(tmp_path)
    ca = authority.ca
    cert, key = authority.issue(tmp_path, "127.0.0.1", server=True)
    tls_port = free_port()
    broker = Mosquitto(
        extra_config=f"listener {tls_port} 127.0.0.1\ncafile {ca}\ncertfile {cert}\nkeyfile {key}"
    )
    try:
        broker.start()
    except ServerUnavailable as exc:
        broker.close()
        pytest.fail(str(exc), pytrace=False)
    try:
        async with subscriber(broker.host, broker.port, "plcstack/#") as sub:
            s = parse_mqtt({"url": f"mqtts://127.0.0.1:{tls_port}", "ca_file": str(ca)})
            sink = MqttSink(s)
            await sink.start()
            await sink.wait_connected(5)
            sink.submit([scan(sample("p", "n", 1))])
            await sub.wait_for(lambda x: any("/data/" in t for t, _ in x.messages))
            await sink.aclose()
        # without the CA the broker's certificate is not trusted: no connection
        untrusted = MqttSink(parse_mqtt({"url": f"mqtts://127.0.0.1:{tls_port}"}))
        await untrusted.start()
        with pytest.raises(ConnectFailed, match="the broker's certificate is not trusted"):
            await untrusted.wait_connected(1)
        await untrusted.aclose(drain=0)
    finally:
        broker.close()


async def test_a_message_in_flight_is_counted_once_when_the_budget_overflows(
    mosquitto: Mosquitto,
) -> None:
    """Every queued message ends as exactly one of sent, waiting or dropped, even when the
    byte budget overflows while the broker holds acknowledgements back."""
    buffer = StoreAndForward(None, max_bytes=2000)
    sink = MqttSink(settings(mosquitto), buffer=buffer)
    await sink.start()
    broker = mosquitto._proc
    assert broker is not None
    try:
        await sink.wait_connected(10)
        await sink.wait_drained(10)
        broker.send_signal(signal.SIGSTOP)  # it reads nothing and acknowledges nothing
        for n in range(3):
            sink.submit([scan(sample("p", "n", n))])
        last = buffer.next_seq - 1
        await eventually(lambda: buffer.in_flight_through == last, "the publisher sent them")
        for n in range(3, 200):
            sink.submit([scan(sample("p", "n", n))])
        assert buffer.dropped > 0
        broker.send_signal(signal.SIGCONT)
        await sink.wait_drained(10)
    finally:
        broker.send_signal(signal.SIGCONT)
        await sink.aclose()
    assert sink.stats.sent + buffer.dropped == sink.stats.submitted
