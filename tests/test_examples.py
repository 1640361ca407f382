"""The shipped example config: reachable from the installed package, pointed at the simulators
(their default ports, or ports moved together with --base-port), and every tag of it reads good."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from plcstack.cli import build_parser, main
from plcstack.cli.demo import example_config
from plcstack.config import parse_config
from plcstack.poll.engine import Poller, Quality
from plcstack.sim import e71, s5lan
from tests.ports import free_ports_in_a_row


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
        config = parse_config(text).poll
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
    # the comment's commands name the file they are in, not the default name
    assert target.read_text() == example_config().replace(" plant.toml", f" {target}")
    assert f"#   plcstack poll {target} --duration 5" in target.read_text()
    assert "plcstack poll" in capsys.readouterr().err
    assert main(["demo", "--write-config", str(target)]) == 2  # never overwritten
    assert "exists" in capsys.readouterr().err
    assert main(["demo", "--write-config", "-"]) == 0
    assert capsys.readouterr().out == example_config()


async def test_base_port_moves_the_config_and_its_sim_commands_together(tmp_path: Path) -> None:
    # the sim commands the written file shows start simulators exactly where its URLs point
    base = free_ports_in_a_row(3)
    target = tmp_path / "plant.toml"
    argv = ["demo", "--write-config", str(target), "--base-port", str(base)]
    assert await asyncio.to_thread(main, argv) == 0
    text = target.read_text()
    for default in (5000, 5010, 4840):
        assert f"127.0.0.1:{default}" not in text
    assert f"opc.tcp://127.0.0.1:{base + 2}/plcstack" in text
    commands = [
        line[1:].split("#", 1)[0].strip().rstrip("&").split()[1:]
        for line in text.splitlines()
        if line.startswith("#   plcstack sim ")
    ]
    assert [c[:2] for c in commands] == [["sim", "e71"], ["sim", "s5lan"]]
    ports = [build_parser().parse_args(c).port for c in commands]
    assert ports == [base, base + 1]
    config = parse_config(text.replace("fast = 0.2", "fast = 0.05")).poll
    assert [p.url for p in config.plcs] == [
        f"e71+tcp://127.0.0.1:{base}",
        f"s5lan://127.0.0.1:{base + 1}",
    ]
    async with (
        await e71.start(port=ports[0]),
        await s5lan.start(port=ports[1]),
        Poller(config) as poller,
        asyncio.timeout(10),
    ):
        async for sample in poller:
            assert sample.quality is Quality.GOOD, sample.error
            if sample.plc == "oven2":
                break


def test_base_port_alone_or_out_of_range_is_a_usage_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["demo", "--base-port", "7000"]) == 2
    assert "give both" in capsys.readouterr().err
    assert main(["demo", "--write-config", "-", "--base-port", "65534"]) == 2
    assert "1..65533" in capsys.readouterr().err
