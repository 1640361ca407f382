"""What the loader checks of the PLCs themselves, for every command and the Python API alike.

Before, ``poll`` took a PLC named ``line1.press`` that ``serve opcua`` refused, names with
``/``, ``+``, ``#`` became MQTT topic levels, a TOML tag ``DB10.DW0`` on an E71 was told about
"the bit of a word" (``plcstack read`` says it is S5 notation), ``type = "kg"`` on an E71 word
loaded silently, an address error had no file:line, and nothing was said when more PLCs of a
file share one E71 than it has connections, or two share an S5-LAN module or an AS511 line.
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

import plcstack
from plcstack.cli import main
from plcstack.config import load_config, parse_config
from plcstack.errors import AddressError, ConfigError
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig

COMMANDS = [
    ["poll", "{path}", "--format", "none", "--duration", "0.1"],
    ["serve", "opcua", "{path}", "--duration", "0.1"],
    ["serve", "modbus", "{path}", "--duration", "0.1"],
    ["tags", "list", "{path}"],
]
IDS = ["poll", "serve-opcua", "serve-modbus", "tags-list"]


def _plc(name: str = "press1", tags: str = 'strokes = { address = "D100", modbus = "hr:0" }',
         url: str = "e71+tcp://127.0.0.1:9") -> str:  # fmt: skip
    return f'\n[[plc]]\nname = "{name}"\nurl = "{url}"\n[plc.tags]\n{tags}\n'


BAD_NAMES = [
    # (file, the words, the line)
    (_plc("line1.press"), "PLC name 'line1.press' contains a dot", 3),
    (_plc("line1/press"), "PLC name 'line1/press' contains a slash", 3),
    (_plc("press+"), "PLC name 'press+' contains a plus (+: an MQTT wildcard)", 3),
    (_plc("press#1"), "PLC name 'press#1' contains a hash (#: an MQTT wildcard)", 3),
    (_plc(""), "a PLC name must be a non-empty string", 3),
    (_plc(" press1"), "PLC name ' press1' begins or ends with a space", 3),
    (_plc("a\\tb"), "PLC name 'a\\tb' contains the control character '\\t'", 3),
    (_plc(tags='"a/b" = "D100"'), "tag name 'a/b' contains a slash", 6),
    (_plc(tags='"x#y" = "D100"'), "tag name 'x#y' contains a hash", 6),
    (_plc(tags='"+" = "D100"'), "tag name '+' contains a plus", 6),
    (_plc(tags='".." = "D100"'), "tag name '..' is a path step", 6),
    ('[groups]\n"fast/slow" = 0.1\n' + _plc(), "scan group name 'fast/slow' contains a slash", 2),
    ('[[plc]]\nurl = "e71+tcp://127.0.0.1:9"\ntags = { a = "D0" }\n', "missing name", 1),
]


@pytest.mark.parametrize("argv", COMMANDS, ids=IDS)
@pytest.mark.parametrize(("text", "words", "line"), BAD_NAMES)
def test_a_name_no_face_can_carry_is_refused_by_every_command(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    argv: list[str],
    text: str,
    words: str,
    line: int,
) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(text)
    code = main([a.format(path=path) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and words in err, err
    assert "MQTT topic level" in err and "OPC UA" in err, err  # the reason, said once
    assert err.rstrip().endswith(f"({path}:{line})"), err


def test_names_every_face_can_carry_load() -> None:
    config = parse_config(_plc("press-1_A", tags='"level.1" = "D100"\n"Füllstand 2" = "D101"'))
    assert [t.name for t in config.plcs[0].tags] == ["level.1", "Füllstand 2"]


def test_the_python_api_keeps_the_same_rule() -> None:
    tag = TagConfig("t", "D0")
    with pytest.raises(ConfigError, match="PLC name 'line1.press' contains a dot"):
        PollConfig((PlcConfig("line1.press", "e71+tcp://127.0.0.1:9", (tag,)),))
    with pytest.raises(ConfigError, match="tag name 'a#b' contains a hash"):
        PollConfig((PlcConfig("p", "e71+tcp://127.0.0.1:9", (TagConfig("a#b", "D0"),)),))
    with pytest.raises(ConfigError, match="scan group name 'a/b'"):
        PollConfig((PlcConfig("p", "e71+tcp://127.0.0.1:9", (tag,)),), {"default": 1, "a/b": 1})


S5_ON_MELSEC = (
    "address 'DB10.DW0': that is Siemens S5 notation (DB10.DW0), but this is a MELSEC PLC;"
    " use device letters and numbers like D100"
)


def test_plcstack_read_says_it_too(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["read", "e71+tcp://127.0.0.1:9", "DB10.DW0"]) == 2
    assert S5_ON_MELSEC in capsys.readouterr().err


async def test_an_s5_address_on_a_melsec_plc_gets_the_same_words_everywhere(
    tmp_path: Path,
) -> None:
    words = S5_ON_MELSEC
    path = tmp_path / "plant.toml"
    path.write_text(_plc(tags='strokes = "D100"\ntemp = { address = "DB10.DW0", type = "int16" }'))
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"press1: tag 'temp': {words}"), caught.value
    assert str(caught.value).endswith(f"({path}:7)")
    client = plcstack.connect("e71+tcp://127.0.0.1:9")
    for call in (
        lambda: client.split_bit("DB10.DW0"),
        lambda: client.locate("DB10.DW0"),
    ):
        with pytest.raises(AddressError) as api:
            call()
        assert words in str(api.value)
    with pytest.raises(AddressError) as typed:
        await client.read_as("DB10.DW0", plcstack.INT16)
    assert words in str(typed.value)


@pytest.mark.parametrize(
    ("address", "words"),
    [
        ("XG", "address 'XG': X takes a hexadecimal (0-9, A-F) device number"),
        ("D99999", "device number out of range"),
        ("D100.G", "the bit of a word is one hexadecimal digit 0-F"),
    ],
)
def test_every_address_error_names_its_file_and_line(
    tmp_path: Path, address: str, words: str
) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(
        "# plant\n" + _plc(tags=f'ok = "D0"\nbad = {{ address = "{address}", type = "bool" }}')
    )
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    text = str(caught.value)
    assert text.startswith("press1: tag 'bad': ") and words in text, text
    assert text.endswith(f"({path}:8)"), text


@pytest.mark.parametrize(
    ("s5", "melsec"),
    [("kg", "float32"), ("kf", "int16"), ("kt", "bcd16"), ("kc", "string:2"), ("kh", "uint16")],
)
def test_an_s5_format_on_a_melsec_plc_is_refused_at_load(
    tmp_path: Path, s5: str, melsec: str
) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(_plc(tags=f'a = "D0"\nb = {{ address = "D100", type = "{s5}" }}'))
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    text = str(caught.value)
    assert f"tag 'b': type {s5} is an S5 format" in text and "this is a MELSEC PLC" in text
    assert f"use type = {melsec!r}" in text and text.endswith(f"({path}:7)"), text
    # the same type on an S5 PLC is what it is for
    s5_plc = _plc(tags=f'b = {{ address = "DB10.DW0", type = "{s5}" }}', url="s5lan://h:1")
    assert parse_config(s5_plc).plcs[0].tags[0].type.name == s5


def _fleet(urls: list[str]) -> str:
    return "".join(_plc(f"p{i}", 'a = "DB1.DW0"' if "e71" not in u else 'a = "D0"', u)
                   for i, u in enumerate(urls))  # fmt: skip


@pytest.mark.parametrize(
    ("urls", "words", "nth"),
    [
        (["e71+tcp://10.0.0.5:5000"] * 9, "(9) share the E71 at 10.0.0.5:5000, which takes 8"
         " connections: the 9th and later cannot connect", 8),
        (["s5lan://10.0.0.7:5010", "s5lan://10.0.0.7:5010?timeout=3"], "share the S5-LAN"
         " module at 10.0.0.7:5010, which takes one connection at a time: the second", 1),
        (["as511:///dev/ttyS0", "as511:///dev/ttyS0"], "share the AS511 line at /dev/ttyS0", 1),
        (["as511+tcp://10.0.0.9:4001"] * 3, "share the AS511 line at 10.0.0.9:4001", 1),
    ],
)  # fmt: skip
def test_plcs_sharing_a_connection_the_device_cannot_share_are_said_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, urls: list[str], words: str, nth: int
) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(_fleet(urls))
    with caplog.at_level(logging.WARNING, logger="plcstack.config"):
        config = load_config(path)
    (record,) = caplog.records
    text = record.getMessage()
    assert words in text and "one [[plc]]" in text and "gateway" in text, text
    assert text.endswith(f"({path}:{2 + 6 * nth})"), text  # the first PLC beyond the limit
    assert config.notices == (text,)


def test_plcs_that_each_get_a_connection_are_not_warned_about(
    caplog: pytest.LogCaptureFixture,
) -> None:
    urls = ["e71+tcp://10.0.0.5:5000"] * 8 + [
        "e71+tcp://10.0.0.5:5001",
        "s5lan://10.0.0.7:5010",
        "s5lan://10.0.0.8:5010",
        "fetchwrite://10.0.0.7:2000",
        "fetchwrite://10.0.0.7:2000",
    ]
    with caplog.at_level(logging.WARNING, logger="plcstack.config"):
        assert parse_config(_fleet(urls)).notices == ()
    assert not caplog.records


@pytest.mark.parametrize("argv", COMMANDS, ids=IDS)
def test_a_modbus_overlap_is_refused_by_every_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str]
) -> None:
    path = tmp_path / "plant.toml"
    path.write_text(_plc(tags='a = { address = "D0", type = "float32", modbus = "hr:0" }\n'
                          'b = { address = "D2", modbus = "hr:1" }'))  # fmt: skip
    code = main([a.format(path=path) for a in argv])
    err = capsys.readouterr().err
    assert code == 2 and "overlaps" in err and f"{path}:6" in err and f"{path}:7" in err, err
