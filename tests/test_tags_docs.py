"""docs/tags.md runs as written: every file it shows is the file in docs/tags/ (decoded), and
every ``plcstack tags`` command it shows prints exactly the block that follows it."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from plcstack.tags.table import decode
from tests.cli_helpers import cli_in_process

ROOT = Path(__file__).resolve().parents[1]
PAGE = (ROOT / "docs" / "tags.md").read_text(encoding="utf-8")
SHOWN_FILES = re.findall(r"`(docs/tags/[^`]+)`[^\n]*:\n\n```\w*\n(.*?)```", PAGE, re.S)
COMMANDS = re.findall(r"```sh\n(plcstack tags [^\n]*)\n```\n\n```\w*\n(.*?)```", PAGE, re.S)


def test_the_page_shows_files_and_commands() -> None:
    assert len(SHOWN_FILES) >= 4 and len(COMMANDS) >= 6
    shown = {cmd.split()[2] for cmd, _ in COMMANDS}
    assert {"import", "export", "list"} <= shown


@pytest.mark.parametrize(("name", "body"), SHOWN_FILES, ids=[n for n, _ in SHOWN_FILES])
def test_shown_file_is_the_file(name: str, body: str) -> None:
    data = (ROOT / name).read_bytes()
    fallback = "cp932" if "gxdeveloper" in name else "cp1252"
    assert decode(data, name, fallback=fallback).replace("\r\n", "\n") == body


@pytest.mark.parametrize(("line", "body"), COMMANDS, ids=[c for c, _ in COMMANDS])
async def test_command_prints_what_the_page_shows(
    line: str, body: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    command, _, comment = line.partition("#")
    m = re.match(r"\s*exit (\d+)", comment)
    expected = int(m.group(1)) if m else 0
    monkeypatch.chdir(ROOT)
    code, out, err = await cli_in_process(*shlex.split(command)[1:])
    assert code == expected, err
    shown = out if expected == 0 else err
    assert shown.replace("\r\n", "\n") == body
    if expected:
        assert out == ""
