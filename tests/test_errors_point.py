"""Errors that point the right way: what a newcomer's first mistakes get as an answer.

Each test names a mistake a new user makes in the first hour (an address in the other PLC
family's notation, a float handed to ``write``, ``--type int64``, a TOML typo) and checks that
the answer says what the notation is, what was probably meant, and how to go on, in one line.
"""

from __future__ import annotations

import argparse
import asyncio
import pydoc
import re
import shlex
from pathlib import Path

import pytest

import plcstack
from plcstack import ConfigError, load_config
from plcstack.cli import _all_parsers, build_parser
from plcstack.cli.io import shown
from plcstack.codecs.e71_devices import parse_address
from plcstack.errors import AddressError, ValueEncodeError
from plcstack.s5address import parse_s5_address
from plcstack.sim import e71, s5lan
from plcstack.sim.s5memory import Area
from tests.cli_helpers import cli_in_process

#: a port nothing listens on: the checks tested here all run before a connection is made
NOWHERE = "127.0.0.1:9"


@pytest.mark.parametrize(
    ("address", "fragments"),
    [
        ("DB10.DW0", ["Siemens S5 notation (DB10.DW0)", "MELSEC", "D100"]),
        ("MB100", ["Siemens S5 notation (MB100)", "MELSEC"]),
        ("IB0", ["Siemens S5 notation (EB0)"]),
        ("DB10.DBW4", ["Siemens S5/S7 notation"]),
        ("XYZ", ["X takes a hexadecimal (0-9, A-F) device number like X1F", "'YZ' is not one"]),
        ("D1O0", ["did you mean D100?"]),
        ("D1A", ["decimal", "not hexadecimal '1A'", "X, Y, B, W"]),
        ("D100.3", ["bit of the word D100", "--type bool"]),
    ],
)
def test_melsec_address_errors_say_the_notation_and_what_was_meant(
    address: str, fragments: list[str]
) -> None:
    with pytest.raises(AddressError) as err:
        parse_address(address)
    for fragment in fragments:
        assert fragment in str(err.value)


@pytest.mark.parametrize(
    ("address", "fragment"),
    [
        ("D100", "MELSEC notation (this is a Siemens S5 PLC)"),
        ("X1F", "MELSEC notation"),
        ("M10.3", "--type bool, or read_as(address, BOOL) in Python); a plain read or write "
                  "takes the byte MB10"),
        ("DB10.DW5.3", "takes the word DB10.DW5"),
    ],
)  # fmt: skip
def test_s5_address_errors_name_melsec_and_the_one_bit_story(address: str, fragment: str) -> None:
    with pytest.raises(AddressError) as err:
        parse_s5_address(address)
    assert fragment in str(err.value)


async def test_a_bit_operand_reads_as_bool_as_the_error_says() -> None:
    # the advice of the raw read's error works as written, from the CLI and from Python
    async with await s5lan.start() as sim:
        sim.memory.write_area(Area.FLAGS, 10, bytes([0b0000_1000]))
        code, _, err = await cli_in_process("read", sim.url, "M10.3")
        assert code == 2 and "--type bool" in err
        code, out, err = await cli_in_process("read", sim.url, "M10.3", "--type", "bool")
        assert (code, out.strip()) == (0, "M10.3: True"), err
        async with plcstack.connect(sim.url) as plc:
            assert await plc.read_as("M10.3", plcstack.values.BOOL) is True


@pytest.mark.parametrize("scheme", ["e71+tcp", "s5lan", "fetchwrite", "as511+tcp"])
@pytest.mark.parametrize(
    ("value", "kind"),
    [(1.5, "float"), (None, "NoneType"), (b"\x01\x02", "bytes"), ("12", "str")],
)
async def test_write_of_the_wrong_kind_is_a_value_encode_error(
    scheme: str, value: object, kind: str
) -> None:
    address = "D6" if scheme.startswith("e71") else "DB10.DW6"
    plc = plcstack.connect(f"{scheme}://{NOWHERE}")
    with pytest.raises(ValueEncodeError) as err:
        await plc.write(address, value)  # type: ignore[arg-type]
    assert f"value {value!r} ({kind})" in str(err.value)
    assert f"write {address}" in str(err.value) and NOWHERE in str(err.value)
    with pytest.raises(ValueEncodeError, match=r"1\.5 \(float\) is not an integer"):
        await plc.write(address, [1.5])  # type: ignore[list-item]
    await plc.aclose()


