"""SIGHUP never ends a plcstack process; SIGTERM and Ctrl-C still end it cleanly.

Before: ``kill -HUP`` ended ``poll`` with exit 129, no statistics and no offline statuses, and
``serve modbus`` died with no log line (SIGHUP's default action).
"""

from __future__ import annotations

import asyncio
import logging
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from plcstack.cli.signals import Signals, StopEvent
from tests.ports import free_port

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


async def test_a_hangup_is_said_once_and_changes_nothing(caplog: pytest.LogCaptureFixture) -> None:
    stop = StopEvent()
    with caplog.at_level(logging.DEBUG, "plcstack.cli.signals"), Signals(stop) as signals:
        for _ in range(3):
            os.kill(os.getpid(), signal.SIGHUP)
            await asyncio.sleep(0.05)
        assert not stop.is_set()
        assert signals.hangups == 3
        os.kill(os.getpid(), signal.SIGTERM)
        async with asyncio.timeout(5):
            await stop.wait()
    assert stop.exit_code() == 0
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert [r.getMessage().split(":")[0] for r in warned] == ["SIGHUP received"]
    assert sum(r.levelno == logging.DEBUG for r in caplog.records) == 2


async def test_a_hangup_handler_is_called_for_each_hangup() -> None:
    calls: list[int] = []
    with Signals(asyncio.Event(), lambda: calls.append(1)):
        os.kill(os.getpid(), signal.SIGHUP)
        os.kill(os.getpid(), signal.SIGHUP)
        async with asyncio.timeout(5):
            while len(calls) < 2:  # noqa: ASYNC110 - waits for the handler
                await asyncio.sleep(0.01)


def _start(argv: list[str], cwd: Path) -> subprocess.Popen[bytes]:
    # unbuffered: a line read must not take the next one into a buffer select() cannot see
    return subprocess.Popen(
        [sys.executable, "-m", "plcstack", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        bufsize=0,
        env=ENV,
        cwd=cwd,
    )


def _wait_for(proc: subprocess.Popen[bytes], text: str, timeout: float = 20.0) -> None:
    """Until ``text`` appears on the process's stdout or stderr (read line by line)."""
    assert proc.stdout is not None and proc.stderr is not None
    deadline = time.monotonic() + timeout
    streams = [proc.stdout, proc.stderr]
    said: list[str] = []
    while time.monotonic() < deadline:
        ready, _, _ = select.select(streams, [], [], 0.2)
        for stream in ready:
            line = stream.readline().decode()
            said.append(line)
            if text in line:
                return
        assert proc.poll() is None, f"{proc.args!r} ended: {proc.communicate()}"
    raise AssertionError(f"{proc.args!r} never said {text!r}, only {said}")


@pytest.mark.slow  # five interpreters start: a few seconds on a loaded machine
def test_sighup_ends_no_plcstack_command(tmp_path: Path) -> None:
    e71_port, as511_port, modbus_port, s5lan_port = (free_port() for _ in range(4))
    plc = (
        "[poll]\ninterval = 0.2\n"
        f'[[plc]]\nname = "press1"\nurl = "e71+tcp://127.0.0.1:{e71_port}"\n'
        '[plc.tags]\nstrokes = { address = "D100", modbus = "hr:0" }\n'
    )
    (tmp_path / "poll.toml").write_text(plc)
    (tmp_path / "serve.toml").write_text(f'[modbus]\nendpoint = "127.0.0.1:{modbus_port}"\n' + plc)
    sims = [
        _start(["sim", "e71", "--port", str(e71_port)], tmp_path),
        _start(["sim", "as511", "--port", str(as511_port)], tmp_path),
    ]
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for sim in sims:
            _wait_for(sim, "listening on")
        gateway = ["gateway", f"as511+tcp://127.0.0.1:{as511_port}", "--s5lan", str(s5lan_port)]
        procs = [
            _start(["-v", "poll", "poll.toml", "--format", "none", "--web-port", "0"], tmp_path),
            _start(["-v", "serve", "modbus", "serve.toml"], tmp_path),
            _start(gateway, tmp_path),
        ]
        _wait_for(procs[0], "web console on")
        _wait_for(procs[1], "Modbus server listening on")
        _wait_for(procs[2], "listening on")
        for proc in [*procs, *sims]:
            proc.send_signal(signal.SIGHUP)
        time.sleep(0.5)
        alive = [proc.args for proc in [*procs, *sims] if proc.poll() is not None]
        assert not alive, f"ended by SIGHUP: {alive}"
        for proc in [*procs, *sims]:
            proc.send_signal(signal.SIGTERM)
        for proc in [*procs, *sims]:
            _out, raw = proc.communicate(timeout=20)
            err = raw.decode()
            assert proc.returncode == 0, (proc.args, err)
            # poll and serve read their file again and apply it (and say so); the others ignore
            # it, once
            reloaded = "reload (SIGHUP): PLCs added: none; removed: none; changed: none"
            said = reloaded if proc in procs[:2] else "SIGHUP received"
            assert err.count(said) == 1, (proc.args, err)
            assert "Traceback" not in err
    finally:
        for proc in [*procs, *sims]:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
