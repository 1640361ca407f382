"""CLI behaviour every protocol shares: usage errors are exit 2 with one clear stderr line."""

import subprocess
import sys

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
