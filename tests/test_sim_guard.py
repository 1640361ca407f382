"""``plcstack sim`` takes the limits of a listening face (``--max-clients``,
``--max-clients-per-host``, ``--first-request-timeout``, ``--idle-timeout``), and the replay
of a capture is guarded as every simulator is.

Before: ``plcstack sim`` took only ``--idle-timeout``; a replayed server served any number of
silent sockets for the idle timeout (600 s) and said each different request it did not hold
once, remembering every one of them (a flood of distinct requests grew that memory).
"""

from __future__ import annotations

import asyncio
import logging
import os
import sys
from pathlib import Path

import pytest

import plcstack
from plcstack.cli import build_parser, main
from plcstack.sim.base import limits_of
from plcstack.transports.guard import Limits
from plcstack.wire import replay
from tests.aio_helpers import eventually
from tests.guard_helpers import ATTACKER, guard_lines, idle_sockets
from tests.test_cli_rules import _one_error_line
from tests.test_wire_replay import record_one_read

ROOT = Path(__file__).resolve().parent.parent

#: every simulator, with the arguments it needs besides the options
SIMULATORS = [
    (["e71"], 8),
    (["s5lan"], 1),
    (["fetchwrite"], 16),
    (["as511"], 16),
    (["replay", "capture.pcapng"], 16),
]


@pytest.mark.parametrize(("argv", "module_connections"), SIMULATORS)
def test_every_simulator_takes_the_limits_of_a_face(
    argv: list[str], module_connections: int
) -> None:
    parse = build_parser().parse_args
    defaults = limits_of(parse(["sim", *argv]))
    assert defaults == Limits(module_connections, module_connections, 10.0, 600.0)
    given = parse(
        ["sim", *argv, "--max-clients", "4", "--max-clients-per-host", "2",
         "--first-request-timeout", "500ms", "--idle-timeout", "0"]
    )  # fmt: skip
    assert limits_of(given) == Limits(4, 2, 0.5, None)
    off = parse(["sim", *argv, "--first-request-timeout", "0", "--idle-timeout", "2m"])
    assert limits_of(off) == Limits(module_connections, module_connections, None, 120.0)


@pytest.mark.parametrize(
    ("options", "words"),
    [
        (["--max-clients", "2", "--max-clients-per-host", "3"], "cannot be more than"),
        (
            ["--first-request-timeout", "ten"],
            "--first-request-timeout: must be a number of seconds",
        ),
        (["--max-clients", "0"], "--max-clients: must be a whole number 1..10000"),
    ],
)
def test_limits_a_simulator_cannot_take_are_exit_2(
    options: list[str], words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["sim", "e71", "--port", "0", *options]) == 2
    assert words in _one_error_line(capsys.readouterr().err)


async def test_sim_closes_silent_sockets_at_the_first_request_timeout_it_was_given() -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "plcstack", "sim", "e71", "--port", "0",
        "--first-request-timeout", "300ms", "--max-clients", "2",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=env,
    )  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    try:
        line = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode()
        assert line.startswith("listening on 127.0.0.1:"), line
        port = int(line.split()[2].rsplit(":", 1)[1])
        readers = []
        for _ in range(3):
            readers.append(await asyncio.open_connection("127.0.0.1", port))
        loop = asyncio.get_running_loop()
        began = loop.time()
        ends = await asyncio.wait_for(asyncio.gather(*(reader.read() for reader, _ in readers)), 10)
        took = loop.time() - began
        for _, writer in readers:
            writer.close()
    finally:
        proc.terminate()
        await asyncio.wait_for(proc.wait(), 15)
    err = (await proc.stderr.read()).decode()
    assert ends == [b"", b"", b""]  # one refused at once, two closed at their deadline
    assert 0.2 < took < 5, took
    assert "E71 simulator: refusing 127.0.0.1:" in err, err
    assert "no complete request within 0.3 s" in err, err


async def test_a_replayed_server_is_guarded_like_every_simulator(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    capture = await record_one_read(tmp_path / "one.pcapng")
    sim = await replay.start(capture, limits=Limits(4, 2, first_request_timeout=0.5))
    try:
        (guard,) = sim.guards.values()
        port = int(sim.url.rsplit(":", 1)[1])
        async with idle_sockets(port, count=12):
            await eventually(lambda: guard.refused == 10, "all but two sockets refused")
            # the per-host cap leaves the others a slot: a client is served at once
            async with plcstack.connect(f"e71+tcp://{sim.url}", timeout=2) as plc:
                assert await plc.read("D0", 1) == [0]
            await eventually(lambda: not guard.hosts[ATTACKER], "the silent sockets closed")
        assert guard.counts["first_request_timeout"] == 2
        for _ in range(20):  # requests the capture does not hold: said once, then counted
            async with plcstack.connect(f"e71+tcp://{sim.url}", timeout=1) as plc:
                with pytest.raises(plcstack.PlcError):
                    await plc.read("D1", 1)
        assert guard.counts["malformed"] == sim.mismatches == 20
    finally:
        await sim.aclose()
    attacker = guard_lines(caplog)
    assert len([line for line in attacker if "refus" in line]) == 2, attacker
    assert any("no complete request within 0.5 s" in line for line in attacker), attacker
    mine = [
        line
        for line in guard_lines(caplog, "127.0.0.1:")
        if "sent a request that is not in the capture" in line
    ]
    assert len(mine) == 1 and "differs at byte" in mine[0], mine
    said = [r.getMessage() for r in caplog.records]
    assert any("19 more malformed requests from 127.0.0.1" in line for line in said), said
