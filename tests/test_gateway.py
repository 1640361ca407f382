"""The AS511 gateway: plcstack's own S5-LAN and FETCH/WRITE clients against the gateway in front
of the AS511 simulator on a real pseudo-terminal (and over TCP where the test is about the
queue), at full speed and at emulated 9600 baud."""

from __future__ import annotations

import asyncio
import dataclasses
import os
import re
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import pytest

from plcstack import gateway
from plcstack.cli import build_parser
from plcstack.cli.gateway import face_settings
from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.config import parse_config
from plcstack.errors import AddressError, PlcErrorResponse
from plcstack.gateway.allow import WriteAllowList
from plcstack.sim import as511 as sim_as511
from plcstack.sim import e71 as sim_e71
from plcstack.sim.base import Simulator
from plcstack.sim.s5memory import Area, BlockType
from plcstack.sim.s5store import ABSOLUTE, FAULT_CODES, FaultKind
from tests.robust_helpers import GOOD

ROOT = Path(__file__).resolve().parents[1]
LOOP = ("127.0.0.1", 0)


def machine(s: Simulator) -> sim_as511.AS511Machine:
    m = getattr(s, "machine", None)
    assert isinstance(m, sim_as511.AS511Machine)
    return m


@asynccontextmanager
async def running(
    *,
    pty: bool = True,
    baud: int | None = None,
    char_timeout: float = GOOD,
    **options: object,
) -> AsyncIterator[tuple[Simulator, gateway.Gateway]]:
    """An AS511 simulator and a gateway in front of it, serving S5-LAN and FETCH/WRITE.

    The gateway's AS511 client waits ``char_timeout`` for each character of the line: long by
    default, since the simulator runs in the test's own event loop and a loaded machine can stall
    that loop for hundreds of milliseconds between two characters (a 0.3 s wait answered
    requests with "Err 9: timeout" under load). Only a test about a dead line sets it short."""
    sim: Simulator = await (sim_as511.start_pty(baud=baud) if pty else sim_as511.start(baud=baud))
    async with sim:
        plc = connect(sim.url, nak_backoff=0.05, char_timeout=char_timeout)
        assert isinstance(plc, AS511Client)
        gw = await gateway.start(plc, s5lan=LOOP, fetchwrite=LOOP, **options)  # type: ignore[arg-type]
        async with gw:
            yield sim, gw


def urls(gw: gateway.Gateway) -> tuple[str, str]:
    assert gw.s5lan is not None and gw.fetchwrite is not None
    return gw.s5lan.url, gw.fetchwrite.url


async def test_reads_and_writes_reach_the_plc_through_both_protocols() -> None:
    async with running(writable="DB5, M") as (sim, gw):
        mem = machine(sim).memory
        lan_url, fw_url = urls(gw)
        async with connect(lan_url) as lan, connect(fw_url) as fw:
            # DBn.DWk = n * 100h + k in the AS511 simulator's default memory
            assert await lan.read("DB5.DW0", 4) == [0x0500, 0x0501, 0x0502, 0x0503]
            assert await fw.read("DB7.DW10", 2) == [0x070A, 0x070B]
            await lan.write("DB5.DW3", [0x1234])
            assert mem.read_db_words(5, 3, 1) == [0x1234]
            await fw.write("DB5.DW4", [0xBEEF, 0x0001])
            assert mem.read_db_words(5, 4, 2) == [0xBEEF, 0x0001]
            await lan.write("MB10", [7, 8])
            assert await fw.read("MB10", 2) == [7, 8]
            assert mem.read_area(Area.FLAGS, 10, 2) == b"\x07\x08"
            # word areas: timers travel as words through both servers
            mem.write_area(Area.TIMERS, 2 * 3, b"\x12\x34")
            assert await lan.read("T3") == [0x1234]
            assert await fw.read("T3") == [0x1234]
        assert gw.stats.line_writes == 3 and gw.stats.denied == 0


