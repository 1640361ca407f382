"""Kepware tag CSV: files in Kepware's own layout become the expected TOML, every refusal is one
line FILE:ROW with the column and why, and nothing reaches stdout when a row is refused."""

from __future__ import annotations

from pathlib import Path

import pytest

from plcstack import values as vt
from plcstack.config import parse_config
from plcstack.tags import TagListError, read_kepware, to_toml
from plcstack.tags.addresses import native_address
from tests.cli_helpers import cli_in_process

DATA = Path(__file__).parent / "data" / "tags"
PRESS = DATA / "press.csv"
E71 = "e71+tcp://10.0.0.5:5000"
S5 = "s5lan://10.0.0.7:5010"


def _import(path: Path, plc: str, url: str) -> str:
    return to_toml(read_kepware(path.read_bytes(), str(path), plc=plc, url=url))


def test_press_file_becomes_the_golden_toml() -> None:
    text = _import(PRESS, "press1", E71)
    assert text == (DATA / "press.toml").read_text(encoding="utf-8")
    config = parse_config(text).poll
    tags = {t.name: t for t in config.plcs[0].tags}
    assert tags["level"].scale is not None and tags["level"].scale.eng_hi == 100
    assert tags["level"].unit == "%" and tags["level"].description == "Tank 1 level, radar"
    assert config.groups["scan_100ms"] == 0.1 and tags["level"].group == "scan_100ms"
    assert tags["counter"].group == "default"  # 1000 ms: the default group, no table needed
    assert tags["temp"].group == "default"  # blank Scan Rate: the server's default
    assert tags["setpoint"].writable and tags["recipe"].writable and not tags["counter"].writable
    assert tags["door"].address == "D120.B" and tags["door"].type is vt.BOOL  # Kepware .11
    assert tags["alarms"].count == 16 and tags["alarms"].address == "M0"
    assert tags["recipe"].type.name == "string:8" and tags["total"].type is vt.BCD32


def test_s5_file_with_semicolons_in_windows_1252() -> None:
    raw = (DATA / "kiln-s5.csv").read_bytes()
    assert "°".encode("cp1252") in raw and b";" in raw  # the form Kepware writes on Windows
    text = _import(DATA / "kiln-s5.csv", "kiln", S5)
    assert text == (DATA / "kiln-s5.toml").read_text(encoding="utf-8")
    tags = {t.name: t for t in parse_config(text).plcs[0].tags}
    assert tags["Ofen.Temperatur"].address == "DB10.DW5" and tags["Ofen.Temperatur"].type is vt.KG
    assert tags["Zaehler"].address == "MW10"  # STEP 5 English flag word FW10
    assert tags["Rezept"].type.name == "string:16"
    assert tags["Ofen.Tuer"].description == "Tür geschlossen"


@pytest.mark.parametrize(
    ("family", "kepware", "native"),
    [
        ("melsec", "D0100", "D100"),
        ("melsec", "X001F", "X1F"),
        ("melsec", "d0120.03", "D120.3"),
        ("melsec", "D0120.15", "D120.F"),
        ("melsec", "D120.F", "D120.F"),  # plcstack's own notation is taken as is
        ("melsec", "TN0005", "TN5"),
        ("s5", "DB010:DW005", "DB10.DW5"),
        ("s5", "DB10:DL5", "DB10.DL5"),
        ("s5", "DX3:DR0", "DX3.DR0"),
        ("s5", "DB10:DW9.03", "DB10.DW9.3"),
        ("s5", "FY10", "MB10"),
        ("s5", "FW10", "MW10"),
        ("s5", "MW10", "MW10"),
    ],
)
def test_kepware_address_forms(family: str, kepware: str, native: str) -> None:
    assert native_address(kepware, family) == native


