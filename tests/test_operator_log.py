"""What an operator sees at the default log level: each change once, not each scan."""

from __future__ import annotations

import asyncio
import logging

import pytest

from plcstack.errors import ConnectFailed, ValueDecodeError
from plcstack.north.buffer import StoreAndForward
from plcstack.north.config import NorthConfig
from plcstack.north.mqtt import MqttSettings, MqttSink
from plcstack.north.pipeline import North
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Sample, Scan
from plcstack.values import BCD16
from tests.scan_helpers import scan
from tests.servers import Mosquitto


def _scan(ok: bool, t: float) -> list[Scan]:
    if ok:
        return [scan(Sample("press1", "x", 1, Quality.GOOD, t, t))]
    error = "press1: connect: connection refused"
    return [scan(Sample("press1", "x", None, Quality.BAD, t, t + 0.1, error, ConnectFailed))]


def test_a_plc_going_offline_and_back_is_one_warning_each(
    caplog: pytest.LogCaptureFixture,
) -> None:
    plc = PlcConfig("press1", "e71+tcp://127.0.0.1:1", (TagConfig("x", "D0"),))
    poller = Poller(PollConfig((plc,), {"default": 1}))  # never started
    north = North(poller, NorthConfig())
    pattern = [True] * 3 + [False] * 20 + [True] * 5 + [False] * 2
    with caplog.at_level(logging.WARNING):
        for i, ok in enumerate(pattern):
            north.deliver(_scan(ok, 1_800_000_000.0 + i))
    # main: nothing at all; a poll --format none run showed a dead PLC only in its final table
    assert [r.getMessage() for r in caplog.records] == [
        "PLC press1 is offline: press1: connect: connection refused",
        "PLC press1 is back online",
        "PLC press1 is offline: press1: connect: connection refused",
    ]


def test_a_cold_start_whose_failing_group_reports_first_says_nothing_offline(
    caplog: pytest.LogCaptureFixture,
) -> None:
    tags = (TagConfig("x", "D0"), TagConfig("code", "D1", BCD16, group="slow"))
    plc = PlcConfig("press1", "e71+tcp://127.0.0.1:1", tags)
    poller = Poller(PollConfig((plc,), {"default": 1, "slow": 1}))  # never started
    north = North(poller, NorthConfig())
    t = 1_800_000_000.0
    error = "press1: read D1: 00AF is no BCD"
    failing = Sample("press1", "code", None, Quality.BAD, t, t + 0.1, error, ValueDecodeError)
    with caplog.at_level(logging.INFO):
        north.deliver([scan(failing, group="slow")])  # before: "PLC press1 is offline"
        north.deliver(_scan(True, t + 0.2))
    assert [r.getMessage() for r in caplog.records] == ["PLC press1 is online"]


async def test_a_sink_losing_and_regaining_its_broker_says_so_once_each(
    mosquitto: Mosquitto, caplog: pytest.LogCaptureFixture
) -> None:
    settings = MqttSettings(host=mosquitto.host, port=mosquitto.port, reconnect_max=0.1)
    sink = MqttSink(settings, buffer=StoreAndForward(None))
    with caplog.at_level(logging.WARNING, "plcstack.north.mqtt"):
        await sink.start()
        try:
            await sink.wait_connected(5)
            mosquitto.stop()
            async with asyncio.timeout(10):
                while sink.connected or sink.stats.failures < 5:  # noqa: ASYNC110
                    await asyncio.sleep(0.02)  # several retries while the broker is away
            mosquitto.start()
            await sink.wait_connected(10)
        finally:
            await sink.aclose(drain=0)
    messages = [r.getMessage() for r in caplog.records]
    lost = [m for m in messages if "retrying with backoff" in m]
    back = [m for m in messages if "again" in m]
    assert 1 <= len(lost) <= 2 < sink.stats.failures  # the change, not every retry
    assert not [m for m in lost if "TLS" in m]  # a stopped broker is no configuration question
    assert back == [f"mqtt: connected to {settings.url} again; 0 messages waiting are sent first"]


def test_a_session_the_broker_closes_is_not_explained_as_a_wrong_port() -> None:
    """What a broker stopped with SIGTERM looks like to the sink (seen in a soak, half of the
    stops): paho's receive error, then aiomqtt's. Said of a session that was up, the meaning
    of a reset at connect time ("mqtt:// to a TLS port") sent the operator to the config."""
    import aiomqtt

    from plcstack.errors import ConnectionLost
    from plcstack.north.mqtt_errors import connect_error

    settings = MqttSettings(host="127.0.0.1", port=1883)
    paho = ["failed to receive on socket: [Errno 104] Connection reset by peer"]
    exc = aiomqtt.MqttError("Disconnected during message iteration")
    lost = connect_error(exc, paho, broker="MQTT broker x", connected=True, settings=settings)
    assert isinstance(lost, ConnectionLost)
    assert lost.message == (
        "connection lost: the broker closed the connection (it stopped or restarted, or it"
        " dropped this client) (failed to receive on socket: [Errno 104] Connection reset by"
        " peer; Disconnected during message iteration)"
    )
    # the same reset while connecting keeps its connect-time meaning
    failed = connect_error(exc, paho, broker="MQTT broker x", connected=False, settings=settings)
    assert "mqtt:// to a TLS port" in failed.message
