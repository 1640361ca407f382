"""Sparkplug B: the schema against hand-assembled bytes, and a session on a real mosquitto."""

from __future__ import annotations

import json
import socket
from typing import Any

import aiomqtt

from plcstack.clients.base import Client
from plcstack.north.mqtt import MqttSettings, MqttSink
from plcstack.north.sparkplug import SparkplugLayout, metric_value
from plcstack.north.sparkplug_pb import Payload
from plcstack.north.writes import WritePath
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.values import BOOL, FLOAT32, INT16, UINT16
from tests.aio_helpers import eventually
from tests.north_helpers import sample, subscriber
from tests.poll_fakes import FakeClient
from tests.scan_helpers import scan as as_scan
from tests.servers import Mosquitto


def test_payload_bytes_follow_the_specification_field_numbers() -> None:
    # timestamp (1) = 1, metrics (2) = [name (1) "a", datatype (4) Int32, int_value (10) 5],
    # seq (3) = 2; assembled by hand from the specification's field numbers
    golden = bytes.fromhex("080112070a0161200350051802")
    p = Payload()
    p.timestamp, p.seq = 1, 2
    m = p.metrics.add()
    m.name, m.datatype, m.int_value = "a", 3, 5
    assert p.SerializeToString() == golden
    back = Payload.FromString(golden)
    assert (back.seq, back.metrics[0].name, metric_value(back.metrics[0])) == (2, "a", 5)
    # a negative Int16 travels as two's complement in the uint32 int_value
    neg = Payload.FromString(bytes.fromhex("1208200250fbffffff0f"))
    assert neg.metrics[0].int_value == 0xFFFFFFFB and metric_value(neg.metrics[0]) == -5


TAGS = (
    TagConfig("speed", "D10", UINT16, writable=True),  # DCMD writes it (the one allow-list)
    TagConfig("neg", "D11", INT16),
    TagConfig("temp", "D12", FLOAT32),
    TagConfig("alarms", "M0", BOOL, count=2),
)


def decode(messages: list[tuple[str, bytes]], kind: str) -> list[tuple[str, Any]]:
    return [(t, Payload.FromString(p)) for t, p in messages if f"/{kind}/" in t]


def unique(sub: Any) -> list[tuple[str, bytes]]:
    return list(dict.fromkeys(sub.messages))


def metrics(p: Any) -> dict[str, Any]:
    return {m.name: metric_value(m) for m in p.metrics}


def _deaths(sub: Any) -> list[int]:
    """The bdSeq of each NDEATH the subscriber saw (a redelivered copy once)."""
    return [metrics(p)["bdSeq"] for _, p in decode(unique(sub), "NDEATH")]


def host_view(messages: list[tuple[str, bytes]]) -> list[tuple[str, bytes]]:
    """The messages a host acts on: an NDEATH whose bdSeq is not that of the node's last NBIRTH
    is stale (a Will of an earlier session, delivered late) and is left out."""
    kept, current = [], None
    for topic, payload in messages:
        kind = topic.split("/")[2]
        if kind == "NBIRTH":
            current = metrics(Payload.FromString(payload))["bdSeq"]
        elif kind == "NDEATH" and metrics(Payload.FromString(payload))["bdSeq"] != current:
            continue
        kept.append((topic, payload))
    return kept


