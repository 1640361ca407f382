"""docs/web.md's quickstart runs as written: its configuration and every command of its ``sh``
blocks, against a real ``plcstack sim e71`` and a real ``plcstack poll`` (both subprocesses),
with real ``curl`` (each line in ``/bin/sh``, in the configuration's directory); the documented
ports replaced by free ones. A trailing comment that shows output must match: JSON compared as
JSON, a comment with ``...`` (any text) as a pattern of the whole output."""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.servers import free_port

PAGE = Path(__file__).resolve().parents[1] / "docs" / "web.md"


def _blocks(text: str, lang: str) -> list[str]:
    """The ``lang`` blocks of the Quickstart section, in order."""
    section = text.split("## Quickstart", 1)[1].split("\n## ", 1)[0]
    return re.findall(rf"```{lang}\n(.*?)```", section, flags=re.S)


def _wait_line(proc: subprocess.Popen[str], stream: str, needle: str) -> str:
    """The first line of the process's ``stream`` holding ``needle`` (10 s at most)."""
    pipe = getattr(proc, stream)
    deadline = time.monotonic() + 10
    seen = []
    while time.monotonic() < deadline:
        line = pipe.readline()
        if not line:
            break
        seen.append(line)
        if needle in line:
            return str(line)
    raise AssertionError(f"no {needle!r} from {proc.args!r}: {''.join(seen)}")


@pytest.fixture
def background() -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    yield procs
    for proc in procs:
        proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.slow  # several seconds: run by the slow run
def test_web_quickstart_runs(tmp_path: Path, background: list[subprocess.Popen[str]]) -> None:
    if shutil.which("curl") is None:
        pytest.fail("the quickstart uses curl, which is not installed")
    text = PAGE.read_text(encoding="utf-8")
    toml = _blocks(text, "toml")[0]
    lines = [line.strip() for block in _blocks(text, "sh") for line in block.splitlines()]
    lines = [line for line in lines if line]
    web_port = str(free_port())
    env = dict(os.environ)
    plcstack = [sys.executable, "-m", "plcstack"]
    replace: dict[str, str] = {"127.0.0.1:8080": f"127.0.0.1:{web_port}"}

    def substitute(s: str) -> str:
        for old, new in replace.items():
            s = s.replace(old, new)
        return s

    for line in lines:
        command, _, comment = line.partition("#")
        comment = substitute(comment.strip())
        argv = shlex.split(substitute(command.strip().rstrip("&")))
        if argv[0] == "export":
            name, _, value = argv[1].partition("=")
            env[name] = value
        elif argv[:2] == ["plcstack", "sim"]:
            proc = subprocess.Popen(
                [*plcstack, *argv[1:], "--port", "0"], stdout=subprocess.PIPE, text=True
            )
            background.append(proc)
            where = _wait_line(proc, "stdout", "listening on").split("listening on ")[1].split()[0]
            replace["127.0.0.1:5000"] = where
            config = substitute(toml).replace("127.0.0.1:8080", f"127.0.0.1:{web_port}")
            (tmp_path / "plant.toml").write_text(config, encoding="utf-8")
        elif argv[:2] == ["plcstack", "poll"]:
            proc = subprocess.Popen(
                [*plcstack, *argv[1:]],
                cwd=tmp_path,
                env=env,
                stderr=subprocess.PIPE,
                text=True,
            )
            background.append(proc)
            assert comment in _wait_line(proc, "stderr", "web console on")
        else:
            if argv[0] == "plcstack":
                run: str | list[str] = [*plcstack, *argv[1:]]
            else:  # as written, in /bin/sh (quotes, redirections), beside the configuration
                run = substitute(command.strip())
            done = subprocess.run(
                run,
                shell=isinstance(run, str),
                cwd=tmp_path,
                env=env,
                capture_output=True,
                text=True,
                timeout=30,
            )
            assert done.returncode == 0, (line, done.stderr)
            out = done.stdout.strip()
            if "..." in comment:
                pattern = ".*".join(re.escape(part) for part in comment.split("..."))
                assert re.fullmatch(pattern, out), (line, out)
            elif argv[0] == "curl" and out:
                json.loads(out)  # every answer is JSON
                if comment:
                    assert json.loads(out) == json.loads(comment), line
            elif comment:
                assert out == comment, line
