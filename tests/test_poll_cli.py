"""CLI pieces of ``plcstack poll`` and ``plcstack demo`` that need no simulator."""

from __future__ import annotations

from argparse import Namespace
from pathlib import Path

import pytest

from plcstack.cli import build_parser, main
from plcstack.cli.demo import clip, plain_line, run_demo
from plcstack.poll.engine import Quality, Sample


def test_clip_keeps_ansi_and_cuts_visible_text() -> None:
    assert clip("\x1b[1mhello\x1b[0m world", 7) == "\x1b[1mhello\x1b[0m w"
    assert clip("abc", 10) == "abc"
    assert clip("\x1b[32mabc\x1b[0m", 0) == "\x1b[32m\x1b[0m"


def test_plain_line() -> None:
    good = Sample("p1", "light", [True, False], Quality.GOOD, 0.0, 0.001)
    assert plain_line(good).endswith(" p1 light good #.")
    s5 = Sample("p2", "light", 8, Quality.GOOD, 0.0, 0.001)  # an S5 flag byte
    assert plain_line(s5).endswith(" p2 light good ...#....")
    bad = Sample("p1", "t", None, Quality.BAD, 0.0, 0.0, "p1: read D0 x1: no answer")
    assert plain_line(bad).endswith(" p1 t bad p1: read D0 x1: no answer")


def test_commands_are_registered() -> None:
    parser = build_parser()
    args = parser.parse_args(["poll", "x.toml", "--format", "influx", "--duration", "2"])
    assert (args.config, args.format, args.duration) == ("x.toml", "influx", 2.0)
    args = parser.parse_args(["demo", "--plcs", "5"])
    assert (args.plcs, args.duration) == (5, None)


async def test_bad_arguments_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert await run_demo(Namespace(plcs=0, duration=None, interval=0.25)) == 2
    assert await run_demo(Namespace(plcs=None, duration=-1.0, interval=0.25)) == 2
    assert "must be" in capsys.readouterr().err
    # the options every running command shares are checked by the parser, before the file
    for argv, option in [
        (["poll", "x.toml", "--duration", "0"], "--duration"),
        (["poll", "x.toml", "--stats-every", "0"], "--stats-every"),
        (["poll", "x.toml", "--web-port", "70000"], "--web-port"),
        (["poll", "x.toml", "--metrics-port", "-1"], "--metrics-port"),
        (["serve", "modbus", "x.toml", "--duration", "-1"], "--duration"),
        (["serve", "opcua", "x.toml", "--metrics-port", "70000"], "--metrics-port"),
    ]:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "must be" in err and option in err, err


def test_missing_or_invalid_config_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["poll", str(tmp_path / "nope.toml")]) == 2
    assert "cannot read" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text('[[plc]]\nname = "press"\nurl = "e71+tcp://127.0.0.1:1"\n[plc.tags]\nx = 5\n')
    assert main(["poll", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "press" in err and "tag 'x'" in err and "bad.toml:5" in err