async def test_write_outside_the_allow_list_is_refused_without_touching_the_plc() -> None:
    async with running() as (sim, gw):  # default: nothing writable
        m = machine(sim)
        lan_url, fw_url = urls(gw)
        async with connect(lan_url) as lan, connect(fw_url) as fw:
            before = m.requests
            with pytest.raises(PlcErrorResponse) as lan_err:
                await lan.write("DB5.DW0", [1])
            assert lan_err.value.code == FAULT_CODES[FaultKind.WRITE_DENIED][0] == 6
            # the client's line names the refusal, not only "incorrect request format"
            assert "gateway refuses so a write outside its --writable" in str(lan_err.value)
            with pytest.raises(PlcErrorResponse) as fw_err:
                await fw.write("MB0", [1])
            assert fw_err.value.code == FAULT_CODES[FaultKind.WRITE_DENIED][1] == 0x01
            assert m.requests == before  # the line was never used
            assert m.memory.read_db_words(5, 0, 1) == [0x0500]
            assert await lan.read("DB5.DW0") == [0x0500]  # reads are still served
        assert gw.stats.denied == 2


async def test_missing_block_and_short_block_map_to_the_protocols_codes() -> None:
    async with running() as (_sim, gw):
        lan_url, fw_url = urls(gw)
        async with connect(lan_url) as lan, connect(fw_url) as fw:
            for plc in (lan, fw):
                with pytest.raises(PlcErrorResponse) as missing:
                    await plc.read("DB50.DW0")
                assert missing.value.code == 2  # both: block does not exist
                with pytest.raises(PlcErrorResponse) as short:
                    await plc.read("DB5.DW250", 10)  # DB5 has 256 data words
                assert short.value.code == 3  # both: block too small
            assert await lan.read("DB5.DW255") == [0x05FF]


async def test_nak_and_dead_line_answer_promptly_and_recover() -> None:
    async with running(char_timeout=0.3) as (sim, gw):
        m = machine(sim)
        lan_url, fw_url = urls(gw)
        async with connect(lan_url) as lan, connect(fw_url) as fw:
            m.busy = True  # DLE NAK after STX: the PLC refuses
            with pytest.raises(PlcErrorResponse) as lan_nak:
                await lan.read("MB0")
            assert lan_nak.value.code == 9
            with pytest.raises(PlcErrorResponse) as fw_nak:
                await fw.read("MB0")
            assert fw_nak.value.code == 0x01
            m.busy = False
            # a dead cable: answered with the timeout codes (char_timeout 0.3 s each) before
            # the clients' own deadlines, which would raise PlcTimeout instead
            m.mute = True
            with pytest.raises(PlcErrorResponse) as lan_dead:
                await lan.read("MB0")
            assert lan_dead.value.code == 9
            with pytest.raises(PlcErrorResponse) as fw_dead:
                await fw.read("MB0")
            assert fw_dead.value.code == 0x04
            m.mute = False
            for _ in range(50):  # the AS511 side comes back (after its backoff)
                try:
                    assert await lan.read("DB5.DW1") == [0x0501]
                    break
                except PlcErrorResponse as exc:
                    assert exc.code == 9
                    await asyncio.sleep(0.1)
            else:
                pytest.fail("the gateway did not recover after the line came back")


async def test_concurrent_clients_share_one_line_with_consistent_values() -> None:
    async with running(writable="DB1-10") as (sim, gw):
        mem = machine(sim).memory
        lan_url, fw_url = urls(gw)

        async def worker(k: int) -> None:
            url = lan_url if k % 2 else fw_url
            async with connect(url) as plc:
                for i in range(8):
                    value = (k << 8) | i
                    await plc.write(f"DB{k + 1}.DW{i}", [value])
                    assert await plc.read(f"DB{k + 1}.DW{i}") == [value]
                    # another client's block: a value it wrote or the original, never a mix
                    other = (k + 1) % 6
                    seen = (await plc.read(f"DB{other + 1}.DW0"))[0]
                    assert seen in ((other + 1) << 8, other << 8)

        await asyncio.gather(*(worker(k) for k in range(6)))
        for k in range(6):
            assert mem.read_db_words(k + 1, 0, 8) == [(k << 8) | i for i in range(8)]
        assert gw.stats.line_writes == 48 and gw.stats.failed == 0


