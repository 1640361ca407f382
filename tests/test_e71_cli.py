"""The CLI against E71 simulators: `python -m plcstack read/write/sim e71`.

A ``read`` end to end in a subprocess (``run_cli``) per transport; the other commands through the
same ``plcstack.cli.main`` in this process (``cli_in_process``, tests/cli_helpers.py), which
saves a new interpreter per command."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import sys
from pathlib import Path

import pytest

from plcstack.sim import e71 as sim_e71
from tests.cli_helpers import cli_in_process

ROOT = Path(__file__).resolve().parents[1]


async def run_cli(*args: str) -> tuple[int, str, str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "plcstack",
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env=env,
        cwd=str(ROOT),
    )
    out, err = await asyncio.wait_for(proc.communicate(), 30)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


@pytest.mark.parametrize(("transport", "code"), [("tcp", "binary"), ("udp", "ascii")])
async def test_read_json_and_write(transport: str, code: str) -> None:
    sim = await sim_e71.start(transport=transport, code=code)  # type: ignore[arg-type]
    try:
        sim.memory.write_words("D", 100, [1, 2, 65535])
        rc, out, err = await run_cli("read", sim.url, "D100", "3", "--json")
        assert (rc, err) == (0, "")
        assert out == '{"address": "D100", "values": [1, 2, 65535]}\n'
        assert json.loads(out) == {"address": "D100", "values": [1, 2, 65535]}
        # the rest through the same main in this process (the entry point is proven above)
        rc, out, err = await cli_in_process("write", sim.url, "M10", "true", "false", "1")
        assert rc == 0, err
        assert sim.memory.read_bits("M", 10, 3) == [True, False, True]
        rc, out, _ = await cli_in_process("read", sim.url, "M10", "3", "--json")
        assert out == '{"address": "M10", "values": [true, false, true]}\n'
    finally:
        await sim.aclose()


async def test_plc_error_code_end_to_end() -> None:
    sim = await sim_e71.start()
    try:
        sim.memory.write_in_run = False
        rc, out, err = await cli_in_process("write", sim.url, "D0", "5")
        assert rc == 1 and out == ""
        lines = err.splitlines()
        assert len(lines) == 1
        assert "55H" in lines[0] and "write during RUN not enabled" in lines[0]
        assert sim.url in lines[0] and "write D0 x1" in lines[0]
        rc, _, err = await cli_in_process("read", sim.url + "?pc=05", "D0")
        assert rc == 1
        assert len(err.splitlines()) == 1
        assert "5BH/10H" in err and "wrong PC number" in err
    finally:
        await sim.aclose()


async def test_dead_plc_and_bad_address() -> None:
    sim = await sim_e71.start()
    url = sim.url
    try:
        rc, _, err = await cli_in_process("read", url, "Q0")
        assert rc == 2 and "unknown MELSEC device" in err
        rc, _, err = await cli_in_process("read", url + "?code=ebcdic", "D0")
        assert rc == 2 and "code" in err
    finally:
        await sim.aclose()
    rc, _, err = await cli_in_process("read", url, "D0", "--timeout", "1")
    assert rc == 1 and len(err.splitlines()) == 1 and url in err


async def test_sim_subcommand_announces_and_serves() -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "plcstack",
        "sim",
        "e71",
        "--port",
        "0",
        "--code",
        "ascii",
        "--transport",
        "udp",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env=env,
    )
    try:
        assert proc.stdout is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode()
        assert line.startswith("listening on 127.0.0.1:") and line.endswith(" (UDP)\n")
        port = int(line.split()[2].rsplit(":", 1)[1])
        rc, out, err = await cli_in_process(
            "read", f"e71+udp://127.0.0.1:{port}?code=ascii", "D9000", "2", "--json"
        )
        assert (rc, out) == (0, '{"address": "D9000", "values": [0, 0]}\n'), err
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            await asyncio.wait_for(proc.wait(), 10)
        except TimeoutError:
            proc.kill()
            await proc.wait()