async def test_sparkplug_session_births_data_deaths_rebirth_and_dcmd(mosquitto: Mosquitto) -> None:
    fakes: dict[str, FakeClient] = {}

    def factory(plc: PlcConfig) -> Client:
        fakes[plc.name] = FakeClient(f"fake://{plc.name}")
        return fakes[plc.name]

    config = PollConfig((PlcConfig("press1", "e71+tcp://127.0.0.1:1", TAGS),), {"default": 60})
    settings = MqttSettings(
        host=mosquitto.host, port=mosquitto.port, client_id="edge1", mode="sparkplug",
        group_id="plant", reconnect_max=0.2,
    )  # fmt: skip
    layout = SparkplugLayout.for_config(settings, config)
    async with (
        Poller(config, client_factory=factory) as poller,
        subscriber(mosquitto.host, mosquitto.port, "#") as sub,
    ):
        sink = MqttSink(settings, writes=WritePath(poller), layout=layout)
        await sink.start()
        await sink.wait_connected(5)
        await sub.wait_for(lambda s: len(s.messages) >= 2)
        (nb_topic, nbirth), (db_topic, dbirth) = [
            (t, Payload.FromString(p)) for t, p in sub.messages[:2]
        ]
        assert nb_topic == "spBv1.0/plant/NBIRTH/edge1" and nbirth.seq == 0
        assert metrics(nbirth) == {"bdSeq": 0, "Node Control/Rebirth": False}
        assert db_topic == "spBv1.0/plant/DBIRTH/edge1/press1" and dbirth.seq == 1
        assert metrics(dbirth) == dict.fromkeys(["speed", "neg", "temp", "alarms/0", "alarms/1"])

        first = [("speed", 1200), ("neg", -5), ("temp", 21.5), ("alarms", [True, False])]
        sink.submit([as_scan(*(sample("press1", tag, value) for tag, value in first))])
        sink.submit(
            [as_scan(*(sample("press1", tag, None, error="down") for tag in ("speed", "neg")))]
        )
        sink.submit([as_scan(sample("press1", "speed", 1201))])
        await sub.wait_for(lambda s: len(s.messages) >= 5)
        kinds = [t.split("/")[2] for t, _ in sub.messages[2:5]]
        assert kinds == ["DDATA", "DDEATH", "DBIRTH"]
        seqs = [Payload.FromString(p).seq for _, p in sub.messages[2:5]]
        assert seqs == [2, 3, 4]
        ddata = Payload.FromString(sub.messages[2][1])
        assert metrics(ddata) == {"speed": 1200, "neg": -5, "temp": 21.5,
                                  "alarms/0": True, "alarms/1": False}  # fmt: skip
        assert [m.datatype for m in ddata.metrics] == [6, 2, 9, 11, 11]  # UInt16 Int16 Float Bool
        rebirth = metrics(Payload.FromString(sub.messages[4][1]))
        assert rebirth["speed"] == 1201 and rebirth["temp"] == 21.5  # the last known values

        async with aiomqtt.Client(mosquitto.host, mosquitto.port) as host:
            cmd = Payload()
            m = cmd.metrics.add()
            m.name, m.datatype, m.boolean_value = "Node Control/Rebirth", 11, True
            await host.publish("spBv1.0/plant/NCMD/edge1", cmd.SerializeToString(), qos=1)
            await sub.wait_for(lambda s: len(decode(s.messages, "NBIRTH")) >= 2)
            await sub.wait_for(lambda s: len(decode(s.messages, "DBIRTH")) >= 3)
            reborn = decode(sub.messages, "NBIRTH")[-1][1]
            assert reborn.seq == 0 and metrics(reborn)["bdSeq"] == 0  # same session, same bdSeq
            assert decode(sub.messages, "DBIRTH")[-1][1].seq == 1

            write = Payload()
            for name, value in (("speed", 77), ("nope", 1)):
                m = write.metrics.add()
                m.name, m.datatype, m.int_value = name, 6, value
            await host.publish("spBv1.0/plant/DCMD/edge1/press1", write.SerializeToString(), qos=1)
            await sub.wait_for(lambda s: any("write/resp" in t for t, _ in s.messages))
            refused = next(json.loads(p) for t, p in sub.messages if "write/resp" in t)
            assert refused["id"] == "dcmd:nope" and refused["error"] == "unknown_tag"
        assert fakes["press1"].memory["D"][10] == 77

        # the network drops: the broker sends the Will (NDEATH, bdSeq 0); the next session is 1
        sink._client._client.socket().shutdown(socket.SHUT_RDWR)
        await sub.wait_for(lambda s: len(decode(s.messages, "NDEATH")) >= 1)
        assert metrics(decode(sub.messages, "NDEATH")[0][1]) == {"bdSeq": 0}
        await sub.wait_for(lambda s: len(decode(s.messages, "NBIRTH")) >= 3)
        assert metrics(decode(sub.messages, "NBIRTH")[-1][1])["bdSeq"] == 1
        # the new session fully up (births acknowledged, subscribed) before closing: on Python
        # 3.11 a close while aiomqtt awaits an acknowledgement can lose its cancellation in
        # asyncio.wait_for and hang (a product issue, reported; not this test's subject)
        await sink.wait_connected(10)
        await sink.aclose()