async def test_request_that_waits_past_its_deadline_is_not_executed() -> None:
    # 9600 baud: each write takes tens of ms on the line; max_wait 0.05 s expires the tail
    async with running(pty=False, baud=9600, writable="DB1-10", max_wait=0.05) as (sim, gw):
        mem = machine(sim).memory
        lan_url, _ = urls(gw)
        clients = [connect(lan_url) for _ in range(6)]
        for c in clients:
            await c.aopen()
        try:
            results = await asyncio.gather(
                *(c.write(f"DB{k + 1}.DW0", [0xAAAA]) for k, c in enumerate(clients)),
                return_exceptions=True,
            )
        finally:
            for c in clients:
                await c.aclose()
        failed = [k for k, r in enumerate(results) if isinstance(r, BaseException)]
        assert failed, "expected some requests to expire in the queue"
        for k, r in enumerate(results):
            written = mem.read_db_words(k + 1, 0, 1) == [0xAAAA]
            if isinstance(r, PlcErrorResponse):
                assert r.code == 9 and not written  # answered "timeout", and truly not executed
            else:
                assert r is None and written
        assert gw.stats.expired == len(failed)


async def test_full_queue_answers_busy() -> None:
    async with running(pty=False, baud=9600, queue_size=1, max_wait=5.0) as (_sim, gw):
        _, fw_url = urls(gw)
        clients = [connect(fw_url) for _ in range(4)]
        for c in clients:
            await c.aopen()
        try:
            results = await asyncio.gather(
                *(c.read("DB1.DW0", 64) for c in clients), return_exceptions=True
            )
        finally:
            for c in clients:
                await c.aclose()
        busy = [r for r in results if isinstance(r, PlcErrorResponse)]
        assert busy and all(r.code == FAULT_CODES[FaultKind.BUSY][1] for r in busy)
        assert any(isinstance(r, list) for r in results)
        assert gw.stats.busy == len(busy)


async def test_read_cache_serves_repeats_and_writes_invalidate_it() -> None:
    async with running(writable="DB2", cache_max_age=30.0) as (sim, gw):
        m = machine(sim)
        lan_url, fw_url = urls(gw)
        async with connect(lan_url) as lan, connect(fw_url) as fw:
            assert await lan.read("DB2.DW0", 10) == [0x0200 + i for i in range(10)]
            requests = m.requests
            for _ in range(5):  # ten SCADA clients polling the same DB: one AS511 read
                assert await fw.read("DB2.DW2", 4) == [0x0202 + i for i in range(4)]
                assert await lan.read("DB2.DW0", 10) == [0x0200 + i for i in range(10)]
            assert m.requests == requests and gw.stats.cache_hits == 10
            await fw.write("DB2.DW3", [0x4242])
            assert (await lan.read("DB2.DW0", 10))[3] == 0x4242  # invalidated, read again
            assert gw.stats.line_reads == 2


async def test_without_cache_every_read_uses_the_line() -> None:
    async with running() as (_sim, gw):
        lan_url, _ = urls(gw)
        async with connect(lan_url) as lan:
            for _ in range(3):
                await lan.read("DB2.DW0", 2)
        assert gw.stats.line_reads == 3 and gw.stats.cache_hits == 0


async def test_gateway_at_emulated_9600_baud_over_a_pty() -> None:
    async with running(baud=9600, writable="DB3") as (sim, gw):
        lan_url, fw_url = urls(gw)
        async with connect(lan_url) as lan, connect(fw_url) as fw:
            assert await lan.read("DB3.DW0", 64) == [0x0300 + i for i in range(64)]
            await fw.write("DB3.DW0", list(range(32)))
            assert machine(sim).memory.read_db_words(3, 0, 32) == list(range(32))


