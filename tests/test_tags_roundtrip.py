"""import(export(config)) gives the same tags: names, addresses, types, counts, writable, scale,
unit, description and scan interval, for MELSEC and S5 configs Hypothesis makes up, through the
whole path a user takes (Kepware CSV text, the TOML printed, the config loaded from it)."""

from __future__ import annotations

from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack import values as vt
from plcstack.checks import name_problem
from plcstack.config import parse_config
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.tags import read_kepware, to_toml, write_kepware
from plcstack.values import Scale

E71 = "e71+tcp://10.0.0.5:5000"
S5 = "fetchwrite://10.0.0.7:2000"

#: free text as people write it: any printable character, tabs, quotes, commas, semicolons
TEXT = st.text(
    st.characters(blacklist_categories=("Cc", "Cs"), blacklist_characters="\x7f") | st.just("\t"),
    min_size=1,
    max_size=40,
).filter(str.strip)
#: a tag name as the configuration takes it (the name rule: plcstack.checks.name_problem)
NAME = st.text(
    st.characters(blacklist_categories=("Cc", "Cs", "Zs", "Zl", "Zp"), blacklist_characters="\x7f"),
    min_size=1,
    max_size=20,
).filter(lambda name: name_problem("tag", name) is None)
FINITE = st.floats(-1e6, 1e6, allow_nan=False) | st.integers(-30000, 30000)
WORD_TYPES: list[vt.ValueType[Any]] = [
    vt.RAW,
    vt.INT16,
    vt.UINT16,
    vt.INT32,
    vt.UINT32,
    vt.FLOAT32,
    vt.BCD16,
    vt.BCD32,
]


@st.composite
def scales(draw: st.DrawFn) -> Scale | None:
    if not draw(st.booleans()):
        return None
    raw_lo, eng_lo = draw(FINITE), draw(FINITE)
    raw_hi = draw(FINITE.filter(lambda v: v != raw_lo))
    eng_hi = draw(FINITE.filter(lambda v: v != eng_lo))
    return Scale(raw_lo, raw_hi, eng_lo, eng_hi)


@st.composite
def melsec_tag(draw: st.DrawFn, name: str, group: str) -> TagConfig:
    # no S5 formats: a MELSEC word holds none, and the loader refuses them on a MELSEC PLC
    kind = draw(st.sampled_from(["word", "bits", "bit_of_word", "string"]))
    common: dict[str, Any] = {
        "group": group,
        "writable": draw(st.booleans()),
        "unit": draw(st.none() | TEXT),
        "description": draw(st.none() | TEXT),
    }
    n = draw(st.integers(0, 2000))  # inside every A-series CPU's ranges (D, M, X/Y/B up to 7FF)
    if kind == "bits":
        device = draw(st.sampled_from(["M", "X", "Y", "B"]))
        address = f"{device}{n:X}" if device in "XYB" else f"{device}{n}"
        return TagConfig(name, address, vt.BOOL, draw(st.integers(1, 32)), **common)
    if kind == "bit_of_word":  # read-only: a writable bit of a word is refused at load
        common["writable"] = False
        return TagConfig(name, f"D{n}.{draw(st.integers(0, 15)):X}", vt.BOOL, **common)
    if kind == "string":
        return TagConfig(name, f"D{n}", vt.string(draw(st.integers(1, 40))), **common)
    vtype = draw(st.sampled_from(WORD_TYPES))
    scale = draw(scales()) if vtype.kind in ("int", "float") else None
    count = draw(st.integers(1, 8))
    return TagConfig(name, f"D{n}", vtype, count, scale=scale, **common)


@st.composite
def s5_tag(draw: st.DrawFn, name: str, group: str) -> TagConfig:
    common: dict[str, Any] = {
        "group": group,
        "writable": draw(st.booleans()),
        "unit": draw(st.none() | TEXT),
        "description": draw(st.none() | TEXT),
    }
    db, word = draw(st.integers(1, 255)), draw(st.integers(0, 200))
    address = draw(st.sampled_from([f"DB{db}.DW{word}", f"MW{word * 2}", f"DX{db}.DW{word}"]))
    choices: list[vt.ValueType[Any]] = [*WORD_TYPES, vt.KG, vt.KF, vt.KT, vt.KZ]
    vtype = draw(st.sampled_from(choices))
    scale = draw(scales()) if vtype.kind in ("int", "float") else None
    return TagConfig(name, address, vtype, draw(st.integers(1, 4)), scale=scale, **common)


@st.composite
def configs(draw: st.DrawFn) -> PollConfig:
    url = draw(st.sampled_from([E71, S5]))
    rates = draw(st.lists(st.integers(1, 100_000), min_size=1, max_size=4, unique=True))
    groups = {"default": draw(st.sampled_from([1.0, 0.25, 2.0]))}
    groups |= {f"g{i}": ms / 1000 for i, ms in enumerate(rates)}
    names = draw(st.lists(NAME, min_size=1, max_size=12, unique=True))
    make = melsec_tag if url == E71 else s5_tag
    tags = tuple(draw(make(name, draw(st.sampled_from(sorted(groups))))) for name in names)
    return PollConfig((PlcConfig("p1", url, tags),), groups)


def _same(tag: TagConfig) -> tuple[object, ...]:
    return (
        tag.name,
        tag.address,
        tag.type.name,
        tag.count,
        tag.writable,
        tag.scale,
        tag.unit,
        tag.description,
    )


@settings(max_examples=80, deadline=None)
@given(configs())
def test_import_of_export_gives_the_same_tags(config: PollConfig) -> None:
    plc = config.plcs[0]
    csv_text = write_kepware(plc, config.groups)
    imported = read_kepware(csv_text.encode("utf-8"), "t.csv", plc=plc.name, url=plc.url)
    again = parse_config(to_toml(imported)).poll
    tags = again.plcs[0].tags
    assert [_same(t) for t in tags] == [_same(t) for t in plc.tags]
    # the scan group's interval survives; its name follows the rate (Kepware has no column for it)
    for before, after in zip(plc.tags, tags, strict=True):
        assert again.groups[after.group] == config.groups[before.group]


def test_group_names_survive_when_they_follow_the_rule() -> None:
    tags = (
        TagConfig("a", "D0", vt.INT16, group="scan_100ms"),
        TagConfig("b", "D1", vt.INT16),
    )
    config = PollConfig((PlcConfig("p", E71, tags),), {"default": 1.0, "scan_100ms": 0.1})
    text = write_kepware(config.plcs[0], config.groups)
    again = parse_config(to_toml(read_kepware(text.encode(), "t.csv", plc="p", url=E71))).poll
    assert [t.group for t in again.plcs[0].tags] == ["scan_100ms", "default"]
    assert again.groups == config.groups
