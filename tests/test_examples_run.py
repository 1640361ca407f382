"""Every example in examples/ runs as its docstring says, against the simulators.

Each script is started as a user starts it (``python examples/NAME.py URL``, a new interpreter,
the installed package) against an in-process simulator on a free port; its output and the
simulator's memory show it did what it says. The north config polls a simulator into a real
mosquitto through ``plcstack poll``.
"""

from __future__ import annotations

import asyncio
import json
import struct
import sys
from pathlib import Path

from plcstack.sim import e71, s5lan
from tests.north_helpers import subscriber
from tests.servers import Mosquitto, free_port

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


async def run(*argv: str, timeout: float = 30) -> str:
    """``python ARGV`` to the end: its stdout; a non-zero exit fails with its stderr."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, *argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    async with asyncio.timeout(timeout):
        out, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()
    return out.decode()


async def test_read_write() -> None:
    async with await e71.start() as sim:
        out = await run(str(EXAMPLES / "read_write.py"), sim.url)
        assert sim.memory.read_words("D", 100, 4) == [1, 2, 3, 4]
    assert out.splitlines() == ["D100..D103: [1, 2, 3, 4]", "M0..M2: [True, False, True]"]


async def test_typed_values() -> None:
    async with await e71.start() as plc, await s5lan.start() as s5:
        out = await run(str(EXAMPLES / "typed_values.py"), plc.url, s5.url)
    assert out.splitlines() == [
        "float32: 21.5",
        "int32:   [-100000, 70000]",
        "text:    PRESS 1",
        "by name: 21.5",
        "KG:      10.0",
    ]


async def test_blocking() -> None:
    async with await s5lan.start() as sim:
        out = await run(str(EXAMPLES / "blocking.py"), sim.url)
    lines = out.splitlines()
    assert lines[:2] == ["DB10.DW0..2: [10, 20, 30]", "DB10.DW3 as int16: -5"]
    assert lines[2].startswith("refused: ") and "MELSEC notation" in lines[2]


async def test_poller_sink() -> None:
    async with await e71.start() as sim:
        sim.memory.write_words("D", 100, [42])
        sim.memory.write_words("D", 102, list(struct.unpack("<2H", struct.pack("<f", 2.5))))
        out = await run(str(EXAMPLES / "poller_sink.py"), sim.url, "1")
    assert out.splitlines()[-1] == "done: {'press1.strokes': 42, 'press1.force': 2.5}, 0 bad"


async def test_north_config_publishes_to_a_real_broker(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    text = (EXAMPLES / "north.toml").read_text(encoding="utf-8")
    async with await e71.start() as sim:
        sim.memory.write_words("D", 100, [7])
        # the example's addresses, each on this run's own (one that no longer matches fails
        # here, not as a port another test holds)
        for documented, ours in (
            ("e71+tcp://127.0.0.1:5000", sim.url),
            ("mqtt://127.0.0.1:1883", mosquitto.url),
            ('listen = "127.0.0.1:9108"', f'listen = "127.0.0.1:{free_port()}"'),
        ):
            assert documented in text, documented
            text = text.replace(documented, ours)
        config = tmp_path / "north.toml"
        config.write_text(text, encoding="utf-8")
        host, port = mosquitto.url.removeprefix("mqtt://").split(":")
        async with subscriber(host, int(port), "plcstack/press1/#") as sub:
            # run until the first scan arrived, then stopped as a service is (SIGTERM, exit 0):
            # a fixed --duration could end before a loaded machine had published anything
            poll = await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                "plcstack",
                "poll",
                str(config),
                "--format",
                "none",
                stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.PIPE,
            )
            try:
                await sub.wait_for(
                    lambda s: (
                        poll.returncode is not None
                        or any(t == "plcstack/press1/data/default" for t, _ in s.messages)
                    ),
                    timeout=20,
                )
            finally:
                if poll.returncode is None:
                    poll.terminate()
                async with asyncio.timeout(20):
                    _, err = await poll.communicate()
            assert poll.returncode == 0, err.decode()
    data = [json.loads(m) for t, m in sub.messages if t == "plcstack/press1/data/default"]
    assert data, f"plcstack poll published no data: {err.decode()}"
    assert data[0]["values"]["strokes"] == 7 and data[0]["values"]["running"] is False
