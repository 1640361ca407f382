"""What a UaExpert-style client reads of the OPC UA server: AccessLevel and UserAccessLevel per
session, BuildInfo, IndexRange on Read, PercentDeadband, and the bit-of-a-word refusal."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("asyncua")  # the optional extra; CI installs it with [test]

from asyncua import Client, ua

from plcstack.config import parse_config
from plcstack.north.opcua_services import apply_index_range, software_version
from plcstack.poll.config import ConfigError
from tests.test_opcua import Plant, good, plant, wait_for, with_login

__all__ = ["plant"]  # the module-scoped plant of test_opcua, one of its own here

#: the plant is module-scoped, so are the loops of the tests that use it
on_plant = pytest.mark.asyncio(loop_scope="module")

S = ua.StatusCodes
READ, WRITE = ua.AccessLevel.CurrentRead, ua.AccessLevel.CurrentWrite


async def access(client: Client, plant: Plant, tag: str) -> tuple[set[Any], set[Any]]:
    node = plant.node(client, "press1", tag)
    return set(await node.get_access_level()), set(await node.get_user_access_level())


@on_plant
async def test_user_access_level_says_what_this_session_may_do(plant: Plant) -> None:
    async with Client(with_login(plant.server.url, "viewer")) as viewer:
        sessions = {"anonymous": plant.anonymous, "viewer": viewer, "operator": plant.operator}
        seen = {name: await access(c, plant, "strokes") for name, c in sessions.items()}
        read_only = {name: await access(c, plant, "force") for name, c in sessions.items()}
    assert seen == {
        "anonymous": ({READ, WRITE}, {READ}),  # anonymous = "read" (the default)
        "viewer": ({READ, WRITE}, {READ}),  # a user without write = true
        "operator": ({READ, WRITE}, {READ, WRITE}),
    }
    assert all(v == ({READ}, {READ}) for v in read_only.values())  # not writable = true


@on_plant
async def test_build_info_names_plcstack_and_its_version(plant: Plant) -> None:
    client = plant.anonymous
    fields = {}
    for name in ("ProductName", "SoftwareVersion", "ManufacturerName", "ProductUri"):
        node = client.get_node(getattr(ua.ObjectIds, f"Server_ServerStatus_BuildInfo_{name}"))
        fields[name] = await node.read_value()
    assert fields == {
        "ProductName": "plcstack",
        "SoftwareVersion": software_version(),
        "ManufacturerName": "the plcstack authors",
        "ProductUri": "urn:plcstack",
    }
    endpoints = await client.get_endpoints()
    assert {e.Server.ProductUri for e in endpoints} == {"urn:plcstack"}


async def read_range(plant: Plant, tag: str, index_range: str) -> ua.DataValue:
    item = ua.ReadValueId()
    item.NodeId = ua.NodeId(f"press1.{tag}", plant.idx)
    item.AttributeId = ua.AttributeIds.Value
    item.IndexRange = index_range
    params = ua.ReadParameters()
    params.NodesToRead = [item]
    [dv] = await plant.anonymous.uaclient.read(params)
    return dv


@on_plant
async def test_index_range_on_read_is_honoured_or_refused_with_the_standard_status(
    plant: Plant,
) -> None:
    await wait_for(plant.node(plant.anonymous, "press1", "alarms"), good)
    # M0..M3 hold true, false, true, true
    parts = {r: (await read_range(plant, "alarms", r)).Value.Value for r in ("1:2", "3", "2:9")}
    assert parts == {"1:2": [False, True], "3": [True], "2:9": [True, True]}
    statuses = {
        r: (await read_range(plant, tag, r)).StatusCode.value
        for tag, r in (("alarms", "4"), ("alarms", "2:1"), ("alarms", "x"), ("strokes", "0"))
    }
    assert statuses == {
        "4": S.BadIndexRangeNoData,  # beyond the 4 elements
        "2:1": S.BadIndexRangeInvalid,
        "x": S.BadIndexRangeInvalid,
        "0": S.BadIndexRangeNoData,  # a scalar
    }
    whole = await read_range(plant, "alarms", "")
    assert whole.Value.Value == [True, False, True, True]


def test_index_range_rules() -> None:
    dv = ua.DataValue(ua.Variant([1, 2, 3], ua.VariantType.Int16))
    assert apply_index_range(dv, "0:1").Value.Value == [1, 2]
    assert apply_index_range(dv, "0:1,0:1").StatusCode.value == S.BadIndexRangeNoData
    text = ua.DataValue(ua.Variant("Hello", ua.VariantType.String))
    assert apply_index_range(text, "1:3").Value.Value == "ell"  # strings by character


@on_plant
async def test_percent_deadband_needs_an_eu_range(plant: Plant) -> None:
    client = plant.anonymous

    class Handler:
        def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
            pass

    subscription = await client.create_subscription(50, Handler())
    try:
        results = {}
        for tag in ("force", "level"):  # force has no EURange, level has one (0..100 %)
            flt = ua.DataChangeFilter()
            flt.Trigger = ua.DataChangeTrigger.StatusValue
            flt.DeadbandType = ua.DeadbandType.Percent
            flt.DeadbandValue = 5.0
            request = ua.MonitoredItemCreateRequest()
            request.ItemToMonitor = ua.ReadValueId(
                NodeId=ua.NodeId(f"press1.{tag}", plant.idx), AttributeId=ua.AttributeIds.Value
            )
            request.MonitoringMode = ua.MonitoringMode.Reporting
            request.RequestedParameters = ua.MonitoringParameters(
                ClientHandle=1, SamplingInterval=50, Filter=flt, QueueSize=1, DiscardOldest=True
            )
            params = ua.CreateMonitoredItemsParameters()
            params.SubscriptionId = subscription.subscription_id
            params.TimestampsToReturn = ua.TimestampsToReturn.Both
            params.ItemsToCreate = [request]
            [result] = await client.uaclient.create_monitored_items(params)
            results[tag] = result.StatusCode.value
    finally:
        await subscription.delete()
    assert results == {"force": S.BadDeadbandFilterInvalid, "level": S.Good}


BIT_TOML = """\
[[plc]]
name = "press1"
url = "e71+tcp://127.0.0.1:5000"

[plc.tags]
setpoint = { address = "D100", type = "int16", writable = true }
lamp = { address = "D100.3", type = "bool", writable = true }
"""


def test_a_writable_bit_of_a_word_is_refused_when_the_config_loads(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"tag 'lamp': writable = true on a bit of a word"):
        parse_config(BIT_TOML, source="plant.toml")
    path = tmp_path / "plant.toml"
    path.write_text(BIT_TOML)
    run = subprocess.run(
        [sys.executable, "-m", "plcstack", "poll", str(path), "--duration", "0.1"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert run.returncode == 2
    assert "tag 'lamp'" in run.stderr and "plant.toml:7" in run.stderr
    # read-only, the same bit loads
    parse_config(BIT_TOML.replace('type = "bool", writable = true', 'type = "bool"'))