async def test_usage_errors_are_one_line_with_one_prefix_and_the_choices() -> None:
    code, out, err = await cli_in_process("read", f"e71+tcp://{NOWHERE}", "D0", "--type", "int64")
    assert (code, out) == (2, "")
    assert err.count("\n") == 1 and err.count("error:") == 1
    assert err.startswith("plcstack: error: read: argument --type: unknown value type 'int64'")
    assert "int16, uint16, int32" in err and "string:N[:space]" in err
    assert "plcstack read --help" in err
    code, _, err = await cli_in_process("poll")
    assert code == 2 and err.startswith("plcstack: error: poll: the following arguments")
    assert err.count("\n") == 1
    code, _, err = await cli_in_process("sim", "e71", "--code", "x")
    assert code == 2 and err.startswith("plcstack: error: sim e71: argument --code: invalid")
    assert "'binary', 'ascii'" in err


async def test_an_option_error_names_the_option_once() -> None:
    for url, extra in (
        (f"e71+tcp://{NOWHERE}", ["--timeout", "0"]),
        (f"e71+tcp://{NOWHERE}?timeout=0", []),
    ):
        code, _, err = await cli_in_process("read", url, "D0", *extra)
        assert code == 2 and err.count("option timeout=") == 1, err
        assert "must be a finite number of seconds greater than 0" in err


async def test_options_may_stand_before_the_count() -> None:
    async with await e71.start() as sim:
        sim.memory.write_words("D", 100, [7, 8])
        code, out, err = await cli_in_process("read", sim.url, "D100", "--timeout", "5", "2")
        assert (code, out.strip()) == (0, "D100: 7 8"), err


def test_help_of_connect_shows_the_real_defaults() -> None:
    text = pydoc.render_doc(plcstack.connect, renderer=pydoc.plaintext)  # type: ignore[attr-defined]
    assert "_Unset" not in text and "UNSET" not in text
    assert "timeout: 'float' = 2.0" in text and "code: 'str' = 'binary'" in text
    assert "strict: 'bool' = s5lan: True" in text


async def test_read_as_takes_the_type_names_of_the_cli_and_the_config() -> None:
    async with await e71.start() as sim:
        sim.memory.write_words("D", 0, [0x0000, 0x3F40])
        async with plcstack.connect(sim.url) as plc:
            assert await plc.read_as("D0", "float32") == 0.75
            assert await plc.read_as("D0", "uint16", 2) == [0, 0x3F40]
            await plc.write_as("D10", "int32", -2)
            assert await plc.read_as("D10", "INT32") == -2
            with pytest.raises(AddressError, match="unknown value type 'kgx'; types: raw"):
                await plc.read_as("D0", "kgx")


async def test_control_characters_are_escaped_in_output() -> None:
    assert shown("A\x01") == "A\\x01" and shown("\x1b[2J") == "\\x1b[2J" and shown(5) == "5"
    async with await s5lan.start() as sim:
        sim.memory.write_area(Area.FLAGS, 0, b"\x01A")
        code, out, err = await cli_in_process("read", sim.url, "MW0", "--type", "kc")
        assert (code, out) == (0, "MW0: \\x01A\n"), err


@pytest.mark.parametrize(
    ("toml", "fragment"),
    [
        ('[mqt]\nurl = "mqtt://h"\n', "mqt (did you mean mqtt?)"),
        ('[poll]\nconcurency = 2\n', "concurency (did you mean concurrency?)"),
        ('[mqtt]\nurl = "mqtt://h"\nprefx = "a"\n', "prefx (did you mean prefix?)"),
        ('[metrics]\nprot = 9\n', "prot (did you mean port?)"),
        ('[influx]\nmeasurment = "m"\n', "measurment (did you mean measurement?)"),
        ('', "adress (did you mean address?)"),
        ('', "tiemout (did you mean timeout?)"),
    ],
)  # fmt: skip
def test_every_toml_typo_gets_a_did_you_mean(tmp_path: Path, toml: str, fragment: str) -> None:
    plc = '[[plc]]\nname = "a"\nurl = "e71+tcp://127.0.0.1:5000"\n'
    if "adress" in fragment:
        plc += 'tags = { t = { adress = "D0" } }\n'
    elif "tiemout" in fragment:
        plc += "tiemout = 2\n"
    else:
        plc += 'tags = { t = "D0" }\n'
    path = tmp_path / "c.toml"
    path.write_text(toml + plc)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert fragment in str(err.value) and str(path) in str(err.value)


def test_every_option_and_argument_has_a_help_text() -> None:
    missing = [
        f"{parser.prog} {action.option_strings or action.dest}"
        for parser in _all_parsers(build_parser())
        for action in parser._actions
        if action.help is None and not isinstance(action, argparse._SubParsersAction)
    ]
    assert missing == []
    write = next(p for p in _all_parsers(build_parser()) if p.prog == "plcstack write")
    assert "COUNT" not in write.format_help()  # write takes values, not a count


