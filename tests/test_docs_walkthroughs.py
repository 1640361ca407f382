"""The walkthroughs of the docs run as written.

A page's ``## Walkthrough`` section holds one ``sh`` block. Its lines run in order, in this
process: a line ending in ``&`` (a simulator, the gateway) is started and waited for until it
says ``listening on``; every other ``plcstack`` line runs to its end, and a trailing comment
that shows output (``# D0: 1 2``) must match, ``# exit N`` must be the exit code. Every port the
block names is replaced by a free one, the same free one wherever the block repeats it, so the
walkthrough neither needs nor takes its documented ports.
"""

from __future__ import annotations

import asyncio
import re
import shlex
from pathlib import Path

import pytest

from plcstack.cli import build_parser
from tests.servers import free_port
from tests.test_docs import _run

DOCS = Path(__file__).resolve().parents[1] / "docs"
WALKTHROUGHS = ["gateway.md"]


def _block(page: str) -> list[str]:
    text = (DOCS / page).read_text(encoding="utf-8")
    section = text.split("## Walkthrough", 1)[1]
    block = section.split("```sh", 1)[1].split("```", 1)[0]
    return [line.strip() for line in block.splitlines() if line.strip()]


def _moved_ports(lines: list[str]) -> dict[str, str]:
    ports = set(re.findall(r"127\.0\.0\.1:(\d{4,5})|--port (\d{4,5})", "\n".join(lines)))
    return {p: str(free_port()) for pair in ports for p in pair if p}


def _moved(text: str, ports: dict[str, str]) -> str:
    return re.sub(r"\b(\d{4,5})\b", lambda m: ports.get(m.group(1), m.group(1)), text)


async def _wait_listening(capsys: pytest.CaptureFixture[str], task: asyncio.Task[int]) -> str:
    seen = ""
    async with asyncio.timeout(15):
        while "listening on" not in seen:
            assert not task.done(), f"ended before listening: {task.result()}; {seen}"
            seen += capsys.readouterr().out
            await asyncio.sleep(0.02)
    return seen


@pytest.mark.parametrize("page", WALKTHROUGHS)
async def test_walkthrough_runs_as_written(page: str, capsys: pytest.CaptureFixture[str]) -> None:
    lines = _block(page)
    ports = _moved_ports(lines)
    background: list[asyncio.Task[int]] = []
    try:
        for line in lines:
            command, _, comment = line.partition("#")
            command = command.strip()
            comment = comment.strip()
            argv = shlex.split(_moved(command.removesuffix("&"), ports))
            assert argv[0] == "plcstack", line
            build_parser().parse_args(argv[1:])  # every line is valid as written
            if command.endswith("&"):
                task = asyncio.create_task(_run(argv[1:]))
                background.append(task)
                await _wait_listening(capsys, task)
                continue
            code = await _run(argv[1:])
            shown = capsys.readouterr().out.strip()
            expected_code = int(m.group(1)) if (m := re.match(r"exit (\d)", comment)) else 0
            assert code == expected_code, f"{page}: {line}: exit {code}"
            if comment and not comment.startswith("exit") and argv[1] == "read":
                assert shown == _moved(comment, ports), f"{page}: {line}"
    finally:
        for task in background:
            task.cancel()
        await asyncio.gather(*background, return_exceptions=True)
