"""GX Developer / GX Works2 device comments: both tools' layouts and encodings, the tag-name
rule, and every refusal as one line FILE:ROW."""

from __future__ import annotations

import codecs
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from plcstack import values as vt
from plcstack.config import parse_config
from plcstack.tags import TagListError, read_gx, tag_names, to_toml
from plcstack.tags.gx import Skipped
from plcstack.tags.names import MAX_NAME, derive_name
from tests.cli_helpers import cli_in_process

DATA = Path(__file__).parent / "data" / "tags"
URL = "e71+tcp://10.0.0.6:5000"


def _gx(data: bytes, **kw: object) -> str:
    return to_toml(read_gx(data, "c.csv", plc="line1", url=URL, **kw))  # type: ignore[arg-type]


def test_gx_works2_file_utf16_tabs() -> None:
    raw = (DATA / "line1-gxworks2.csv").read_bytes()
    assert raw.startswith(codecs.BOM_UTF16_LE) and "\t".encode("utf-16-le") in raw
    text = _gx(raw)
    assert text == (DATA / "line1-gxworks2.toml").read_text(encoding="utf-8")
    tags = {t.name: t for t in parse_config(text).plcs[0].tags}
    assert tags["Start_push_button"].type is vt.BOOL and tags["Start_push_button"].address == "X0"
    assert tags["Tank_level"].type is vt.UINT16 and tags["Tank_level"].description == "Tank level"
    assert tags["Tank_high_alarm"].address == "D101.F" and tags["Tank_high_alarm"].type is vt.BOOL
    assert tags["油温"].address == "D200"
    # the same comment on two devices: neither keeps the bare name
    assert {"Spare_D300", "Spare_D301"} <= set(tags) and "Spare" not in tags
    assert not any(t.writable for t in tags.values())


def test_gx_developer_file_shift_jis_commas_with_labels() -> None:
    raw = (DATA / "line1-gxdeveloper.csv").read_bytes()
    raw.decode("cp932")
    with pytest.raises(UnicodeDecodeError):
        raw.decode("utf-8")  # really Shift-JIS, as GX Developer writes it on a Japanese system
    text = _gx(raw)
    assert text == (DATA / "line1-gxdeveloper.toml").read_text(encoding="utf-8")
    tags = {t.name: t for t in parse_config(text).plcs[0].tags}
    assert tags["START"].address == "X0" and tags["START"].description == "起動押しボタン"
    assert tags["停止押しボタン"].address == "X1"  # no label: the name comes from the comment
    assert tags["LEVEL_SP"].description is None  # a label without a comment
    assert tags["MOTOR"].address == "Y10"


@pytest.mark.parametrize(
    "encode",
    [
        lambda t: t.encode("utf-8"),
        lambda t: codecs.BOM_UTF8 + t.encode("utf-8"),
        lambda t: t.encode("utf-16"),
        lambda t: codecs.BOM_UTF16_BE + t.encode("utf-16-be"),
        lambda t: t.encode("cp932"),
    ],
)
@pytest.mark.parametrize("sep", ["\t", ","])
def test_every_encoding_and_delimiter_gives_the_same_tags(encode: object, sep: str) -> None:
    text = (
        f'"Title"\r\n"Device Name"{sep}"Comment"\r\n"D0010"{sep}"流量 m3/h"\r\n"M5"{sep}"Run"\r\n'
    )
    out = _gx(encode(text))  # type: ignore[operator]
    tags = parse_config(out).plcs[0].tags
    assert [(t.name, t.address, t.description) for t in tags] == [
        ("流量_m3_h", "D10", "流量 m3/h"),
        ("Run", "M5", "Run"),
    ]


def test_japanese_header_and_type_override() -> None:
    text = "デバイス名,コメント\r\nD100,温度\r\nX0,起動\r\n"
    tags = read_gx(text.encode("cp932"), "c.csv", plc="p", url=URL, word_type=vt.INT16).tags
    assert [(t.address, t.type) for t in tags] == [("D100", vt.INT16), ("X0", vt.BOOL)]


def test_skip_unsupported_reports_each_device() -> None:
    text = '"Device Name"\t"Comment"\r\n"SM400"\t"Always ON"\r\n"D0"\t"Level"\r\n'
    seen: list[Skipped] = []
    tags = read_gx(
        text.encode("utf-16"),
        "c.csv",
        plc="p",
        url=URL,
        skip_unsupported=True,
        skipped=seen.append,
    ).tags
    assert [t.address for t in tags] == ["D0"]
    assert [(s.line, s.device) for s in seen] == [(2, "SM400")]
    assert "special relay of the Q/L and iQ-R series" in seen[0].why
    assert "'M400' is not one" not in seen[0].why


