"""CLI behaviour every protocol shares: usage errors are exit 2 with one clear stderr line."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from plcstack.cli import main
from plcstack.cli.io import parse_value
from plcstack.errors import AddressError


def test_bad_url_is_exit_2_with_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["read", "modbus://h:1", "D0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "plcstack: error: modbus://h:1: unknown scheme 'modbus'; known schemes: "
        "e71+tcp, e71+udp, s5lan, fetchwrite, as511, as511+tcp"
    ]


def test_value_syntax() -> None:
    assert [parse_value(v) for v in ["1", "-5", "0x1F", "true", "OFF"]] == [1, -5, 31, True, False]
    # integral decimals, as every north side's write grammar takes them
    assert [parse_value(v) for v in ["1201.0", "-5.0", "1.2e3"]] == [1201, -5, 1200]
    for text in ("nan", "inf", "1.5"):
        with pytest.raises(AddressError):
            parse_value(text)
    with pytest.raises(AddressError, match="'1.5' is not an integer"):
        parse_value("1.5")


def test_console_entry_point_runs_as_module() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "plcstack", "--help"], capture_output=True, text=True, check=True
    )
    assert "read" in out.stdout and "sim" in out.stdout


def test_a_decimal_raw_write_names_the_plc_and_the_type_it_needs(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # refused before anything is sent: nobody needs to listen on port 1
    assert main(["write", "e71+tcp://127.0.0.1:1", "D100", "1", "12.5"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "plcstack: error: e71+tcp://127.0.0.1:1: write D100: value '12.5' is not an integer or "
        "true/false; a decimal needs a type: --type float32 (two points per value)"
    ]


def test_a_terminal_that_is_not_utf8_gets_escapes_not_a_crash() -> None:
    """LANG=de_DE.ISO-8859-1 or a Windows code page: PYTHONIOENCODING=ascii stands in for it."""
    docs = Path(__file__).resolve().parents[1] / "docs"
    page = next(p for p in sorted(docs.glob("*.md")) if not p.read_text("utf-8").isascii())
    text = page.read_text("utf-8")
    out = subprocess.run(
        [sys.executable, "-m", "plcstack", "docs", page.stem],
        capture_output=True,
        env={**os.environ, "PYTHONIOENCODING": "ascii"},
        check=False,
    )
    assert (out.returncode, out.stderr) == (0, b"")
    assert out.stdout.decode("ascii") == text.encode("ascii", "backslashreplace").decode("ascii")


@pytest.mark.parametrize("argv", [["docs"], ["docs", "cli"], ["demo", "--write-config", "-"]])
def test_a_reader_that_went_away_is_exit_0_and_silent(argv: list[str]) -> None:
    """``plcstack docs | head -3``: head closes the pipe; the command stops as ``poll`` does.
    The pipe's read end is closed before the command starts, so every write meets EPIPE."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        out = subprocess.run(
            [sys.executable, "-m", "plcstack", *argv],
            stdout=write_end,
            stderr=subprocess.PIPE,
            check=False,
        )
    finally:
        os.close(write_end)
    assert (out.returncode, out.stderr) == (0, b"")