def test_allow_list_parsing() -> None:
    allow = WriteAllowList.parse("DB10-20, dx3 M q")
    assert allow.allows((BlockType.DB, 10)) and allow.allows((BlockType.DB, 20))
    assert not allow.allows((BlockType.DB, 21)) and not allow.allows((BlockType.DB, 9))
    assert allow.allows((BlockType.DX, 3)) and not allow.allows((BlockType.DX, 4))
    assert allow.allows(Area.FLAGS) and allow.allows(Area.OUTPUTS)
    assert not allow.allows(Area.INPUTS) and not allow.allows(ABSOLUTE)
    nothing = WriteAllowList.parse("")
    assert not any(nothing.allows(t) for t in (Area.FLAGS, (BlockType.DB, 1), ABSOLUTE))
    assert str(nothing) == "nothing"
    everything = WriteAllowList.parse("*")
    assert everything.allows(ABSOLUTE) and everything.allows((BlockType.DX, 255))
    for bad in ("DB0", "DB20-10", "DB256", "X", "DB"):
        with pytest.raises(AddressError, match="writable"):
            WriteAllowList.parse(bad)


async def test_gateway_needs_a_server_and_an_s5_plc() -> None:
    with pytest.raises(AddressError, match="--s5lan and/or --fetchwrite"):
        await gateway.start("as511+tcp://127.0.0.1:1")
    with pytest.raises(AddressError, match="needs an S5 PLC"):
        await gateway.start("e71+tcp://127.0.0.1:1", s5lan=LOOP)
    with pytest.raises(AddressError, match="needs an E71 PLC"):
        await gateway.start("s5lan://127.0.0.1:1", e71=LOOP)


SHORTCUT = [
    ("s5lan://10.0.0.6:5010", "--s5lan", "0.0.0.0:2000", "--fetchwrite", "2001", "--mk",
     "--writable", "DB10-20, M", "--queue-size", "8", "--max-wait", "0.5"),
    ("e71+tcp://10.0.0.5:5000", "--e71", "5000", "--e71-udp", "0.0.0.0:5001", "--e71-code",
     "ascii", "--writable", "D100-199"),
    ("as511:///dev/ttyUSB0", "--as511", "0.0.0.0:5021", "--s5lan", "5010",
     "--s5lan-connections", "4"),
]  # fmt: skip
ENTRIES = [
    """
[[gateway]]
protocol = "s5lan"
listen = "0.0.0.0:2000"
plc = "p"
writable = "DB10-20, M"
queue = 8
max_wait = 0.5

[[gateway]]
protocol = "fetchwrite"
listen = "127.0.0.1:2001"
plc = "p"
mk = true
writable = "DB10-20, M"
queue = 8
max_wait = 0.5
""",
    """
[[gateway]]
protocol = "e71"
listen = "127.0.0.1:5000"
plc = "p"
code = "ascii"
writable = "D100-199"

[[gateway]]
protocol = "e71"
listen = "0.0.0.0:5001"
plc = "p"
transport = "udp"
code = "ascii"
writable = "D100-199"
""",
    """
[[gateway]]
protocol = "s5lan"
listen = "127.0.0.1:5010"
plc = "p"
max_connections = 4

[[gateway]]
protocol = "as511"
listen = "0.0.0.0:5021"
plc = "p"
""",
]


@pytest.mark.parametrize(("argv", "entries"), list(zip(SHORTCUT, ENTRIES, strict=True)))
def test_the_command_is_a_shortcut_for_the_gateway_entries_of_a_file(
    argv: tuple[str, ...], entries: str
) -> None:
    """plcstack gateway's options are the [[gateway]] entries of one PLC, run by the same code
    (the PLC named by its URL); the defaults are the entries' own."""
    args = build_parser().parse_args(["gateway", *argv])
    url = argv[0]
    plc = f'[[plc]]\nname = "p"\nurl = "{url}"\n[plc.tags]\nv = "{_TAG[url[:3]]}"\n'
    faces = parse_config(plc + entries).gateway
    assert face_settings(args) == [dataclasses.replace(f, plc=url) for f in faces]


_TAG = {"s5l": "DB1.DW0", "e71": "D0", "as5": "DB1.DW0"}


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


