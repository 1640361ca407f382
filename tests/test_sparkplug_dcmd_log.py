"""A refused Sparkplug DCMD is logged once, by the write path every north side shares.

Sparkplug has no reply message, so a refusal is counted, answered on the JSON response topic
and logged; the one WARNING comes from :mod:`plcstack.north.writes` (rate-limited per client,
PLC and tag), not a second time by the Sparkplug layout.
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from plcstack.clients.base import Client
from plcstack.north.mqtt import MqttSettings, MqttSink
from plcstack.north.sparkplug import SparkplugLayout
from plcstack.north.sparkplug_pb import Payload
from plcstack.north.writes import WritePath
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.values import UINT16
from tests.aio_helpers import eventually
from tests.poll_fakes import FakeClient


async def test_a_refused_dcmd_is_one_warning(
    caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    def factory(plc: PlcConfig) -> Client:
        return FakeClient(f"fake://{plc.name}")

    config = PollConfig(
        (PlcConfig("press1", "e71+tcp://127.0.0.1:1", (TagConfig("speed", "D10", UINT16),)),),
        {"default": 60},
    )
    settings = MqttSettings(
        host="127.0.0.1", port=1, client_id="edge1", mode="sparkplug", group_id="plant",
        state_path=str(tmp_path / "state"),
    )  # fmt: skip
    layout = SparkplugLayout.for_config(settings, config)
    async with Poller(config, client_factory=factory) as poller:
        # never started: no broker
        sink = MqttSink(settings, writes=WritePath(poller), layout=layout)
        command = Payload()
        metric = command.metrics.add()
        metric.name, metric.datatype, metric.int_value = "nope", 6, 1
        with caplog.at_level(logging.DEBUG, logger="plcstack"):
            sink.handle_request(
                "spBv1.0/plant/DCMD/edge1/press1", bytes(command.SerializeToString())
            )
            await eventually(lambda: sink.stats.writes_refused == 1, "the DCMD is refused")
    warnings = [
        r for r in caplog.records if r.levelno >= logging.WARNING and "nope" in r.getMessage()
    ]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    text = warnings[0].getMessage()
    assert "sparkplug" in text and "nope" in text and "unknown_tag" in text, text
