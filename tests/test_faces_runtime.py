"""[[gateway]] in the configuration file: native faces run by ``plcstack poll`` beside the
poller, on each PLC's one connection; their writes through the run's write path and audit;
their mistakes said with FILE:LINE before anything starts."""

from __future__ import annotations

import asyncio
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from plcstack.clients import connect
from plcstack.config import parse_config
from plcstack.errors import ConfigError, PlcErrorResponse
from plcstack.sim import e71 as e71_sim
from plcstack.sim import s5lan as lan_sim
from plcstack.transports.guard import Limits
from tests.ports import free_port
from tests.test_gateway import _env

ROOT = Path(__file__).resolve().parents[1]

PLC = """
[poll]
interval = 0.05

[[plc]]
name = "kiln1"
url = "{url}"

[plc.tags]
v = "DB10.DW7"
"""


async def test_plcstack_poll_runs_the_faces_of_its_file_on_the_plcs_one_connection(
    tmp_path: Path,
) -> None:
    module = await lan_sim.start()  # takes one connection: the poller's
    port = free_port()
    config = tmp_path / "plant.toml"
    config.write_text(
        PLC.format(url=module.url)
        + f"""
[audit]
path = "writes.jsonl"

[[gateway]]
protocol = "s5lan"
listen = "127.0.0.1:{port}"
plc = "kiln1"
writable = "DB10"
"""
    )
    async with module:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "poll", str(config), "--duration", "30",
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=ROOT,
        )  # fmt: skip
        assert proc.stderr is not None and proc.stdout is not None
        try:
            async with asyncio.timeout(20):
                while True:
                    line = (await proc.stderr.readline()).decode()
                    assert line, "plcstack poll ended before its face listened"
                    if "listening on" in line:
                        break
            assert line == f"s5lan face of kiln1 listening on 127.0.0.1:{port} (TCP)\n"
            async with connect(f"s5lan://127.0.0.1:{port}") as plc:
                await plc.write("DB10.DW7", [0x4242])
                assert await plc.read("DB10.DW7") == [0x4242]
                with pytest.raises(PlcErrorResponse):
                    await plc.write("DB11.DW0", [1])
            async with asyncio.timeout(10):  # the poller reads what the face wrote
                while json.loads(await proc.stdout.readline())["value"] != 0x4242:
                    pass
        finally:
            proc.terminate()
            _, err_bytes = await asyncio.wait_for(proc.communicate(), 10)
    err = err_bytes.decode()
    assert proc.returncode == 0, err
    assert module.connection_count.peak == 1 and module.refused_connections == 0
    assert re.search(r"faces of kiln1: \d+ requests on its connection, busy 0", err), err
    assert "write from gateway refused (write_denied)" in err
    lines = [json.loads(x) for x in (tmp_path / "writes.jsonl").read_text().splitlines()]
    assert [
        (x["source"], x["plc"], x["tag"], x["value"], x["previous"], x["result"]) for x in lines
    ] == [
        ("gateway", "kiln1", "DB10+14", [0x42, 0x42], [0, 0], "ok"),
        ("gateway", "kiln1", "DB11+0", [0, 1], None, "write_denied"),
    ]


GATEWAY = """
[[gateway]]
protocol = "s5lan"
listen = "127.0.0.1:2000"
plc = "kiln1"
"""


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (('plc = "kiln1"', 'plc = "kiln9"'), "plc 'kiln9' is no [[plc]] of this file"),
        (('protocol = "s5lan"', 'protocol = "e71"'), "a e71 face stands in front of"),
        (('protocol = "s5lan"', 'protocol = "modbus"'), "protocol must be"),
        (('plc = "kiln1"', 'writable = "D100"'), "writable 'D100' is not"),
        (('listen = "127.0.0.1:2001"', 'listen = "2001"'), "listen must be"),
        (('plc = "kiln1"', "mk = true"), "mk (the Tani MK header)"),
        (('plc = "kiln1"', "queue = 0"), "queue must be 1..65536"),
        (('plc = "kiln1"', "first_request_timeout = -1"), "first_request_timeout must be"),
        (('plc = "kiln1"', "max_clients_per_host = 9"), "cannot be more than max_connections (8)"),
    ],
)
def test_gateway_mistakes_are_said_with_their_line(change: tuple[str, str], message: str) -> None:
    old, new = change
    second = GATEWAY.replace("2000", "2001")  # the mistake is in the second [[gateway]]
    if new.split(" =")[0] != old.split(" =")[0]:  # a key added after the one named
        new = f"{old}\n{new}"
    text = PLC.format(url="s5lan://127.0.0.1:5010") + GATEWAY + second.replace(old, new)
    lines = text.splitlines()
    line = len(lines) - lines[::-1].index(new.splitlines()[-1])  # the mistake's own line
    with pytest.raises(ConfigError) as error:
        parse_config(text, source="plant.toml")
    assert message in str(error.value) and "[[gateway]] #2" in str(error.value)
    assert f"(plant.toml:{line})" in str(error.value)