async def test_cli_gateway_serves_and_exits_cleanly() -> None:
    async with await sim_as511.start() as sim:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "gateway", sim.url, "--s5lan", "0",
            "--fetchwrite", "127.0.0.1:0", "--writable", "DB4", "--duration", "20",
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(),
        )  # fmt: skip
        assert proc.stdout is not None
        try:
            lan_line = (await asyncio.wait_for(proc.stdout.readline(), 20)).decode()
            fw_line = (await asyncio.wait_for(proc.stdout.readline(), 5)).decode()
            allow_line = (await asyncio.wait_for(proc.stdout.readline(), 5)).decode()
            lan = re.fullmatch(r"s5lan listening on 127\.0\.0\.1:(\d+) \(TCP\)\n", lan_line)
            fw = re.fullmatch(r"fetchwrite listening on 127\.0\.0\.1:(\d+) \(TCP\)\n", fw_line)
            assert lan and fw, (lan_line, fw_line)
            assert allow_line == "writable: DB4\n"
            async with connect(f"s5lan://127.0.0.1:{lan[1]}") as plc:
                await plc.write("DB4.DW1", [0x0BAD])
                assert await plc.read("DB4.DW1") == [0x0BAD]
            async with connect(f"fetchwrite://127.0.0.1:{fw[1]}") as plc:
                assert await plc.read("DB4.DW0", 2) == [0x0400, 0x0BAD]
        finally:
            proc.terminate()
            _, err = await asyncio.wait_for(proc.communicate(), 10)
        assert proc.returncode == 0, err
        assert "AS511 " in err.decode() and "1 writes" in err.decode()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["as511+tcp://127.0.0.1:1"], "give --s5lan and/or --fetchwrite"),
        (["as511+tcp://127.0.0.1:1", "--s5lan", "99999"], "a port is 0..65535"),
        (["as511+tcp://127.0.0.1:1", "--s5lan", "0", "--writable", "DB0"], "writable"),
        (["e71+tcp://127.0.0.1:1", "--s5lan", "0"], "needs an S5 PLC"),
    ],
)
def test_cli_gateway_usage_errors_exit_2(args: list[str], message: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "plcstack", "gateway", *args],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=30,
    )
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


async def test_cli_gateway_serves_e71_faces_in_the_other_code_and_transport() -> None:
    async with await sim_e71.start() as sim:  # binary, TCP
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "gateway", sim.url, "--e71", "0",
            "--e71-udp", "127.0.0.1:0", "--e71-code", "ascii", "--writable", "D100-199",
            "--duration", "20",
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(),
        )  # fmt: skip
        assert proc.stdout is not None
        try:
            tcp_line = (await asyncio.wait_for(proc.stdout.readline(), 20)).decode()
            udp_line = (await asyncio.wait_for(proc.stdout.readline(), 5)).decode()
            allow_line = (await asyncio.wait_for(proc.stdout.readline(), 5)).decode()
            tcp = re.fullmatch(r"e71 listening on 127\.0\.0\.1:(\d+) \(TCP\)\n", tcp_line)
            udp = re.fullmatch(r"e71 listening on 127\.0\.0\.1:(\d+) \(UDP\)\n", udp_line)
            assert tcp and udp, (tcp_line, udp_line)
            assert allow_line == "writable: D100-D199\n"
            async with connect(f"e71+tcp://127.0.0.1:{tcp[1]}?code=ascii") as plc:
                await plc.write("D100", [0x0BAD])
                with pytest.raises(PlcErrorResponse) as refused:
                    await plc.write("D200", [1])
                assert refused.value.code == 0x55
            async with connect(f"e71+udp://127.0.0.1:{udp[1]}?code=ascii") as plc:
                assert await plc.read("D100", 2) == [0x0BAD, 0]
        finally:
            proc.terminate()
            _, err = await asyncio.wait_for(proc.communicate(), 10)
        assert proc.returncode == 0, err
        assert sim.memory.read_words("D", 100, 1) == [0x0BAD]
        assert "answered by the PLC 2; busy 0, expired 0, denied 1" in err.decode()