def test_every_error_line_of_the_cli_has_the_one_prefix(capsys: pytest.CaptureFixture[str]) -> None:
    from plcstack.cli import main

    assert main(["demo", "--plcs", "0"]) == 2
    assert capsys.readouterr().err == "plcstack: error: demo: --plcs must be at least 1\n"
    # no command prints a prefix of its own ("plcstack poll: error:"): they all go through one
    sources = Path(__file__).resolve().parents[1] / "plcstack" / "cli"
    own = [
        f"{path.name}: {line.strip()}"
        for path in sorted(sources.glob("*.py"))
        for line in path.read_text(encoding="utf-8").splitlines()
        if re.search(r"plcstack [a-z][a-z ]*: (error|internal error):", line)
    ]
    assert own == []


async def test_the_blocking_facade_takes_type_names_too() -> None:
    import plcstack.sync

    def blocking(url: str) -> tuple[float, int]:
        with plcstack.sync.connect(url) as plc:
            plc.write_as("D20", "float32", 1.25)
            value: float = plc.read_as("D20", "float32")  # Any to mypy: no cast needed
            return value, plc.read_as("D20", "uint16", 2)[1]

    async with await e71.start() as sim:
        value, high = await asyncio.to_thread(blocking, sim.url)
    assert value == 1.25 and high == 0x3FA0


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["e71://h:5000", "D0"], "unknown scheme 'e71' (did you mean e71+tcp or e71+udp?)"),
        (["s5lam://h:5010", "DB1.DW0"], "unknown scheme 's5lam' (did you mean s5lan?)"),
        (["10.0.0.5:5000", "D0"], "mean e71+tcp://10.0.0.5:5000 or s5lan://10.0.0.5:5000?"),
        (["5000", "D0"], "did you mean e71+tcp://127.0.0.1:5000 or s5lan://127.0.0.1:5000?"),
        ([f"e71+tcp://{NOWHERE}", "D9999"], "out of range for D (D0-D6143, D9000-D9255)"),
        ([f"e71+tcp://{NOWHERE}", "X800"], "out of range for X (X0-X7FF)"),
        ([f"e71+tcp://{NOWHERE}", "D0", "--type", "string"], "string:N:space, e.g. string:20"),
    ],
)  # fmt: skip
async def test_a_newcomers_first_url_address_and_type_get_what_was_meant(
    argv: list[str], fragment: str
) -> None:
    code, out, err = await cli_in_process("read", *argv)
    assert (code, out, err.count("\n")) == (2, "", 1), err
    assert err.startswith("plcstack: error: ") and fragment in err, err


def test_the_range_a_cpu_group_refuses_is_its_own(tmp_path: Path) -> None:
    from plcstack.codecs.e71_devices import CpuGroup, device_ranges

    with pytest.raises(AddressError, match=r"out of range for R \(this CPU has no R\)"):
        parse_address("R0", last=device_ranges(CpuGroup.I))
    with pytest.raises(AddressError, match=r"out of range for R \(R0-R4095\)"):
        parse_address("R4096", last=device_ranges(CpuGroup.II))


def test_an_array_of_tag_tables_is_named_as_such(tmp_path: Path) -> None:
    # [[plc.tags]] (one bracket pair too many) got "no tags: add a [plc.tags] table"
    path = tmp_path / "c.toml"
    path.write_text(
        '[[plc]]\nname = "a"\nurl = "e71+tcp://127.0.0.1:5000"\n[[plc.tags]]\nt = "D0"\n'
    )
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert "tags is an array of tables ([[plc.tags]]); write one table [plc.tags]" in str(err.value)


async def test_the_examples_of_read_and_write_help_run_as_written() -> None:
    """``plcstack read --help`` and ``write --help`` show commands against the simulators at
    their default ports; each runs (on the simulators' free ports instead) and prints a line."""
    examples = [
        shlex.split(line.strip())
        for parser in _all_parsers(build_parser())
        if parser.prog in ("plcstack read", "plcstack write")
        for line in (parser.description or "").splitlines()
        if line.startswith("  plcstack ")
    ]
    assert [argv[1] for argv in examples] == ["read", "read", "write", "write"]
    e71_sim, s5_sim = await e71.start(), await s5lan.start()
    ports = {"127.0.0.1:5000": e71_sim.url, "127.0.0.1:5010": s5_sim.url}
    try:
        for argv in examples:
            url = argv[2]
            scheme, hostport = url.split("://")
            argv[2] = f"{scheme}://{ports[hostport].split('://')[1]}"
            code, out, err = await cli_in_process(*argv[1:])
            assert (code, err) == (0, ""), argv
            assert out.startswith(f"{argv[3]}: "), (argv, out)
    finally:
        await e71_sim.aclose()
        await s5_sim.aclose()