def test_two_faces_on_one_address_are_refused() -> None:
    text = PLC.format(url="s5lan://127.0.0.1:5010") + GATEWAY + GATEWAY
    with pytest.raises(
        ConfigError, match=r"listens on 127.0.0.1:2000 \(tcp\) as \[\[gateway\]\] #1"
    ):
        parse_config(text, source="plant.toml")
    config = parse_config(PLC.format(url="s5lan://127.0.0.1:5010") + GATEWAY)
    assert [f.describe() for f in config.gateway] == ["s5lan face of kiln1"]


def test_a_faces_guard_limits_are_its_tables_keys() -> None:
    """[[gateway]] takes the guard's keys of every listening face (plcstack.transports.guard);
    its clients at once are its max_connections."""
    keys = 'plc = "kiln1"\nmax_connections = 4\nmax_clients_per_host = 1\n'
    keys += 'first_request_timeout = "2s"\nidle_timeout = 0\n'
    text = PLC.format(url="s5lan://127.0.0.1:5010") + GATEWAY.replace('plc = "kiln1"\n', keys)
    (face,) = parse_config(text).gateway
    assert face.guard_limits == Limits(4, 1, 2.0, None)
    (plain,) = parse_config(PLC.format(url="s5lan://127.0.0.1:5010") + GATEWAY).gateway
    assert plain.guard_limits == Limits(8, 6, 10.0, 600.0)


@pytest.mark.parametrize("command", [["poll", "--format", "none"], ["serve", "modbus"]])
async def test_an_e71_face_of_the_file_in_the_other_code_and_transport(
    tmp_path: Path, command: list[str]
) -> None:
    """plcstack poll runs the file's [[gateway]] faces, and so does serve modbus, the same
    runtime with its face on (before, serve modbus and serve opcua ran them not at all)."""
    plc = await e71_sim.start()  # binary, TCP
    port = free_port()
    config = tmp_path / "plant.toml"
    config.write_text(
        f"""
[modbus]
listen = "127.0.0.1:{free_port()}"

[poll]
interval = 0.05

[[plc]]
name = "press2"
url = "{plc.url}"

[plc.tags]
strokes = {{ address = "D100", modbus = "hr:0" }}

[[gateway]]
protocol = "e71"
listen = "127.0.0.1:{port}"
plc = "press2"
transport = "udp"
code = "ascii"
writable = "D100-199"
"""
    )
    async with plc:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", *command, str(config), "--duration", "30",
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=ROOT,
        )  # fmt: skip
        assert proc.stderr is not None
        try:
            async with asyncio.timeout(20):
                while "of press2 listening on" not in (
                    line := (await proc.stderr.readline()).decode()
                ):
                    assert line, f"plcstack {command[0]} ended before its face listened"
            assert line == f"e71 face (udp, ascii) of press2 listening on 127.0.0.1:{port} (UDP)\n"
            async with connect(f"e71+udp://127.0.0.1:{port}?code=ascii") as face:
                await face.write("D100", [1234])
                assert await face.read("D100", 2) == [1234, 0]
                with pytest.raises(PlcErrorResponse) as refused:
                    await face.write("D200", [1])
                assert refused.value.code == 0x55
        finally:
            proc.terminate()
            _, err = await asyncio.wait_for(proc.communicate(), 10)
        assert proc.returncode == 0, err.decode()
        assert plc.memory.read_words("D", 100, 1) == [1234]
        assert "faces of press2: " in err.decode()