async def test_sparkplug_store_and_forward_marks_replayed_data_historical() -> None:
    # Sparkplug publishes at QoS 0, which a broker queues for no offline session by default:
    # after the restart, whichever of the edge node and this subscriber reconnected first decided
    # whether the replay was seen. The broker here queues QoS 0 for the subscriber's persistent
    # session (as one holding a host's session would), so the order of the reconnects is no
    # matter and everything the node published is seen.
    with Mosquitto(extra_config="queue_qos0_messages true") as mosquitto:
        await _store_and_forward_marks_replayed_data_historical(mosquitto)


async def _store_and_forward_marks_replayed_data_historical(mosquitto: Mosquitto) -> None:
    config = PollConfig((PlcConfig("p", "e71+tcp://127.0.0.1:1", TAGS[:1]),), {"default": 60})
    settings = MqttSettings(
        host=mosquitto.host, port=mosquitto.port, client_id="edge2", mode="sparkplug",
        group_id="g", reconnect_max=0.2,
    )  # fmt: skip
    sink = MqttSink(settings, layout=SparkplugLayout.for_config(settings, config))
    async with subscriber(mosquitto.host, mosquitto.port, "spBv1.0/g/#") as sub:
        await sink.start()
        await sink.wait_connected(5)
        sink.submit([as_scan(sample("p", "speed", 1))])
        await sub.wait_for(lambda s: len(decode(s.messages, "DDATA")) >= 1)
        mosquitto.stop()
        # what comes now must go to the buffer (and be replayed as historical)
        await eventually(lambda: not sink.connected, "the sink notices the broker left")
        for v in (2, 3):
            sink.submit([as_scan(sample("p", "speed", v))])
        mosquitto.start()
        try:
            await sub.wait_for(lambda s: len(decode(unique(s), "DDATA")) >= 3, timeout=15)
        except TimeoutError:
            kinds = [t.split("/")[2] for t, _ in sub.messages]
            state = (sink.connected, len(sink.buffer), sink.stats, mosquitto.log())
            raise AssertionError(f"replay did not arrive: {kinds} {state}") from None
        await sink.aclose()
        # the close's NDEATH (bdSeq 1) is on its way: seen before this subscriber leaves
        await sub.wait_for(lambda s: _deaths(s).count(1) >= 1)
    # the broker may deliver a message to the subscriber again after its own restart (QoS 1, at
    # least once): the same topic and bytes, dropped here
    data = [p for _, p in decode(unique(sub), "DDATA")]
    assert [metrics(p)["speed"] for p in data] == [1, 2, 3]
    assert [p.metrics[0].is_historical for p in data] == [False, True, True]
    # The broker's own stop published the first session's Will (NDEATH, bdSeq 0), queued for the
    # persistent subscriber; after the restart it may come after the next session's first
    # messages. A host ignores an NDEATH whose bdSeq is not its node's current one (Sparkplug B
    # 3.0, host rules for NDEATH), and so does this check. The new session (bdSeq 1) died once:
    # at the sink's close, after everything else.
    deaths = _deaths(sub)
    assert deaths.count(1) == 1 and set(deaths) <= {0, 1}, deaths
    last_topic, last_payload = host_view(unique(sub))[-1]
    assert "/NDEATH/" in last_topic and metrics(Payload.FromString(last_payload))["bdSeq"] == 1
    # after the reconnect: NBIRTH (seq 0), DBIRTH (1), then the stored data (2, 3)
    kinds = [(t.split("/")[2], Payload.FromString(p).seq) for t, p in host_view(unique(sub))]
    last_birth = max(i for i, (kind, _) in enumerate(kinds) if kind == "NBIRTH")
    assert kinds[last_birth : last_birth + 4] == [
        ("NBIRTH", 0), ("DBIRTH", 1), ("DDATA", 2), ("DDATA", 3),
    ]  # fmt: skip
