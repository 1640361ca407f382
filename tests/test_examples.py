"""The shipped example config: reachable from the installed package, pointed at the simulators'
default ports, and every tag of it reads good against them."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from plcstack.cli import build_parser, main
from plcstack.cli.demo import example_config
from plcstack.poll.config import parse_config
from plcstack.poll.engine import Poller, Quality
from plcstack.sim import e71, s5lan


def _default_port(simulator: str) -> int:
    args = build_parser().parse_args(["sim", simulator])
    port: int = args.port
    return port


def test_example_points_at_the_simulators_default_ports() -> None:
    text = example_config()
    assert f'url = "e71+tcp://127.0.0.1:{_default_port("e71")}"' in text
    assert f'url = "s5lan://127.0.0.1:{_default_port("s5lan")}"' in text


async def test_every_tag_of_the_example_reads_good() -> None:
    # the same simulators `plcstack sim e71` / `sim s5lan` run, on free ports instead of 5000/5010
    async with await e71.start() as sim1, await s5lan.start() as sim2:
        text = example_config()
        text = text.replace("e71+tcp://127.0.0.1:5000", sim1.url)
        text = text.replace("s5lan://127.0.0.1:5010", sim2.url)
        text = text.replace("fast = 0.2", "fast = 0.05").replace(
            "interval = 1.0", "interval = 0.05"
        )
        config = parse_config(text)
        expected = {(p.name, t.name) for p in config.plcs for t in p.tags}
        seen = {}
        async with Poller(config) as poller:
            async with asyncio.timeout(10):
                async for s in poller:
                    seen[s.plc, s.tag] = s
                    if set(seen) == expected:
                        break
    bad = [f"{k}: {s.error}" for k, s in seen.items() if s.quality is not Quality.GOOD]
    assert not bad


def test_write_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "plant.toml"
    assert main(["demo", "--write-config", str(target)]) == 0
    assert target.read_text() == example_config()
    assert "plcstack poll" in capsys.readouterr().err
    assert main(["demo", "--write-config", str(target)]) == 2  # never overwritten
    assert "exists" in capsys.readouterr().err
    assert main(["demo", "--write-config", "-"]) == 0
    assert capsys.readouterr().out == example_config()
