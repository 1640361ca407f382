"""docs/tags.md runs as written: every file it shows is the file in docs/tags/ (decoded), and
every ``plcstack tags`` command it shows prints exactly the block that follows it."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
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


@pytest.mark.slow  # several seconds: run by the slow run
def test_the_example_files_copy_out_of_the_package_as_the_page_says(tmp_path: Path) -> None:
    """A wheel has no docs/tags/ to run the page's commands from: the page's copy block, run as
    written by /bin/sh with this environment's ``plcstack`` first on PATH, makes the folder
    with every file the page reads, byte for byte (UTF-16 and Shift-JIS included)."""
    block = re.search(r"```sh\n(mkdir -p docs/tags\n.*?)```", PAGE, re.S)
    assert block is not None
    named = set(re.findall(r"docs/tags/([\w.-]+)", PAGE))
    scripts = str(Path(sys.executable).parent)
    env = {**os.environ, "PATH": scripts + os.pathsep + os.environ.get("PATH", "")}
    subprocess.run(["/bin/sh", "-ec", block.group(1)], cwd=tmp_path, env=env, check=True)
    copied = {p.name for p in (tmp_path / "docs" / "tags").iterdir()}
    assert copied == named
    for name in named:
        assert (tmp_path / "docs" / "tags" / name).read_bytes() == (
            ROOT / "docs" / "tags" / name
        ).read_bytes(), name
