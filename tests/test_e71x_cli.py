"""E71-only CLI commands (issue 3) against the E71 simulator, run through ``plcstack.cli.main``
as ``python -m plcstack`` runs them (in this process: tests/cli_helpers.py)."""

from __future__ import annotations

import json
from array import array
from pathlib import Path

from plcstack.sim import e71 as sim_e71
from plcstack.sim.e71_module import module_of
from plcstack.sim.melsec_memory import CpuState
from tests.cli_helpers import cli_in_process


async def run_cli(*args: str) -> tuple[int, str, str]:
    # in this process: these commands only talk to the PLC (see tests/cli_helpers.py)
    return await cli_in_process(*args)


async def test_info_run_stop_loopback() -> None:
    async with await sim_e71.start(code="ascii") as sim:
        rc, out, err = await run_cli("info", sim.url)
        assert (rc, err) == (0, "")
        assert out.splitlines() == [
            "model: 94H (A3A, A3U, A4U, Q3A, Q4A, AJ72LP25/BR15, AJ72QLP25/QBR15)",
            "state: RUN (D9015 = 0000H)",
        ]
        rc, out, err = await run_cli("stop", sim.url)
        assert (rc, out, err) == (0, "remote STOP accepted\n", "")
        assert sim.memory.state is CpuState.STOP
        rc, out, _ = await run_cli("info", sim.url, "--json")
        assert json.loads(out)["state"] == "STOP"
        rc, out, _ = await run_cli("run", sim.url)
        assert (rc, out) == (0, "remote RUN accepted\n")
        assert module_of(sim.memory).remote_stop_by is None
        rc, out, err = await run_cli("loopback", sim.url, "1234AB")
        assert rc == 0 and out.startswith("loopback: 3 bytes echoed in "), err
        rc, out, err = await run_cli("loopback", sim.url, "xyz")
        assert rc == 2 and "not hex" in err


async def test_rab_read_write_and_errors() -> None:
    async with await sim_e71.start(transport="udp") as sim:
        rc, out, err = await run_cli("rab-write", sim.url, "6000", "1", "0x1F", "-1")
        assert (rc, out, err) == (0, "RAB 6000: wrote 3 word(s)\n", "")
        assert module_of(sim.memory).rab_read(6000, 3) == [1, 0x1F, 0xFFFF]
        rc, out, _ = await run_cli("rab-read", sim.url, "6000", "3", "--json")
        assert json.loads(out) == {"address": 6000, "values": [1, 31, 65535]}
        rc, out, err = await run_cli("rab-read", sim.url, "6143", "2")
        assert rc == 2 and out == "" and "6143" in err and len(err.splitlines()) == 1


async def test_plc_error_is_one_line_exit_1() -> None:
    async with await sim_e71.start() as sim:
        module_of(sim.memory).remote_stop(by="AJ71C24")
        rc, out, err = await run_cli("run", sim.url)
        assert rc == 1 and out == ""
        (line,) = err.splitlines()
        assert line.startswith(f"plcstack: error: {sim.url}: remote RUN: ")
        assert "5BH/18H" in line and "remote RUN/STOP not possible" in line


async def test_area_read_write_with_progress(tmp_path: Path) -> None:
    async with await sim_e71.start() as sim:
        sim.memory.state = CpuState.STOP
        source = tmp_path / "comments.bin"
        source.write_bytes(bytes(range(256)) * 3)
        rc, out, err = await run_cli(
            "e71-area", "write", sim.url, "comments", "0x100", str(source), "--progress"
        )
        assert rc == 0, err
        assert out == "comments: wrote 768 bytes\n"
        assert err.endswith("[##############################] 768/768 bytes\n")
        assert err.count("\r") == 3
        assert bytes(module_of(sim.memory).comments[0x100 : 0x100 + 768]) == source.read_bytes()
        target = tmp_path / "back.bin"
        rc, out, err = await run_cli(
            "e71-area",
            "read",
            sim.url,
            "comments",
            "0x100",
            "768",
            "--out",
            str(target),
            "--chunk",
            "100",
        )
        assert rc == 0 and err == ""  # no tty, no --progress: no bar
        assert target.read_bytes() == source.read_bytes()
        module_of(sim.memory).programs[0x0A][0:2] = array("H", [0x1234, 5])
        rc, out, err = await run_cli("e71-area", "read", sim.url, "main-program", "0", "2")
        assert (rc, out) == (0, "34120500\n")
