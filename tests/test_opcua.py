"""The OPC UA server against asyncua's own client over loopback, fed by a poller of simulators.

One server per module (starting one takes about a second): an E71 simulator, a FETCH/WRITE (S5)
simulator and a third E71 that the tests stop and restart, polled every 50 ms. Anonymous sessions
may only read (the default); ``operator`` may write, ``viewer`` may not.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio

pytest.importorskip("asyncua")  # the optional extra; CI installs it with [test]

from asyncua import Client, ua
from asyncua.ua.uaerrors import UaError, UaStatusCodeError

from plcstack import values as vt
from plcstack.north.audit import Audit, AuditSettings
from plcstack.north.config import NorthConfig
from plcstack.north.opcua import OpcUaServer
from plcstack.north.opcua_config import OpcUaConfig, UserConfig, hash_password
from plcstack.north.pipeline import North
from plcstack.north.writes import WritePath
from plcstack.poll import PlcConfig, PollConfig, Poller, TagConfig
from plcstack.poll.samples import Quality, Sample
from plcstack.sim import e71, fetchwrite
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.sim.s5memory import Area, S5Memory
from tests.aio_helpers import eventually
from tests.scan_helpers import scan

pytestmark = pytest.mark.asyncio(loop_scope="module")

ROOT = Path(__file__).resolve().parent.parent

S = ua.StatusCodes
PASSWORDS = {"operator": "op-secret", "viewer": "view-secret"}


@dataclass
class Plant:
    press: MelsecMemory
    oven: S5Memory
    flaky: MelsecMemory
    flaky_sim: Any
    flaky_port: int
    poller: Poller
    server: OpcUaServer
    anonymous: Client
    operator: Client
    idx: int

    def node(self, client: Client, plc: str, tag: str) -> Any:
        return client.get_node(ua.NodeId(f"{plc}.{tag}", self.idx))


def press_memory() -> MelsecMemory:
    mem = MelsecMemory()
    mem.write_words("D", 100, [7, 0, 0x0000, 0x3FC0])  # strokes 7, force = 1.5 (low word first)
    mem.write_words("D", 110, [0xFFFF])  # raw word
    mem.write_words("D", 130, [2000])  # level: 50 %
    mem.write_words("D", 140, [0x12A4])  # not BCD: the digit A
    mem.write_bits("M", 0, [True, False, True, True])
    return mem


def oven_memory() -> S5Memory:
    mem = S5Memory(default_dbs={10: 16})
    mem.write_db_words(10, 0, [0xFFF6, 0x4120, 0x0000])  # temperature -10, setpoint 10.0
    mem.write_area(Area.FLAGS, 20, b"\x0d")
    return mem


def config(press: str, oven: str, flaky: str) -> PollConfig:
    fast = dict(timeout=0.5, connect_timeout=0.5, backoff_max=0.2)
    return PollConfig(
        (
            PlcConfig(
                "press1",
                press,
                (
                    TagConfig(
                        "strokes", "D100", vt.UINT16, writable=True, description="Press strokes"
                    ),
                    TagConfig("force", "D102", vt.FLOAT32),
                    TagConfig("raw", "D110"),
                    TagConfig("alarms", "M0", vt.BOOL, 4),
                    TagConfig("setpoints", "D120", vt.INT16, 2, writable=True),
                    TagConfig(
                        "level",
                        "D130",
                        vt.INT16,
                        scale=vt.Scale(0, 4000, 0.0, 100.0),
                        unit="%",
                        writable=True,
                    ),
                    TagConfig("bcd", "D140", vt.BCD16),
                ),
                **fast,  # type: ignore[arg-type]
            ),
            PlcConfig(
                "oven2",
                oven,
                (
                    TagConfig("temperature", "DB10.DW0", vt.INT16, unit="°C"),
                    TagConfig("setpoint", "DB10.DW1", vt.FLOAT32, writable=True),
                    TagConfig("status", "MB20", vt.UINT8),
                    TagConfig("pair", "DB10.DW3", vt.KY, writable=True),
                ),
                **fast,  # type: ignore[arg-type]
            ),
            PlcConfig(
                "flaky",
                flaky,
                (TagConfig("counter", "D0", vt.UINT16),),
                **fast,  # type: ignore[arg-type]
            ),
        ),
        groups={"default": 0.05},
    )


def server_config() -> OpcUaConfig:
    return OpcUaConfig(
        endpoint="opc.tcp://127.0.0.1:0/plcstack",
        users=(
            UserConfig("operator", hash_password(PASSWORDS["operator"], iterations=1000), True),
            UserConfig("viewer", hash_password(PASSWORDS["viewer"], iterations=1000), False),
        ),
    )


def with_login(url: str, user: str) -> str:
    return url.replace("opc.tcp://", f"opc.tcp://{user}:{PASSWORDS[user]}@")


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def plant() -> AsyncIterator[Plant]:
    press, oven, flaky = press_memory(), oven_memory(), MelsecMemory()
    sims = [await e71.start(press), await fetchwrite.start(oven), await e71.start(flaky)]
    flaky_port = int(sims[2].url.rsplit(":", 1)[1].split("?")[0])
    poller = Poller(config(*(s.url for s in sims)))
    await poller.start()
    server = OpcUaServer(poller, server_config())
    await server.start()
    feed = asyncio.create_task(North(poller, NorthConfig(), faces=[server]).run())
    anonymous = Client(server.url)
    operator = Client(with_login(server.url, "operator"))
    await anonymous.connect()
    await operator.connect()
    idx = await anonymous.get_namespace_index("urn:plcstack")
    plant = Plant(press, oven, flaky, sims[2], flaky_port, poller, server, anonymous, operator, idx)
    try:
        yield plant
    finally:
        for client in (anonymous, operator):
            await client.disconnect()
        feed.cancel()
        await asyncio.gather(feed, return_exceptions=True)
        await server.aclose()
        await poller.aclose()
        for sim in (*sims[:2], plant.flaky_sim):
            await sim.aclose()


async def wait_for(node: Any, ok: Any, limit: float = 5.0) -> ua.DataValue:
    """Read ``node`` until ``ok(data_value)``; fails with the last value after ``limit`` s."""
    deadline = time.monotonic() + limit
    while True:
        dv = await node.read_data_value(raise_on_bad_status=False)
        if ok(dv):
            return dv
        if time.monotonic() > deadline:
            pytest.fail(f"{node} never reached the expected state; last: {dv}")
        await asyncio.sleep(0.02)


def good(dv: ua.DataValue) -> bool:
    return dv.StatusCode is not None and dv.StatusCode.is_good()


# -- address space --------------------------------------------------------------------------------


async def test_browse_one_folder_per_plc_and_one_variable_per_tag(plant: Plant) -> None:
    client = plant.anonymous
    folders = {}
    for child in await client.nodes.objects.get_children():
        name = await child.read_browse_name()
        if name.NamespaceIndex == plant.idx:
            folders[name.Name] = child
    assert sorted(folders) == ["flaky", "oven2", "press1"]
    press = folders["press1"]
    assert await press.read_node_class() == ua.NodeClass.Object
    assert (await press.read_type_definition()) == ua.NodeId(ua.ObjectIds.FolderType)
    assert (await press.read_description()).Text == plant.poller.config.plcs[0].url
    names = sorted([(await c.read_browse_name()).Name for c in await press.get_children()])
    assert names == ["alarms", "bcd", "force", "level", "raw", "setpoints", "strokes"]
    expected = {
        ("press1", "strokes"): ua.VariantType.UInt16,
        ("press1", "force"): ua.VariantType.Float,
        ("press1", "raw"): ua.VariantType.UInt16,  # a raw word
        ("press1", "alarms"): ua.VariantType.Boolean,
        ("press1", "setpoints"): ua.VariantType.Int16,
        ("oven2", "temperature"): ua.VariantType.Int16,
        ("oven2", "setpoint"): ua.VariantType.Float,
        ("oven2", "status"): ua.VariantType.Byte,
        ("press1", "level"): ua.VariantType.Double,  # scaled: engineering units
        ("press1", "bcd"): ua.VariantType.UInt16,
    }
    for (plc, tag), vtype in expected.items():
        node = plant.node(client, plc, tag)
        assert await node.read_data_type() == ua.NodeId(vtype.value), (plc, tag)
        assert await node.read_node_class() == ua.NodeClass.Variable
    alarms = plant.node(client, "press1", "alarms")
    assert await alarms.read_value_rank() == ua.ValueRank.OneDimension
    assert await alarms.read_array_dimensions() == [4]
    assert (await alarms.read_description()).Text == "M0 bool x4"
    strokes = plant.node(client, "press1", "strokes")
    assert (await strokes.read_description()).Text == "Press strokes (D100 uint16)"
    assert await strokes.read_value_rank() == ua.ValueRank.Scalar
    read_write = {ua.AccessLevel.CurrentRead, ua.AccessLevel.CurrentWrite}
    assert set(await strokes.get_access_level()) == read_write
    assert set(await plant.node(client, "press1", "force").get_access_level()) == {
        ua.AccessLevel.CurrentRead
    }
    interval = await strokes.read_attribute(ua.AttributeIds.MinimumSamplingInterval)
    assert interval.Value.Value == pytest.approx(50.0)


async def test_a_scaled_tag_is_an_analog_item_with_its_range_and_unit(plant: Plant) -> None:
    client = plant.anonymous
    level = plant.node(client, "press1", "level")
    assert await level.read_type_definition() == ua.NodeId(ua.ObjectIds.AnalogItemType)
    props = {(await p.read_browse_name()).Name: p for p in await level.get_properties()}
    assert set(props) == {"EURange", "EngineeringUnits"}
    assert await props["EURange"].read_value() == ua.Range(0.0, 100.0)
    unit = await props["EngineeringUnits"].read_value()
    assert unit.DisplayName.Text == "%"
    assert unit.NamespaceUri == "http://www.opcfoundation.org/UA/units/un/cefact"
    assert unit.UnitId == (ord("P") << 8) | ord("1")  # UNECE "P1": percent
    # a unit without scaling: BaseAnalogType with EngineeringUnits only
    temperature = plant.node(client, "oven2", "temperature")
    assert await temperature.read_type_definition() == ua.NodeId(ua.ObjectIds.BaseAnalogType)
    (prop,) = await temperature.get_properties()
    assert (await prop.read_value()).UnitId == 0x43454C  # "CEL"
    # no unit, no scale: a plain variable without properties
    assert await plant.node(client, "press1", "force").get_properties() == []
    # values and writes are in engineering units
    dv = await wait_for(level, good)
    assert dv.Value.Value == pytest.approx(50.0)
    await plant.node(plant.operator, "press1", "level").write_value(
        ua.DataValue(ua.Variant(25.0, ua.VariantType.Double))
    )
    assert plant.press.read_words("D", 130, 1) == [1000]


# -- reads ----------------------------------------------------------------------------------------


async def test_read_gives_the_plc_values_with_their_types_and_source_time(plant: Plant) -> None:
    client = plant.anonymous
    expected = {
        ("press1", "force"): 1.5,
        ("press1", "raw"): 0xFFFF,
        ("press1", "alarms"): [True, False, True, True],
        ("oven2", "temperature"): -10,
        ("oven2", "setpoint"): 10.0,
        ("oven2", "status"): 13,
    }
    for (plc, tag), value in expected.items():
        dv = await wait_for(plant.node(client, plc, tag), good)
        assert dv.Value is not None and dv.Value.Value == value, (plc, tag)
    dv = await plant.node(client, "press1", "force").read_data_value()
    assert dv.SourceTimestamp is not None and dv.ServerTimestamp is not None
    # the source time is when the poller sent the request: before the server took the sample
    assert dv.SourceTimestamp <= dv.ServerTimestamp
    assert abs(dv.SourceTimestamp.timestamp() - time.time()) < 60


async def test_points_that_are_no_value_of_the_type_read_bad_out_of_range(plant: Plant) -> None:
    node = plant.node(plant.anonymous, "press1", "bcd")
    dv = await wait_for(
        node, lambda dv: not good(dv) and dv.StatusCode.value != S.BadWaitingForInitialData
    )
    assert dv.StatusCode.value == S.BadOutOfRange


async def test_unchanged_samples_keep_the_time_of_the_last_change(plant: Plant) -> None:
    node = plant.node(plant.anonymous, "press1", "force")
    first = await wait_for(node, good)
    skipped = plant.server.unchanged
    await eventually(lambda: plant.server.unchanged >= skipped + 3, "more scans, same value")
    again = await node.read_data_value()
    assert again.SourceTimestamp == first.SourceTimestamp
    assert plant.server.unchanged > 0


# -- subscriptions --------------------------------------------------------------------------------


class Changes:
    """asyncua subscription handler: every data change into a queue."""

    def __init__(self) -> None:
        self.queue: asyncio.Queue[tuple[Any, ua.DataValue]] = asyncio.Queue()

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.queue.put_nowait((val, data.monitored_item.Value))

    async def until(self, ok: Any, limit: float = 5.0) -> ua.DataValue:
        async with asyncio.timeout(limit):
            while True:
                value, dv = await self.queue.get()
                if ok(value, dv):
                    return dv


async def test_subscription_hears_when_the_simulator_memory_changes(plant: Plant) -> None:
    handler = Changes()
    sub = await plant.anonymous.create_subscription(20, handler)
    try:
        node = plant.node(plant.anonymous, "oven2", "temperature")
        await sub.subscribe_data_change(node)
        await handler.until(lambda v, dv: v == -10)  # the initial notification
        plant.oven.write_db_words(10, 0, [321])
        dv = await handler.until(lambda v, dv: v == 321)
        assert dv.StatusCode is None or dv.StatusCode.is_good()
    finally:
        await sub.delete()


# -- writes ---------------------------------------------------------------------------------------


async def test_write_completes_when_the_plc_confirmed_it(plant: Plant) -> None:
    node = plant.node(plant.operator, "press1", "strokes")
    await node.write_value(ua.DataValue(ua.Variant(1234, ua.VariantType.UInt16)))
    # the response came after the PLC's confirmation: the simulator holds the value now
    assert plant.press.read_words("D", 100, 1) == [1234]
    await wait_for(node, lambda dv: good(dv) and dv.Value.Value == 1234)

    setpoint = plant.node(plant.operator, "oven2", "setpoint")
    await setpoint.write_value(ua.DataValue(ua.Variant(-2.5, ua.VariantType.Float)))
    assert plant.oven.read_db_words(10, 1, 2) == [0xC020, 0x0000]  # -2.5, S5 high word first

    array = plant.node(plant.operator, "press1", "setpoints")
    await array.write_value(ua.DataValue(ua.Variant([-1, 300], ua.VariantType.Int16)))
    assert plant.press.read_words("D", 120, 2) == [0xFFFF, 300]

    # KY reads as STEP 5 shows it ("12,255") and is written the same way
    pair = plant.node(plant.operator, "oven2", "pair")
    await pair.write_value(ua.DataValue(ua.Variant("12,255", ua.VariantType.String)))
    assert plant.oven.read_db_words(10, 3, 1) == [0x0CFF]
    await wait_for(pair, lambda dv: good(dv) and dv.Value.Value == "12,255")
    with pytest.raises(UaStatusCodeError) as err:
        await pair.write_value(ua.DataValue(ua.Variant("12", ua.VariantType.String)))
    assert err.value.code == S.BadTypeMismatch


async def test_write_refused_for_a_read_only_tag(plant: Plant) -> None:
    node = plant.node(plant.operator, "press1", "force")
    before = plant.press.read_words("D", 102, 2)
    with pytest.raises(UaStatusCodeError) as err:
        await node.write_value(ua.DataValue(ua.Variant(9.0, ua.VariantType.Float)))
    assert err.value.code == S.BadNotWritable
    assert plant.press.read_words("D", 102, 2) == before


async def test_write_refused_for_a_plc_error_says_device_failure(plant: Plant) -> None:
    node = plant.node(plant.operator, "press1", "strokes")
    plant.press.write_words("D", 100, [5])
    plant.press.write_in_run = False  # the E71 answers 55H: no writes while the CPU runs
    try:
        with pytest.raises(UaStatusCodeError) as err:
            await node.write_value(ua.DataValue(ua.Variant(6, ua.VariantType.UInt16)))
        assert err.value.code == S.BadDeviceFailure
    finally:
        plant.press.write_in_run = True
    assert plant.press.read_words("D", 100, 1) == [5]


async def test_write_refused_for_anonymous_and_read_only_users(plant: Plant) -> None:
    node = plant.node(plant.anonymous, "press1", "strokes")
    plant.press.write_words("D", 100, [8])
    with pytest.raises(UaStatusCodeError) as err:
        await node.write_value(ua.DataValue(ua.Variant(9, ua.VariantType.UInt16)))
    assert err.value.code == S.BadUserAccessDenied
    async with Client(with_login(plant.server.url, "viewer")) as viewer:
        with pytest.raises(UaStatusCodeError) as err:
            await plant.node(viewer, "press1", "strokes").write_value(
                ua.DataValue(ua.Variant(9, ua.VariantType.UInt16))
            )
        assert err.value.code == S.BadUserAccessDenied
    assert plant.press.read_words("D", 100, 1) == [8]


async def test_wrong_password_is_refused(plant: Plant) -> None:
    url = plant.server.url.replace("opc.tcp://", "opc.tcp://operator:wrong@")
    with pytest.raises(UaStatusCodeError):
        async with Client(url):
            pass


async def test_write_of_a_wrong_type_or_length_is_refused_before_anything_is_sent(
    plant: Plant,
) -> None:
    writes = plant.poller.stats["press1"].writes
    strokes = plant.node(plant.operator, "press1", "strokes")
    with pytest.raises(UaStatusCodeError) as err:
        await strokes.write_value(ua.DataValue(ua.Variant(5, ua.VariantType.Int32)))
    assert err.value.code == S.BadTypeMismatch
    array = plant.node(plant.operator, "press1", "setpoints")
    with pytest.raises(UaStatusCodeError) as err:
        await array.write_value(ua.DataValue(ua.Variant([1, 2, 3], ua.VariantType.Int16)))
    assert err.value.code == S.BadTypeMismatch
    assert plant.poller.stats["press1"].writes == writes


async def test_one_write_request_gets_one_status_per_item(plant: Plant) -> None:
    strokes = plant.node(plant.operator, "press1", "strokes")
    force = plant.node(plant.operator, "press1", "force")
    setpoint = plant.node(plant.operator, "oven2", "setpoint")
    results = await plant.operator.uaclient.write_attributes(
        [strokes.nodeid, force.nodeid, setpoint.nodeid],
        [
            ua.DataValue(ua.Variant(77, ua.VariantType.UInt16)),
            ua.DataValue(ua.Variant(1.0, ua.VariantType.Float)),
            ua.DataValue(ua.Variant(3.0, ua.VariantType.Float)),
        ],
        ua.AttributeIds.Value,
    )
    assert [r.value for r in results] == [S.Good, S.BadNotWritable, S.Good]
    assert plant.press.read_words("D", 100, 1) == [77]
    assert plant.oven.read_db_words(10, 1, 2) == [0x4040, 0x0000]


async def test_the_servers_own_updates_never_reach_the_plc(plant: Plant) -> None:
    writes = {name: st.writes for name, st in plant.poller.stats.items()}
    await asyncio.sleep(0.3)  # a few scans: every changed sample went into the address space
    assert {name: st.writes for name, st in plant.poller.stats.items()} == writes
    # a write through the server's internal session (not a client's login) is refused too
    internal = plant.server.server.get_node(plant.server.nodeid("press1", "strokes"))
    with pytest.raises(UaStatusCodeError) as err:
        await internal.write_value(ua.DataValue(ua.Variant(4321, ua.VariantType.UInt16)))
    assert err.value.code == S.BadUserAccessDenied
    assert plant.press.read_words("D", 100, 1) != [4321]


# -- a dead PLC -----------------------------------------------------------------------------------


async def test_a_dead_plcs_variables_go_bad_and_recover(plant: Plant) -> None:
    node = plant.node(plant.anonymous, "flaky", "counter")
    plant.flaky.write_words("D", 0, [11])
    await wait_for(node, lambda dv: good(dv) and dv.Value.Value == 11)
    await plant.flaky_sim.aclose()
    dead = {S.BadNoCommunication, S.BadCommunicationError, S.BadTimeout}
    dv = await wait_for(node, lambda dv: dv.StatusCode.value in dead)
    assert dv.Value is None or dv.Value.Value is None  # Bad: no value (Part 4, 7.7.1)
    # the PLC restarts on the same port with a new value
    plant.flaky.write_words("D", 0, [12])
    plant.flaky_sim = await e71.start(plant.flaky, port=plant.flaky_port)
    await wait_for(node, lambda dv: good(dv) and dv.Value.Value == 12)


# -- the command line -----------------------------------------------------------------------------


@pytest.mark.slow  # a second process that starts its own server: several seconds
async def test_serve_opcua_command_serves_and_writes_until_sigterm(tmp_path: Path) -> None:
    memory = MelsecMemory()
    memory.write_words("D", 100, [5])
    sim = await e71.start(memory)
    path = tmp_path / "plant.toml"
    path.write_text(
        f"""
