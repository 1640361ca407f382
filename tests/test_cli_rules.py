"""The command line's shared rules: exit codes, one-line failures, Ctrl-C, logging, help texts.

The rule (``plcstack.cli``): 0 success, 1 the PLC side failed, 2 bad usage (simulator start-up
errors included), 130 Ctrl-C. Every failure is one line on stderr.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import re
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

import plcstack
from plcstack.cli import _all_parsers, build_parser, main
from plcstack.logs import install_trace
from plcstack.sim import e71 as e71_sim
from tests.ports import free_port

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("plcstack: error: "), err
    return lines[0]


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0  # main returns the exit code, --version included
    assert capsys.readouterr().out.strip() == f"plcstack {plcstack.__version__}"


@pytest.fixture
def busy_port() -> Iterator[int]:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield sock.getsockname()[1]


@pytest.mark.parametrize("simulator", ["e71", "s5lan", "as511", "fetchwrite"])
def test_sim_on_a_busy_port_is_exit_2_with_one_line(
    simulator: str, busy_port: int, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["sim", simulator, "--port", str(busy_port)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert f"sim {simulator} cannot start on 127.0.0.1:{busy_port}" in line
    assert "in use" in line


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["sim", "e71", "--port", "80000"], "--port 80000: a port is 0..65535"),
        (["sim", "s5lan", "--port", "-1"], "--port -1: a port is 0..65535"),
        (["sim", "fetchwrite", "--port", "0", "--write-port", "70000"], "--write-port 70000"),
        (["sim", "as511", "--port", "0", "--baud", "0"], "--baud 0: a baud rate is a positive"),
        (["sim", "fetchwrite", "--port", "0", "--life-ack", "5"], "--life-ack needs --mk"),
        (["sim", "e71", "--host", "nosuchhost.invalid", "--port", "0"], "cannot start on"),
    ],
)
def test_sim_start_up_errors_are_exit_2_with_one_line(
    argv: list[str], words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2
    assert words in _one_error_line(capsys.readouterr().err)


def test_plc_failure_is_exit_1_with_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    port = free_port()  # nobody listens there
    assert main(["read", f"e71+tcp://127.0.0.1:{port}", "D0"]) == 1
    assert "cannot connect" in _one_error_line(capsys.readouterr().err)


def test_internal_error_is_one_line_exit_1(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    async def broken(args: argparse.Namespace) -> int:
        raise KeyError("oops")

    import plcstack.cli.io as io

    monkeypatch.setattr(io, "run_read", broken)
    assert main(["read", "e71+tcp://127.0.0.1:1", "D0"]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == ["plcstack: internal error: KeyError: 'oops' (a bug; -vv shows the traceback)"]


def _run_until_first_line(
    argv: list[str], sig: signal.Signals, *, sigint_ignored: bool = False
) -> tuple[int, str, str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "plcstack", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
        # a parent that ignores SIGINT (some shells and test runners): the child inherits it
        preexec_fn=(lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
        if sigint_ignored
        else None,
    )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, first + out, err


@pytest.mark.parametrize(
    ("argv", "sig", "code"),
    [
        (["sim", "e71", "--port", "0"], signal.SIGINT, 130),
        (["sim", "e71", "--port", "0", "--transport", "udp"], signal.SIGTERM, 0),
        (["demo", "--interval", "0.05"], signal.SIGINT, 130),
        (["demo", "--interval", "0.05"], signal.SIGTERM, 0),
    ],
)
def test_ctrl_c_is_130_and_sigterm_0(argv: list[str], sig: signal.Signals, code: int) -> None:
    rc, out, err = _run_until_first_line(argv, sig)
    assert rc == code, err
    assert "Traceback" not in err
    if argv[0] == "demo":
        assert "requests" in err  # the statistics are still printed
    else:
        proto = "UDP" if "udp" in argv else "TCP"
        assert out.startswith("listening on 127.0.0.1:") and f"({proto})" in out


def test_every_subcommand_takes_log_options() -> None:
    parser = build_parser()
    for each in _all_parsers(parser):
        text = each.format_help()
        assert "--log-level" in text and "-v" in text, each.prog


def test_help_texts_are_plain_and_self_contained() -> None:
    for each in _all_parsers(build_parser()):
        text = each.format_help()
        for bad in ("``", "../shared", "DESIGN.md", "spec §", "[R]", "§"):
            assert bad not in text, (each.prog, bad)
        # an installed wheel has no docs/ folder: a page is named as the command that prints it
        assert not re.search(r"docs/[\w-]+\.md", text), (each.prog, "plcstack docs PAGE")


async def test_frame_trace_at_debug(caplog: pytest.LogCaptureFixture) -> None:
    async with await e71_sim.start() as sim:
        with caplog.at_level(logging.DEBUG, logger="plcstack.frames"):
            async with plcstack.connect(sim.url) as plc:
                await plc.write("D100", [0x1234])
                assert await plc.read("D100", 1) == [0x1234]
    lines = [r.getMessage() for r in caplog.records if r.name == "plcstack.frames.e71"]
    assert lines == [
        f"{sim.url} -> 03 ff 07 00 64 00 00 00 20 44 01 00 34 12",
        f"{sim.url} <- 83 00",
        f"{sim.url} -> 01 ff 07 00 64 00 00 00 20 44 01 00",
        f"{sim.url} <- 81 00 34 12",
    ]


async def test_no_trace_no_wrapper() -> None:
    """Off, the transport's methods are the class's own: nothing added on the request path."""
    logging.getLogger("plcstack.frames").setLevel(logging.INFO)
    try:
        plc = plcstack.connect("e71+tcp://127.0.0.1:1")
        assert "write" not in vars(plc.transport) and "read" not in vars(plc.transport)
        assert install_trace(plc.transport, "x", "e71") is False
        await plc.aclose()
    finally:
        logging.getLogger("plcstack.frames").setLevel(logging.NOTSET)


def test_verbose_flag_shows_the_trace_in_a_subprocess() -> None:
    async def run() -> tuple[str, str]:
        async with await e71_sim.start() as sim:
            proc = await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                "plcstack",
                "read",
                sim.url,
                "D0",
                "2",
                "-vv",
                stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.PIPE,
                env=ENV,
            )
            _, err = await asyncio.wait_for(proc.communicate(), 30)
            assert proc.returncode == 0, err
            return sim.url, err.decode()

    url, err = asyncio.run(run())
    assert f"DEBUG plcstack.frames.e71: {url} -> 01 ff 07 00 00 00 00 00 20 44 02 00" in err
    assert f"DEBUG plcstack.frames.e71: {url} <- 81 00 00 00 00 00" in err


@pytest.mark.parametrize("argv", [["sim", "e71", "--port", "0"], ["demo", "--interval", "0.05"]])
def test_ctrl_c_works_when_the_parent_ignored_sigint(argv: list[str]) -> None:
    """asyncio.run handles SIGINT only if it had its default handler at start-up; `sim` once
    never ended in CI that way. Every subcommand installs its own handlers."""
    rc, _, err = _run_until_first_line(argv, signal.SIGINT, sigint_ignored=True)
    assert rc == 130, err


def test_a_refused_connection_says_nothing_listens_there(
    capsys: pytest.CaptureFixture[str],
) -> None:
    port = free_port()  # nobody listens there: the kernel answers with a reset
    assert main(["read", f"e71+tcp://127.0.0.1:{port}", "D0"]) == 1
    assert _one_error_line(capsys.readouterr().err) == (
        f"plcstack: error: e71+tcp://127.0.0.1:{port}: connect: cannot connect to 127.0.0.1:"
        f"{port}: connection refused, nothing listens on that port (wrong port, the module's "
        "connection not open, or the simulator not running)"
    )
