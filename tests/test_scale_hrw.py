"""Rendezvous hashing and static shards (``plcstack poll --shard i/N``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.cli import main
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.scale.cli import select
from plcstack.scale.hrw import (
    ShardSpec,
    assign,
    index_from_hostname,
    owner,
    parse_shard,
    shard_config,
    weight,
)

names = st.text(min_size=1, max_size=20)


def test_weight_golden_values() -> None:
    # Workers of two releases must agree on every owner: these numbers may never change.
    assert weight("shard-0", "press1") == 13271839748658707948
    assert weight("w1", "oven2") == 18013475561061357278
    assert owner("press1", ["shard-0", "shard-1", "shard-2"]) == "shard-0"


def test_no_worker_no_owner() -> None:
    assert owner("press1", []) is None
    assert assign(["press1"], []) == {}


@given(st.lists(names, min_size=1, max_size=6, unique=True), names)
def test_owner_ignores_worker_order(workers: list[str], plc: str) -> None:
    assert owner(plc, workers) == owner(plc, list(reversed(workers))) == owner(plc, sorted(workers))


@settings(max_examples=30)
@given(st.lists(names, min_size=1, max_size=5, unique=True), names)
def test_a_new_worker_takes_only_plcs_it_wins(workers: list[str], newcomer: str) -> None:
    if newcomer in workers:
        return
    plcs = [f"plc{i}" for i in range(200)]
    before = assign(plcs, workers)
    after = assign(plcs, [*workers, newcomer])
    for plc in plcs:
        # a PLC either stays where it was or moves to the newcomer, never between old workers
        assert after[plc] in (before[plc], newcomer)
    # and leaving again puts every PLC back where it was
    assert assign(plcs, workers) == before


def test_balance_and_movement_over_a_fleet() -> None:
    plcs = [f"plc{i}" for i in range(3000)]
    three = assign(plcs, ["a", "b", "c"])
    counts = {w: sum(1 for v in three.values() if v == w) for w in "abc"}
    assert all(850 < c < 1150 for c in counts.values()), counts
    four = assign(plcs, ["a", "b", "c", "d"])
    moved = sum(three[p] != four[p] for p in plcs)
    assert 600 < moved < 900  # about 1/4 of 3000


def test_parse_shard() -> None:
    spec = parse_shard("2/5")
    assert (spec.index, spec.count) == (2, 5)
    spec = parse_shard("host/4", hostname="plcstack-3.plcstack.svc.cluster.local")
    assert (spec.index, spec.count) == (3, 4)
    for bad in ("3", "a/3", "1/x", "3/3", "-1/3", "0/0"):
        with pytest.raises(ValueError):
            parse_shard(bad)
    with pytest.raises(ValueError, match="does not end in a number"):
        parse_shard("host/3", hostname="gateway")
    assert index_from_hostname("worker12") == 12


def _config(n: int) -> PollConfig:
    tags = (TagConfig("x", "D0"),)
    return PollConfig(
        plcs=tuple(PlcConfig(f"plc{i}", "e71+tcp://127.0.0.1:1", tags) for i in range(n)),
        groups={"default": 0.1},
        queue=123,
    )


def test_shards_partition_the_fleet() -> None:
    config = _config(50)
    seen: list[str] = []
    for i in range(3):
        part = shard_config(config, i, 3)
        assert part.queue == 123 and part.groups == config.groups
        assert all(ShardSpec(i, 3).owns(p.name) for p in part.plcs)
        seen.extend(p.name for p in part.plcs)
    assert sorted(seen) == sorted(p.name for p in config.plcs)


def test_select_without_shard_keeps_everything() -> None:
    import argparse

    config = _config(3)
    assert select(config, argparse.Namespace(shard=None)) is config


def test_cli_polls_only_its_shard(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "fleet.toml"
    lines = ["[poll]", "interval = 0.1", "connect_timeout = 0.2", "backoff_max = 0.2"]
    for i in range(12):
        # nothing listens on port 1: every scan is a bad sample, which still names its PLC
        lines += ["[[plc]]", f'name = "plc{i}"', 'url = "e71+tcp://127.0.0.1:1"']
        lines += ["[plc.tags]", 'x = "D0"']
    path.write_text("\n".join(lines) + "\n")
    assert main(["poll", str(path), "--shard", "1/3", "--duration", "0.5"]) == 0
    out = capsys.readouterr().out
    polled = {json.loads(line)["plc"] for line in out.splitlines()}
    expected = {f"plc{i}" for i in range(12) if ShardSpec(1, 3).owns(f"plc{i}")}
    assert polled == expected and expected
    assert main(["poll", str(path), "--shard", "3/3"]) == 2
    assert "shard index" in capsys.readouterr().err


def test_cli_scale_options_that_exclude_each_other(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "one.toml"
    path.write_text('[[plc]]\nname = "p"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\nx = "D0"\n')
    assert main(["poll", str(path), "--nats", "nats://127.0.0.1:4222"]) == 2
    assert "--nats needs --mqtt" in capsys.readouterr().err
    assert main(["poll", str(path), "--shard", "0/2", "--mqtt", "mqtt://127.0.0.1:1"]) == 2
    assert "exclude each other" in capsys.readouterr().err
    assert main(["poll", str(path), "--mqtt", "http://x"]) == 2
    assert "mqtt://HOST:PORT" in capsys.readouterr().err