REFUSALS = [
    # before: "M takes a decimal device number like M100; 'M400' is not one" (S read as M)
    (
        '"Device Name"\t"Comment"\r\n"SM400"\t"Always ON"\r\n',
        "c.csv:2: column 'Device'",
        "SM is a special relay of the Q/L and iQ-R series; the A series has special relays"
        " M9000-M9255 instead",
    ),
    (
        '"Device Name"\t"Comment"\r\n"ZR100"\t"Recipe"\r\n',
        "c.csv:2: column 'Device'",
        "ZR is a file register of the Q/L series",
    ),
    ('"Device Name"\t"Comment"\r\n"D99999"\t"x"\r\n', "c.csv:2: column 'Device'", "out of range"),
    (
        '"Device Name"\t"Comment"\r\n"D1"\t"a"\r\n"D0001"\t"b"\r\n',
        "c.csv:3: column 'Device'",
        "D1 is also the device of row 2",
    ),
    ('"Device Name"\t"Comment"\r\n"D1"\t"a\x07b"\r\n', "c.csv:2: column 'Comment'", "control"),
    (
        '"Device"\t"Label"\t"Comment"\r\n"D1"\t"Spare_D2"\t""\r\n"D2"\t""\t"Spare"\r\n'
        '"D3"\t""\t"Spare"\r\n',
        "c.csv:3:",
        "also the name of row 2",
    ),
    ('"a"\r\n"b"\r\n', "c.csv:", "no header line"),
    ('"Device Name"\t"Comment"\r\n"D1"\t""\r\n', "c.csv:", "no device with a comment"),
]


@pytest.mark.parametrize(("text", "where", "why"), REFUSALS)
async def test_gx_refusals_one_line(tmp_path: Path, text: str, where: str, why: str) -> None:
    path = tmp_path / "c.csv"
    path.write_bytes(text.encode("utf-16"))
    code, out, err = await cli_in_process(
        "tags", "import", "gx", str(path), "--plc", "p", "--url", URL
    )
    assert (code, out) == (2, "")
    assert err.count("\n") == 1 and err.startswith(f"plcstack: error: {tmp_path}/{where}"), err
    assert why in err, err


async def test_cli_type_option_and_skips(tmp_path: Path) -> None:
    path = tmp_path / "c.csv"
    path.write_bytes('"Device Name"\t"Comment"\r\n"SM400"\t"On"\r\n"D0"\t"L"\r\n'.encode("utf-16"))
    code, out, err = await cli_in_process(
        "tags", "import", "gx", str(path), "--plc", "p", "--url", URL, "--type", "int42"
    )
    assert (code, out) == (2, "") and "--type" in err
    code, out, err = await cli_in_process(
        "tags",
        "import",
        "gx",
        str(path),
        "--plc",
        "p",
        "--url",
        URL,
        "--type",
        "float32",
        "--skip-unsupported",
    )
    assert code == 0 and 'L = { address = "D0", type = "float32"' in out
    assert err.startswith(f"plcstack: skipped {path}:2: SM400: ")


# -- the name rule -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "name"),
    [
        ("Feed pump 2 running", "Feed_pump_2_running"),
        ("\uff21\uff22\uff23\uff11\uff12", "ABC12"),  # full-width: NFKC
        ("a/b+c#d.e:f", "a_b_c_d_e_f"),
        ("  --x--  ", "--x--"),
        ("温度 (°C)", "温度_C"),
        ("!!!", ""),
        ("x" * 100, "x" * MAX_NAME),
    ],
)
def test_derive_name(text: str, name: str) -> None:
    assert derive_name(text) == name


@given(
    st.lists(
        st.tuples(st.integers(0, 8000), st.text(max_size=40)),
        unique_by=lambda e: e[0],
        max_size=30,
    )
)
def test_names_are_unique_stable_and_valid_topic_levels(rows: list[tuple[int, str]]) -> None:
    entries = [(f"D{n}", text, i + 2) for i, (n, text) in enumerate(rows)]
    try:
        names = tag_names(entries, "c.csv")
    except TagListError as exc:
        assert "c.csv:" in str(exc)  # a clash the suffix cannot resolve: refused, never merged
        return
    assert len(set(names)) == len(names)
    for name in names:
        assert name and not set(name) & set("/+#. \t\n\x00")
    # stable: the order of the rows does not change anyone's name
    again = tag_names(list(reversed(entries)), "c.csv")
    assert list(reversed(again)) == names
