"""The gateway's writes: a refused one is said at the default log level, each is audited."""

from __future__ import annotations

import asyncio
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from plcstack import connect
from plcstack.errors import PlcErrorResponse
from plcstack.sim import as511 as sim_as511
from tests.test_gateway import _env

ROOT = Path(__file__).resolve().parents[1]


async def test_cli_gateway_logs_a_refused_write_and_audits_every_write(tmp_path: Path) -> None:
    audit = tmp_path / "gateway-writes.jsonl"
    async with await sim_as511.start() as sim:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "gateway", sim.url, "--s5lan", "0",
            "--writable", "DB4", "--duration", "20", "--audit", str(audit),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=ROOT,
        )  # fmt: skip
        assert proc.stdout is not None
        try:
            lan_line = (await asyncio.wait_for(proc.stdout.readline(), 20)).decode()
            lan = re.fullmatch(r"s5lan listening on 127\.0\.0\.1:(\d+) \(TCP\)\n", lan_line)
            assert lan, lan_line
            async with connect(f"s5lan://127.0.0.1:{lan[1]}") as plc:
                await plc.write("DB4.DW1", [0x0BAD])
                lines_at_answer = len(audit.read_text().splitlines())
                with pytest.raises(PlcErrorResponse):
                    await plc.write("DB5.DW0", [1])
        finally:
            proc.terminate()
            _, err_bytes = await asyncio.wait_for(proc.communicate(), 10)
    err = err_bytes.decode()
    assert proc.returncode == 0, err
    assert lines_at_answer == 1  # the line was written before the client had its answer
    # main: nothing at the default level, only "denied 1" in the final counts
    (warning,) = [line for line in err.splitlines() if "refused" in line]
    assert "write from gateway refused (write_denied): write DB5+0: writing DB5" in warning
    lines = [json.loads(line) for line in audit.read_text().splitlines()]
    assert [
        (x["source"], x["plc"], x["tag"], x["value"], x["result"], x["may_have_executed"])
        for x in lines
    ] == [
        ("gateway", sim.url, "DB4+2", [0x0B, 0xAD], "ok", True),
        ("gateway", sim.url, "DB5+0", [0, 1], "write_denied", False),
    ]
