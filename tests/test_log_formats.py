"""Log lines for a terminal, for journald and for machines, checked line by line.

journald: systemd sets ``JOURNAL_STREAM=DEVICE:INODE`` of the stream it gave the service as
stderr. The tests give ``plcstack poll`` a file as stderr and that file's device and inode as
the variable, which is exactly what the command can see of journald; a variable naming another
stream (inherited by a child whose stderr was redirected) must change nothing.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import sys
from pathlib import Path

import pytest

from plcstack.cli import main
from plcstack.logs import JsonFormatter, formatter, journal_priority, on_journal
from plcstack.sim import e71
from plcstack.sim.melsec_memory import MelsecMemory
from tests.aio_helpers import eventually
from tests.systemd_helpers import two_plcs

ROOT = Path(__file__).resolve().parent.parent

TERMINAL = re.compile(r"\d\d:\d\d:\d\d (DEBUG|INFO|WARNING|ERROR|CRITICAL) plcstack[\w.]*: .+")
JOURNAL = re.compile(r"<[2-7]>plcstack[\w.]*: .+")
#: what every format says of the two PLCs of ``poll_with_stderr``
SAID = ("PLC press1 is online", "PLC oven2 is offline: ")


async def poll_with_stderr(tmp_path: Path, *options: str, journal: str | None = None) -> list[str]:
    """``plcstack OPTIONS poll`` of one PLC that answers and one that refuses, stderr into a
    file, until it said both (then SIGTERM: a fixed --duration can end first on a loaded
    machine); ``journal``: what JOURNAL_STREAM says ("this": the file's own device:inode).
    The stderr lines, without the statistics table."""
    sim = await e71.start(MelsecMemory())
    config = two_plcs(tmp_path, sim.url, 0.2)
    err = tmp_path / "stderr.txt"
    env = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
    try:
        with err.open("wb") as stream:
            if journal is not None:
                st = os.fstat(stream.fileno())
                env["JOURNAL_STREAM"] = f"{st.st_dev}:{st.st_ino}" if journal == "this" else journal
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "plcstack", *options, "poll", str(config),
                "--format", "none", "-v",
                cwd=ROOT, env=env, stdout=asyncio.subprocess.DEVNULL, stderr=stream,
            )  # fmt: skip
            try:
                await eventually(
                    lambda: (
                        proc.returncode is not None or all(said in err.read_text() for said in SAID)
                    ),
                    "plcstack poll said both PLCs' states",
                    timeout=30,
                )
            finally:
                if proc.returncode is None:
                    proc.terminate()
                code = await asyncio.wait_for(proc.wait(), 30)
            assert code == 0, err.read_text()
    finally:
        await sim.aclose()
    text = err.read_text()
    table = text.index("plc ")  # the statistics at the end: printed, not logged
    return text[:table].splitlines()


def test_terminal_lines_are_as_before() -> None:
    made = record(logging.WARNING, "PLC oven2 is offline: no answer")
    assert TERMINAL.fullmatch(formatter("text").format(made))
    assert (
        formatter("text")
        .format(made)
        .endswith(" WARNING plcstack.north: PLC oven2 is offline: no answer")
    )


async def test_journald_lines_start_with_their_priority_and_carry_no_time(tmp_path: Path) -> None:
    lines = await poll_with_stderr(tmp_path, journal="this")
    assert lines
    for line in lines:
        assert JOURNAL.fullmatch(line), line
    assert any(x.startswith("<4>plcstack.north: PLC oven2 is offline: ") for x in lines), lines
    assert any(x.startswith("<6>plcstack.north: PLC press1 is online") for x in lines), lines


async def test_json_lines(tmp_path: Path) -> None:
    lines = await poll_with_stderr(tmp_path, "--log-format", "json")
    records = [json.loads(line) for line in lines]  # every line is one object
    assert records
    for record in records:
        assert {"time", "level", "logger", "message"} <= set(record), record
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", record["time"]), record
        assert record["level"] in {"DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"}
        assert record["logger"].startswith("plcstack")
    offline = [r for r in records if r["message"].startswith("PLC oven2 is offline: ")]
    assert offline and offline[0]["plc"] == "oven2" and offline[0]["level"] == "WARNING"
    online = [r for r in records if r["message"] == "PLC press1 is online"]
    assert online and online[0]["plc"] == "press1"


def test_json_lines_under_journald_start_with_the_priority() -> None:
    line = formatter("json", journal=True).format(record(logging.ERROR, "x", plc="p"))
    assert line.startswith("<3>{")
    assert json.loads(line[3:])["plc"] == "p"


def record(level: int, message: str, **extra: object) -> logging.LogRecord:
    made = logging.LogRecord("plcstack.north", level, __file__, 1, message, None, None)
    made.__dict__.update(extra)
    return made


def test_priorities() -> None:
    levels = [logging.CRITICAL, logging.ERROR, logging.WARNING, 25, logging.INFO, logging.DEBUG]
    assert [journal_priority(x) for x in levels] == [2, 3, 4, 5, 6, 7]


def test_every_line_of_a_traceback_gets_the_priority() -> None:
    try:
        raise ValueError("bad\nvalue")
    except ValueError:
        made = record(logging.ERROR, "a sink failed")
        made.exc_info = sys.exc_info()
    lines = formatter("text", journal=True).format(made).split("\n")
    assert lines[0] == "<3>plcstack.north: a sink failed"
    assert len(lines) > 3 and all(line.startswith("<3>") for line in lines)


def test_json_context_and_newlines() -> None:
    line = JsonFormatter().format(
        record(logging.WARNING, "two\nlines", plc="press1", tag="x", face="mqtt", other=1)
    )
    assert "\n" not in line
    parsed = json.loads(line)
    assert parsed["message"] == "two\nlines"
    assert (parsed["plc"], parsed["tag"], parsed["face"]) == ("press1", "x", "mqtt")
    assert "other" not in parsed
    assert "plc" not in json.loads(JsonFormatter().format(record(logging.INFO, "x")))


def test_on_journal_compares_the_stream(tmp_path: Path) -> None:
    with (tmp_path / "a").open("w") as a, (tmp_path / "b").open("w") as b:
        st = os.fstat(a.fileno())
        env = {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        assert on_journal(env, a.fileno())
        assert not on_journal(env, b.fileno())
        assert not on_journal({}, a.fileno())
        assert not on_journal({"JOURNAL_STREAM": "garbage"}, a.fileno())


def test_an_error_line_is_an_error_in_the_journal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """The one ``plcstack: error:`` line of a failed command is filed at priority 3."""
    st = os.fstat(2)  # capfd's file behind fd 2: journald's stream, as far as main() can see
    monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
    assert main(["poll", str(tmp_path / "missing.toml")]) == 2
    assert capfd.readouterr().err.startswith("<3>plcstack: error: cannot read ")
    monkeypatch.delenv("JOURNAL_STREAM")
    assert main(["poll", str(tmp_path / "missing.toml")]) == 2
    assert capfd.readouterr().err.startswith("plcstack: error: cannot read ")