HEADER = (
    "Tag Name,Address,Data Type,Respect Data Type,Client Access,Scan Rate,Scaling,Raw Low,"
    "Raw High,Scaled Low,Scaled High,Scaled Data Type,Clamp Low,Clamp High,Eng Units,Description"
)
GOOD = "a,D100,Word,1,RO,1000,,,,,,,,,,first"

REFUSALS = [
    # (rows after the header, row, column, words of the reason)
    ("b,D99999,Word,1,RO,1000,,,,,,,,,,", 3, "Address", "out of range"),
    ("b,DB10:DW5,Word,1,RO,1000,,,,,,,,,,", 3, "Address", "an S5 address, but e71+tcp"),
    ("b,M0,Short,1,RO,1000,,,,,,,,,,", 3, "Address", "bit area"),
    ("b,D101,QWord,1,RO,1000,,,,,,,,,,", 3, "Data Type", "unknown type 'QWord'"),
    ("a,D101,Word,1,RO,1000,,,,,,,,,,", 3, "Tag Name", "also the name of row 2"),
    (",D101,Word,1,RO,1000,,,,,,,,,,", 3, "Tag Name", "needs a name"),
    ("b,,Word,1,RO,1000,,,,,,,,,,", 3, "Address", "needs an address"),
    ("b,D101,Short,1,RO,1000,Square Root,0,10,0,1,Float,0,0,,", 3, "Scaling", "Square Root"),
    ("b,D101,Short,1,RO,1000,Cubic,0,10,0,1,Float,0,0,,", 3, "Scaling", "Cubic"),
    ("b,D101,Short,1,RO,1000,Linear,0,10,0,1,Float,1,0,,", 3, "Clamp Low", "does not clamp"),
    ("b,D101,Short,1,RO,1000,Linear,0,10,0,1,Float,0,1,,", 3, "Clamp High", "does not clamp"),
    ("b,D101,Short,1,RO,1000,Linear,0,x,0,1,Float,0,0,,", 3, "Raw High", "not 'x'"),
    ("b,D101,Short,1,RO,1000,Linear,5,5,0,1,Float,0,0,,", 3, "Raw Low", "must not be empty"),
    ("b,D101,Short,1,RO,1000,Linear,0,10,0,1,String,0,0,,", 3, "Scaled Data Type", "String"),
    ("b,M1,Boolean,1,RO,1000,Linear,0,10,0,1,Float,0,0,,", 3, "Scaling", "numeric type"),
    ("b,D101,Word,1,WO,1000,,,,,,,,,,", 3, "Client Access", "write-only"),
    ("b,D101,Word,1,XX,1000,,,,,,,,,,", 3, "Client Access", "'XX'"),
    ("b,D101,Word,1,RO,0,,,,,,,,,,", 3, "Scan Rate", "whole milliseconds"),
    ("b,D101,Word,1,RO,2.5,,,,,,,,,,", 3, "Scan Rate", "whole milliseconds"),
    ("b,D101,Word,2,RO,1000,,,,,,,,,,", 3, "Respect Data Type", "0 or 1"),
    ("b,D101 [4],Word,1,RO,1000,,,,,,,,,,", 3, "Address", "Array"),
    ("b,D101,Word Array,1,RO,1000,,,,,,,,,,", 3, "Data Type", "Array"),
    ("b,D101 [0],Word Array,1,RO,1000,,,,,,,,,,", 3, "Address", "at least 1"),
    ("b,D101,String,1,RO,1000,,,,,,,,,,", 3, "Address", "needs its length"),
    ("b,D101.8H,String,1,RO,1000,,,,,,,,,,", 3, "Address", "low byte first"),
    ('b,D101,Word,1,RO,1000,,,,,,,,,,"two\nlines"', 3, "Description", "control characters"),
    ("b,D101,Word,1,RO,1000,,,,,,,,,," + "x" * 1025, 3, "Description", "at most 1024"),
]


