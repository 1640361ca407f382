"""The gateway's writes: a refused one is said at the default log level, each is audited with
the network client it came from."""

from __future__ import annotations

import asyncio
import json
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from plcstack import connect
from plcstack.codecs import s5lan as s5lan_codec
from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.fetchwrite import Org, WriteRequest, encode_request, parse_ack_header
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
    fields = ("source", "plc", "tag", "value", "previous", "result", "may_have_executed")
    assert [tuple(x[k] for k in fields) for x in lines] == [
        # DB4.DW1 held 0401h before (the simulator's DBn.DWk = n * 100h + k)
        ("gateway", sim.url, "DB4+2", [0x0B, 0xAD], [0x04, 0x01], "ok", True),
        ("gateway", sim.url, "DB5+0", [0, 1], None, "write_denied", False),
    ]


async def _exchange(
    port: int, frame: bytes, answer: Callable[[bytes], int | None]
) -> tuple[int, str]:
    """Send one request over a connection of our own: the protocol's error value of the answer
    (0: done) and this end's ``host:port``, the address the audit must name."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        host, me = writer.get_extra_info("sockname")[:2]
        writer.write(frame)
        received = b""
        async with asyncio.timeout(10):
            while (error := answer(received)) is None:
                chunk = await reader.read(4096)
                assert chunk, "the gateway closed the connection without an answer"
                received += chunk
    finally:
        writer.close()
        await writer.wait_closed()
    return error, f"{host}:{me}"


async def s5lan_write(port: int, db: int, dw: int, data: bytes) -> tuple[int, str]:
    codec = s5lan_codec.ClientConnection()
    frame = codec.send(s5lan_codec.Request.write("D", "W", dw, data, db=db))

    def answer(received: bytes) -> int | None:
        codec.receive_data(received[codec.bytes_received :])
        event = codec.next_event()
        return None if event is NEED_DATA else event.header.err

    return await _exchange(port, frame, answer)


async def fetchwrite_write(port: int, db: int, dw: int, data: bytes) -> tuple[int, str]:
    frame = encode_request(WriteRequest.of(Org.DB, db, dw, data))

    def answer(received: bytes) -> int | None:
        return parse_ack_header(received[:16])[1] if len(received) >= 16 else None

    return await _exchange(port, frame, answer)


async def test_the_gateway_audit_names_the_network_client_of_each_write(tmp_path: Path) -> None:
    audit = tmp_path / "gateway-writes.jsonl"
    async with await sim_as511.start() as sim:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "gateway", sim.url, "--s5lan", "0",
            "--fetchwrite", "0", "--writable", "DB4", "--duration", "20", "--audit", str(audit),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(), cwd=ROOT,
        )  # fmt: skip
        assert proc.stdout is not None
        try:
            ports = []
            for _ in ("s5lan", "fetchwrite"):
                line = (await asyncio.wait_for(proc.stdout.readline(), 20)).decode()
                listening = re.search(r"listening on 127\.0\.0\.1:(\d+) ", line)
                assert listening, line
                ports.append(int(listening[1]))
            lan, fw = ports
            confirmed_lan = await s5lan_write(lan, 4, 1, b"\x01\x02")
            confirmed_fw = await fetchwrite_write(fw, 4, 2, b"\x03\x04")
            denied_fw = await fetchwrite_write(fw, 5, 0, b"\x00\x01")
            denied_lan = await s5lan_write(lan, 5, 0, b"\x00\x01")
        finally:
            proc.terminate()
            _, err_bytes = await asyncio.wait_for(proc.communicate(), 10)
    assert proc.returncode == 0, err_bytes.decode()
    answers = [confirmed_lan, confirmed_fw, denied_fw, denied_lan]
    assert [error != 0 for error, _ in answers] == [False, False, True, True]
    lines = [json.loads(line) for line in audit.read_text().splitlines()]
    # the S5-LAN and the FETCH/WRITE client of each write, the refused ones included
    assert [(x["tag"], x["result"], x["peer"]) for x in lines] == [
        ("DB4+2", "ok", confirmed_lan[1]),
        ("DB4+4", "ok", confirmed_fw[1]),
        ("DB5+0", "write_denied", denied_fw[1]),
        ("DB5+0", "write_denied", denied_lan[1]),
    ]
