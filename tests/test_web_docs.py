"""docs/web.md's quickstart runs as written: its configuration and every command of its ``sh``
block, against a real ``plcstack sim e71`` and a real ``plcstack poll`` (both subprocesses), with
real ``curl``; the documented ports replaced by free ones. A trailing comment that shows output
must match (JSON compared as JSON)."""

from __future__ import annotations

import json
import os
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


def _block(text: str, lang: str) -> str:
    section = text.split("## Quickstart", 1)[1]
    return section.split(f"```{lang}\n", 1)[1].split("```", 1)[0]


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


def test_web_quickstart_runs(tmp_path: Path, background: list[subprocess.Popen[str]]) -> None:
    if shutil.which("curl") is None:
        pytest.fail("the quickstart uses curl, which is not installed")
    text = PAGE.read_text(encoding="utf-8")
    toml = _block(text, "toml")
    lines = [line.strip() for line in _block(text, "sh").splitlines() if line.strip()]
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
                argv = [*plcstack, *argv[1:]]
            done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=30)
            assert done.returncode == 0, (line, done.stderr)
            out = done.stdout.strip()
            if argv[0] == "curl":
                json.loads(out)  # every answer is JSON
                if comment:
                    assert json.loads(out) == json.loads(comment), line
            elif comment:
                assert out == comment, line