@pytest.mark.parametrize(("body", "row", "column", "why"), REFUSALS)
async def test_every_refusal_is_one_line_naming_file_row_column(
    tmp_path: Path, body: str, row: int, column: str, why: str
) -> None:
    path = tmp_path / "tags.csv"
    path.write_bytes(f"{HEADER}\r\n{GOOD}\r\n{body}\r\n".encode())
    code, out, err = await cli_in_process(
        "tags", "import", "kepware", str(path), "--plc", "p", "--url", E71
    )
    assert (code, out) == (2, "")  # nothing partial on stdout
    assert err.count("\n") == 1, err
    assert err.startswith(f"plcstack: error: {path}:{row}: column {column!r}: "), err
    assert why in err, err


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("", "empty"),
        (HEADER + "\r\n", "no tags"),
        (HEADER + ",Colour\r\n" + GOOD + "\r\n", "unknown column 'Colour'"),
        ("Address,Data Type\r\nD100,Word\r\n", "no 'Tag Name' column"),
        ("Tag Name,Address,Address\r\na,D1,D2\r\n", "appears twice"),
        ('Tag Name,Address\r\n"a,D1\r\n', "not valid CSV"),
    ],
)
def test_file_level_refusals(text: str, why: str) -> None:
    with pytest.raises(TagListError, match=why) as err:
        read_kepware(text.encode(), "t.csv", plc="p", url=E71)
    assert str(err.value).startswith("t.csv")


def test_melsec_address_on_an_s5_url_says_so() -> None:
    text = f"{HEADER}\r\na,D100,Word,1,RO,1000,,,,,,,,,,\r\n"
    with pytest.raises(TagListError, match="a MELSEC address, but s5lan://"):
        read_kepware(text.encode(), "t.csv", plc="p", url=S5)


def test_bad_url_is_refused() -> None:
    with pytest.raises(TagListError, match="--url"):
        read_kepware(PRESS.read_bytes(), "t.csv", plc="p", url="modbus://x:1")


async def test_cli_import_export_and_list(tmp_path: Path) -> None:
    code, out, err = await cli_in_process(
        "tags", "import", "kepware", str(PRESS), "--plc", "press1", "--url", E71
    )
    assert (code, err) == (0, "")
    config = tmp_path / "press.toml"
    config.write_text(out, encoding="utf-8")
    code, csv_text, err = await cli_in_process("tags", "export", str(config), "--format", "kepware")
    assert (code, err) == (0, "")
    assert csv_text == (DATA / "press-export.csv").read_bytes().decode()
    code, lines, err = await cli_in_process("tags", "list", str(config), "--plc", "press1")
    assert code == 0 and '"description": "Tank 1 level, radar"' in lines
    assert len(lines.splitlines()) == 8
    code, out, err = await cli_in_process(
        "tags", "import", "kepware", str(tmp_path / "nope.csv"), "--plc", "p", "--url", E71
    )
    assert (code, out) == (2, "") and "cannot read" in err


async def test_export_needs_plc_when_several(tmp_path: Path) -> None:
    config = tmp_path / "two.toml"
    config.write_text(
        '[[plc]]\nname = "press1"\nurl = "e71+tcp://10.0.0.5:5000"\n[plc.tags]\na = "D100"\n'
        '[[plc]]\nname = "kiln"\nurl = "s5lan://10.0.0.7:5010"\n[plc.tags]\n'
        'b = { address = "DB10.DW5", type = "kg" }\n',
        encoding="utf-8",
    )
    code, out, err = await cli_in_process("tags", "export", str(config), "--format", "kepware")
    assert (code, out) == (2, "") and "choose it with --plc" in err and "kiln" in err
    code, out, err = await cli_in_process(
        "tags", "export", str(config), "--format", "kepware", "--plc", "kiln"
    )
    assert code == 0 and "DB10.DW5,kg" in out
    code, out, err = await cli_in_process(
        "tags", "export", str(config), "--format", "kepware", "--plc", "nope"
    )
    assert (code, out) == (2, "") and "no PLC named 'nope'" in err
