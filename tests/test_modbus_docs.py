"""docs/modbus.md's quickstart runs as written: its plant.toml, its simulator, ``plcstack serve
modbus`` and every ``mbpoll`` line (a Modbus client independent of plcstack), each checked
against the output its comment shows. Ports: the simulator and the server take free ones and
the lines are rewritten to them. Without mbpoll (``apt-get install mbpoll``) the test fails."""

from __future__ import annotations

import asyncio
import shlex
import shutil
from pathlib import Path

import pytest

from plcstack.cli import build_parser
from plcstack.errors import AddressError, PlcError

PAGE = Path(__file__).resolve().parents[1] / "docs" / "modbus.md"


def _blocks() -> tuple[str, list[str]]:
    section = PAGE.read_text(encoding="utf-8").split("## Quickstart", 1)[1]
    toml = section.split("```toml", 1)[1].split("```", 1)[0]
    sh = section.split("```sh", 1)[1].split("```", 1)[0]
    return toml, [line.strip() for line in sh.splitlines() if line.strip()]


async def _run(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    try:
        code: int = await args.func(args)
    except AddressError:
        return 2
    except PlcError:
        return 1
    return code


async def _wait_for(capsys: pytest.CaptureFixture[str], text: str, task: asyncio.Task[int]) -> str:
    seen = ""
    async with asyncio.timeout(20):
        while text not in seen:
            assert not task.done(), task.result()
            await asyncio.sleep(0.02)
            captured = capsys.readouterr()
            seen += captured.out + captured.err
    return seen.split(text, 1)[1].split()[0]


async def test_quickstart_runs_as_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    mbpoll = shutil.which("mbpoll")
    assert mbpoll is not None, "mbpoll is not installed (apt-get install mbpoll)"
    toml, lines = _blocks()
    monkeypatch.chdir(tmp_path)
    tasks: list[asyncio.Task[int]] = []
    plc = modbus_port = ""
    try:
        for line in lines:
            command, _, comment = line.partition("#")
            comment = comment.strip()
            background = command.strip().endswith("&")
            argv = shlex.split(command.replace("&", " "))
            if argv[0] == "plcstack" and argv[1] == "sim":
                tasks.append(asyncio.create_task(_run([*argv[1:-2], "--port", "0"])))
                plc = await _wait_for(capsys, "listening on ", tasks[-1])
                continue
            if argv[:3] == ["plcstack", "serve", "modbus"]:
                assert background
                text = toml.replace("127.0.0.1:5000", plc).replace("127.0.0.1:5020", "127.0.0.1:0")
                await asyncio.to_thread(Path(argv[3]).write_text, text)
                tasks.append(asyncio.create_task(_run(argv[1:])))
                modbus_port = (await _wait_for(capsys, "listening on ", tasks[-1])).split(":")[-1]
                await _first_poll(mbpoll, modbus_port)
                continue
            argv = [a.replace("127.0.0.1:5000", plc).replace("5020", modbus_port) for a in argv]
            if argv[0] == "plcstack":
                code = await _run(argv[1:])
                shown = capsys.readouterr().out.strip()
            else:
                proc = await asyncio.create_subprocess_exec(
                    *argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
                )
                out, err = await asyncio.wait_for(proc.communicate(), 20)
                code = proc.returncode or 0
                shown = (out + err).decode()
            expected_code = 0
            if comment.startswith("exit "):
                number, _, comment = comment[5:].partition(":")
                expected_code, comment = int(number), comment.strip()
            assert code == expected_code, f"{line}: exit {code}\n{shown}"
            if comment:
                assert " ".join(comment.split()) in " ".join(shown.split()), f"{line}:\n{shown}"
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


async def _first_poll(mbpoll: str, port: str) -> None:
    """Until the server has the first poll (a read before it is exception 0x0B)."""
    async with asyncio.timeout(20):
        while True:
            proc = await asyncio.create_subprocess_exec(
                mbpoll,
                "-0",
                "-1",
                "-r",
                "0",
                "-p",
                port,
                "127.0.0.1",
                stdout=asyncio.subprocess.DEVNULL,
                stderr=asyncio.subprocess.DEVNULL,
            )
            if await proc.wait() == 0:
                return
            await asyncio.sleep(0.1)