[poll]
interval = 0.05

[opcua]
listen = "127.0.0.1:0"
anonymous = "write"

[audit]
path = "writes.jsonl"

[[plc]]
name = "press1"
url = "{sim.url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16", writable = true }}
""",
        encoding="utf-8",
    )
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "plcstack",
        "serve",
        "opcua",
        str(path),
        stderr=asyncio.subprocess.PIPE,
        cwd=ROOT,
    )
    try:
        assert proc.stderr is not None
        async with asyncio.timeout(30):
            while b"listening on" not in (line := await proc.stderr.readline()):
                assert line, "the server ended before listening"
        url = line.decode().rsplit(" ", 1)[1].strip()
        async with Client(url) as client:
            idx = await client.get_namespace_index("urn:plcstack")
            node = client.get_node(ua.NodeId("press1.strokes", idx))
            assert (await wait_for(node, good)).Value.Value == 5
            await node.write_value(ua.DataValue(ua.Variant(6, ua.VariantType.UInt16)))
            assert memory.read_words("D", 100, 1) == [6]
        proc.send_signal(signal.SIGTERM)
        rest = await asyncio.wait_for(proc.stderr.read(), 30)
        assert await proc.wait() == 0
        assert b"press1" in rest  # the statistics table
        # the write's audit line holds the value before it, as serve modbus's and poll's do
        audit = [json.loads(line) for line in (tmp_path / "writes.jsonl").read_text().splitlines()]
        assert [(a["source"], a["tag"], a["previous"], a["value"], a["result"]) for a in audit] == [
            ("opcua", "strokes", 5, 6, "ok")
        ]
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        await sim.aclose()


async def test_submit_is_the_sink_interface_and_keeps_the_newest_sample_per_tag(
    plant: Plant,
) -> None:
    # submit as the runtime calls it, beside the runtime's own feed: never blocks
    server = plant.server
    handler = Changes()
    sub = await plant.anonymous.create_subscription(10, handler)
    try:
        await sub.subscribe_data_change(plant.node(plant.anonymous, "oven2", "status"))
        await handler.until(lambda v, dv: v == 13)
        # the PLC says 2 too from now on: the runtime's feed goes on polling, and a polled
        # sample that comes while the submitted one waits replaces it (the newest wins); with
        # the 13 it replaced the 2 for good on a loaded machine and no change was ever seen
        plant.oven.write_area(Area.FLAGS, 20, b"\x02")
        before = server.coalesced
        now = time.time()
        server.submit(
            [
                scan(Sample("press1", "nosuch", 1, Quality.GOOD, now, now)),  # unknown: ignored
                scan(Sample("oven2", "status", 1, Quality.GOOD, now, now)),
                scan(Sample("oven2", "status", 2, Quality.GOOD, now, now)),  # replaces the 1
            ]
        )
        # the 1 is replaced by the 2 (and a polled sample of the tag that was still waiting,
        # if the runtime's feed had just put one there, by the 1 before it)
        assert server.coalesced - before in (1, 2)
        seen = await handler.until(lambda v, dv: v != 13)
        assert seen.Value is not None and seen.Value.Value == 2
    finally:
        plant.oven.write_area(Area.FLAGS, 20, b"\x0d")
        await sub.delete()


# -- security policies ----------------------------------------------------------------------------


async def make_certificate(directory: Path, name: str, uri: str, server: bool) -> tuple[Path, Path]:
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key, cert = directory / f"{name}-key.pem", directory / f"{name}-cert.der"
    use = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
    await setup_self_signed_certificate(
        key, cert, uri, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH, use], {"commonName": name}
    )
    return cert, key


@pytest.mark.slow  # a second server, RSA keys: several seconds
async def test_an_encrypting_policy_a_trust_list_and_no_anonymous_logins(
    tmp_path: Path,
) -> None:
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    server_cert, server_key = await make_certificate(
        tmp_path, "server", "urn:plcstack:server", True
    )
    client_cert, client_key = await make_certificate(tmp_path, "client", "urn:test:client", False)
    other_cert, other_key = await make_certificate(tmp_path, "other", "urn:test:other", False)
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    (trusted / "client.der").write_bytes(client_cert.read_bytes())
    memory = press_memory()
    sim = await e71.start(memory)
    poller = Poller(
        PollConfig(
            (PlcConfig("press1", sim.url, (TagConfig("strokes", "D100", vt.UINT16),)),),
            groups={"default": 0.05},
        )
    )
    config = OpcUaConfig(
        endpoint="opc.tcp://127.0.0.1:0/plcstack",
        certificate=server_cert,
        private_key=server_key,
        security_policies=("Basic256Sha256_SignAndEncrypt",),
        trusted_client_certificates=trusted,
        anonymous="none",
        users=(UserConfig("operator", hash_password(PASSWORDS["operator"], iterations=1000)),),
    )
    try:
        async with poller, OpcUaServer(poller, config) as server:
            feed = asyncio.create_task(North(poller, NorthConfig(), faces=[server]).run())
            try:
                # the only endpoint encrypts: a client without security is turned away
                with pytest.raises(UaError, match="No matching endpoints"):
                    async with Client(with_login(server.url, "operator")) as plain:
                        await plain.nodes.objects.get_children()
                secure = Client(with_login(server.url, "operator"))
                secure.application_uri = "urn:test:client"  # as in its certificate
                await secure.set_security(
                    SecurityPolicyBasic256Sha256,
                    str(client_cert),
                    str(client_key),
                    mode=ua.MessageSecurityMode.SignAndEncrypt,
                )
                async with secure:
                    idx = await secure.get_namespace_index("urn:plcstack")
                    node = secure.get_node(ua.NodeId("press1.strokes", idx))
                    assert (await wait_for(node, good)).Value.Value == 7
                # a certificate outside the trust list is refused, login or not
                stranger = Client(with_login(server.url, "operator"))
                stranger.application_uri = "urn:test:other"
                await stranger.set_security(
                    SecurityPolicyBasic256Sha256,
                    str(other_cert),
                    str(other_key),
                    mode=ua.MessageSecurityMode.SignAndEncrypt,
                )
                with pytest.raises(UaStatusCodeError) as err:
                    async with stranger:
                        pass
                assert err.value.code == S.BadCertificateUntrusted
                # without a login (anonymous = "none") even an encrypted session is refused
                anonymous = Client(server.url)
                anonymous.application_uri = "urn:test:client"
                await anonymous.set_security(
                    SecurityPolicyBasic256Sha256,
                    str(client_cert),
                    str(client_key),
                    mode=ua.MessageSecurityMode.SignAndEncrypt,
                )
                with pytest.raises(UaStatusCodeError):
                    async with anonymous:
                        pass
            finally:
                feed.cancel()
                await asyncio.gather(feed, return_exceptions=True)
    finally:
        await sim.aclose()


def local_address(client: Client) -> str:
    """The ``host:port`` a connected asyncua client speaks from (what the server sees)."""
    protocol = client.uaclient.protocol
    assert protocol is not None and protocol.transport is not None
    host, port = protocol.transport.get_extra_info("sockname")[:2]
    return f"{host}:{port}"


async def test_every_opcua_write_attempt_is_audited_with_the_sessions_login(
    plant: Plant, tmp_path: Path
) -> None:
    audit = Audit(AuditSettings(str(tmp_path / "audit.jsonl")))
    audit.open()
    writes = plant.server.writes
    plant.server.writes = WritePath(plant.poller, audit=audit)
    try:
        node = plant.node(plant.operator, "press1", "strokes")
        await node.write_value(ua.DataValue(ua.Variant(77, ua.VariantType.UInt16)))
        with pytest.raises(UaStatusCodeError):  # anonymous: refused before the write path
            await plant.node(plant.anonymous, "press1", "strokes").write_value(
                ua.DataValue(ua.Variant(78, ua.VariantType.UInt16))
            )
        with pytest.raises(UaStatusCodeError):  # a value the tag's type cannot take
            await node.write_value(ua.DataValue(ua.Variant("x", ua.VariantType.String)))
    finally:
        plant.server.writes = writes
        audit.close()
    lines = [json.loads(line) for line in (tmp_path / "audit.jsonl").read_text().splitlines()]
    seen = [(r["source"], r["user"], r["plc"], r["tag"], r["value"], r["result"]) for r in lines]
    assert seen == [
        ("opcua", "operator", "press1", "strokes", 77, "ok"),
        ("opcua", None, "press1", "strokes", 78, "unauthorized"),
        ("opcua", "operator", "press1", "strokes", "x", "wrong_type"),
    ]
    assert [r["may_have_executed"] for r in lines] == [True, False, False]
    # which machine: each session's client address, the anonymous one's refusal included
    operator, anonymous = local_address(plant.operator), local_address(plant.anonymous)
    assert operator != anonymous
    assert [r["peer"] for r in lines] == [operator, anonymous, operator]


async def test_a_second_clients_refused_write_is_said_again(
    plant: Plant, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: the repeat suppression keyed on (source, PLC, tag), so a second client refused
    the same tag was only at DEBUG; now each client (address and login) is said once."""
    writes = plant.server.writes
    plant.server.writes = WritePath(plant.poller)
    try:
        async with Client(plant.server.url) as second:
            clients = (plant.anonymous, second, plant.anonymous, second)
            with caplog.at_level(logging.DEBUG, "plcstack.north.writes"):
                for client in clients:
                    with pytest.raises(UaStatusCodeError):
                        await plant.node(client, "press1", "strokes").write_value(
                            ua.DataValue(ua.Variant(9, ua.VariantType.UInt16))
                        )
            addresses = [local_address(plant.anonymous), local_address(second)]
    finally:
        plant.server.writes = writes
    refused = [r for r in caplog.records if "refused (unauthorized)" in r.getMessage()]
    assert [r.levelno for r in refused] == [logging.WARNING] * 2 + [logging.DEBUG] * 2
    for record, address in zip(refused[:2], addresses, strict=True):
        assert record.getMessage().endswith(f"(client {address})")
