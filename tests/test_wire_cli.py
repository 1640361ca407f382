"""``--pcap FILE`` on ``read``, ``write``, ``poll`` and ``sim``: what each command writes."""

from __future__ import annotations

import asyncio
import os
import signal
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from plcstack.sim import e71 as e71_sim
from plcstack.sim import s5lan as s5lan_sim
from plcstack.wire.packets import parse_ip
from plcstack.wire.pcapng import LINKTYPE_RAW, read_capture
from tests.cli_helpers import cli_in_process

ROOT = Path(__file__).resolve().parent.parent


def payloads(path: Path) -> list[tuple[int, bytes]]:
    """(source port, payload) of every TCP/UDP packet with data in the file."""
    out = []
    for packet in read_capture(path.read_bytes()):
        assert packet.linktype == LINKTYPE_RAW
        ip = parse_ip(packet.data)
        assert ip is not None
        if ip.payload:
            out.append((ip.sport, ip.payload))
    return out


async def test_read_and_write_record_their_exchange(tmp_path: Path) -> None:
    sim = await e71_sim.start()
    try:
        path = tmp_path / "w.pcapng"
        code, out, err = await cli_in_process(
            "write", sim.url, "D100", "1", "2", "--pcap", str(path)
        )
        assert (code, out) == (0, "D100: wrote 2 value(s)\n"), err
        written = payloads(path)
        assert [port == sim.port for port, _ in written] == [False, True]
        assert written[1][1] == bytes.fromhex("8300")  # §12 vector 8's answer: 83H 00H
        path = tmp_path / "r.pcapng"
        code, out, err = await cli_in_process("read", sim.url, "D100", "2", "--pcap", str(path))
        assert (code, out) == (0, "D100: 1 2\n"), err
        read = payloads(path)
        assert read[1] == (sim.port, bytes.fromhex("8100 0100 0200"))
    finally:
        await sim.aclose()


async def test_a_capture_file_that_cannot_be_written_is_a_usage_error(tmp_path: Path) -> None:
    sim = await s5lan_sim.start()
    try:
        missing = tmp_path / "no" / "such" / "dir" / "x.pcapng"
        code, out, err = await cli_in_process("read", sim.url, "DB10.DW0", "--pcap", str(missing))
        assert code == 2 and out == ""
        assert err.startswith("plcstack: error: --pcap ") and "cannot write it" in err
        assert len(err.splitlines()) == 1
        assert sim.connection_count.total == 0  # nothing was sent
    finally:
        await sim.aclose()


async def test_a_bad_limit_is_refused_by_the_parser() -> None:
    code, _, err = await cli_in_process(
        "read", "e71+tcp://127.0.0.1:1", "D0", "--pcap", "x", "--pcap-limit", "1k"
    )
    assert code == 2 and "least capture size" in err


@asynccontextmanager
async def plcstack_process(*args: str) -> AsyncIterator[asyncio.subprocess.Process]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "plcstack",
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env=env,
    )
    try:
        yield proc
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(proc.wait(), 15)
            except TimeoutError:
                proc.kill()
                await proc.wait()


async def test_sim_records_the_simulators_side(tmp_path: Path) -> None:
    path = tmp_path / "sim.pcapng"
    async with plcstack_process("sim", "e71", "--port", "0", "--pcap", str(path)) as proc:
        assert proc.stdout is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode()
        port = int(line.split()[2].rsplit(":", 1)[1])
        code, out, err = await cli_in_process("read", f"e71+tcp://127.0.0.1:{port}", "D0")
        assert (code, out) == (0, "D0: 0\n"), err
        proc.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(proc.wait(), 15) == 0
    packets = list(read_capture(path.read_bytes()))
    syn = parse_ip(packets[0].data)
    assert syn is not None and syn.dport == port and syn.flags == 0x02
    assert [p for p, _ in payloads(path)] == [syn.sport, port]


async def test_poll_records_every_plc(tmp_path: Path) -> None:
    e71 = await e71_sim.start()
    lan = await s5lan_sim.start()
    try:
        config = tmp_path / "plant.toml"
        config.write_text(
            f"""
[poll]
interval = 0.05

[[plc]]
name = "press"
url = "{e71.url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16" }}

[[plc]]
name = "oven"
url = "{lan.url}"
[plc.tags]
temperature = {{ address = "DB10.DW0", type = "int16" }}
""",
            encoding="utf-8",
        )
        path = tmp_path / "poll.pcapng"
        async with plcstack_process("poll", str(config), "--pcap", str(path)) as proc:
            # until each PLC was read twice, then stopped as a service is (SIGTERM, exit 0): a
            # fixed --duration 0.5 ended before the second read of one of them under load
            assert proc.stdout is not None
            out = b""
            async with asyncio.timeout(30):
                while out.count(b'"strokes"') < 2 or out.count(b'"temperature"') < 2:
                    line = await proc.stdout.readline()
                    assert line, f"poll ended after {out!r}"
                    out += line
            proc.send_signal(signal.SIGTERM)
            _, err = await asyncio.wait_for(proc.communicate(), 30)
            assert proc.returncode == 0, err.decode()
        ports = {port for port, _ in payloads(path)}
        assert {e71.port, lan.port} <= ports
    finally:
        await e71.aclose()
        await lan.aclose()
