"""TOML configuration: a full example, and validation errors that name PLC, tag and line."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack import config as whole
from plcstack import values as vt
from plcstack.poll.config import (
    ConfigError,
    PlcConfig,
    PollConfig,
    TagConfig,
)
from plcstack.values import WordOrder


def parse_config(text: str, *, source: str = "<config>") -> PollConfig:
    """The poll part of a configuration text, read by the one loader."""
    return whole.parse_config(text, source=source).poll


def load_config(path: object) -> PollConfig:
    return whole.load_config(str(path)).poll


GOOD = """
[poll]
concurrency = 8
queue = 100
max_gap = 4
timeout = 1.5
interval = 0.5

[groups]
fast = 0.1

[[plc]]
name = "press1"
url = "e71+tcp://127.0.0.1:5000"
group = "fast"

[plc.tags]
counter = "D100"
temp = { address = "D102", type = "float32", group = "default" }
alarms = { address = "M0", type = "bool", count = 16 }

[[plc]]
name = "kiln2"
url = "s5lan://127.0.0.1:5010?timeout=3"
word_order = "little"
max_gap = 0
timeout = 0.25

[plc.tags]
"level.1" = { address = "DB10.DW5", type = "int16" }
"""


def test_full_example() -> None:
    config = parse_config(GOOD)
    assert config.concurrency == 8 and config.queue == 100
    assert dict(config.groups) == {"default": 0.5, "fast": 0.1}
    p1, p2 = config.plcs
    assert p1.name == "press1" and p1.max_gap == 4 and p1.timeout == 1.5
    assert [(t.name, t.address, t.type, t.count, t.group) for t in p1.tags] == [
        ("counter", "D100", vt.RAW, 1, "fast"),
        ("temp", "D102", vt.FLOAT32, 1, "default"),
        ("alarms", "M0", vt.BOOL, 16, "fast"),
    ]
    assert p1.order is WordOrder.LITTLE  # MELSEC default
    assert p2.name == "kiln2" and p2.url == "s5lan://127.0.0.1:5010?timeout=3"
    assert p2.order is WordOrder.LITTLE and p2.max_gap == 0 and p2.timeout == 0.25
    assert p2.tags[0].name == "level.1"


def test_batch_wait_default_zero_and_checked_in_python_too() -> None:
    good = parse_config(GOOD)
    assert good.batch_wait == 0.01
    assert parse_config("[poll]\nbatch_wait = 0\n" + GOOD.split("[poll]")[1]).batch_wait == 0
    assert PollConfig(good.plcs, good.groups, batch_wait=0.2).batch_wait == 0.2
    with pytest.raises(ConfigError, match="batch_wait"):
        PollConfig(good.plcs, good.groups, batch_wait=float("inf"))


def test_s5_default_word_order_is_big() -> None:
    plc = PlcConfig("x", "fetchwrite://127.0.0.1:2000", ())
    assert plc.order is WordOrder.BIG


def with_plc(body: str, tags: str = 'a = "D0"') -> str:
    return f'[[plc]]\nname = "p1"\nurl = "e71+tcp://127.0.0.1:5000"\n{body}\n[plc.tags]\n{tags}\n'


ERRORS = [
    # (toml, words the message must contain)
    ("[[plc]\n", ["not valid TOML", "line 1"]),
    ("", ["no PLC configured"]),
    ("[poll]\nconcurency = 3\n" + with_plc(""), ["unknown key", "concurency", "cfg.toml:2"]),
    ("[poll]\nconcurrency = 0\n" + with_plc(""), ["concurrency", "at least 1"]),
    ("[poll]\nbatch_wait = -0.5\n" + with_plc(""), ["batch_wait", "0 to 1", "cfg.toml:2"]),
    ("[poll]\nbatch_wait = 5\n" + with_plc(""), ["batch_wait", "0 to 1", "cfg.toml:2"]),
    ('[poll]\nbatch_wait = "soon"\n' + with_plc(""), ["batch_wait", "'soon'"]),
    ("[poll]\nbatch_wait = nan\n" + with_plc(""), ["batch_wait", "nan"]),
    ("[poll]\ninterval = -1\n" + with_plc(""), ["interval", "greater than 0"]),
    ('[groups]\nfast = "x"\n' + with_plc(""), ["fast", "number"]),
    ('[[plc]]\nname = "p1"\n[plc.tags]\na = "D0"\n', ["p1", "missing url", "cfg.toml:1"]),
    (with_plc("").replace("5000", "99999"), ["p1", "bad url", "port", "cfg.toml:3"]),
    (with_plc("").replace("e71+tcp", "modbus"), ["p1", "unknown scheme"]),
    (with_plc('group = "turbo"'), ["p1", "unknown scan group 'turbo'", "cfg.toml:4"]),
    (with_plc('word_order = "middle"'), ["p1", "word_order", "cfg.toml:4"]),
    (with_plc("colour = 1"), ["p1", "unknown key", "colour", "cfg.toml:4"]),
    (with_plc("", tags=""), ["p1", "no tags"]),
    (with_plc("", tags="a = 5"), ["p1", "tag 'a'", "ADDRESS", "cfg.toml:6"]),
    (
        with_plc("", tags='a = "D0"\nb = { type = "int16" }'),
        ["p1", "tag 'b'", "missing address", "cfg.toml:7"],
    ),
    (
        with_plc("", tags='a = { address = "D0", type = "int42" }'),
        ["p1", "tag 'a'", "unknown type 'int42'", "float32"],
    ),
    (with_plc("", tags='a = { address = "D0", count = 0 }'), ["p1", "tag 'a'", "count"]),
    (with_plc("", tags='a = { address = "D0", count = true }'), ["p1", "tag 'a'", "count"]),
    (with_plc("", tags='a = { address = "D0", group = "x" }'), ["p1", "tag 'a'", "scan group 'x'"]),
    (with_plc("", tags='a = { address = "D0", scale = 2 }'), ["p1", "tag 'a'", "scale"]),
    (
        with_plc("", tags='a = { address = "D0", description = 5 }'),
        ["p1", "tag 'a'", "description", "non-empty string", "cfg.toml:6"],
    ),
    (
        with_plc("", tags='a = { address = "D0", description = " " }'),
        ["p1", "tag 'a'", "description", "non-empty"],
    ),
    (
        with_plc("", tags='a = { address = "D0", description = "two\\nlines" }'),
        ["p1", "tag 'a'", "description", "control characters", "'\\n'"],
    ),
    (
        with_plc("", tags='a = { address = "D0", description = "' + "x" * 1025 + '" }'),
        ["p1", "tag 'a'", "description", "at most 1024"],
    ),
    (with_plc("") + with_plc(""), ["p1", "used twice", "cfg.toml:8"]),
    (with_plc("max_gap = -1"), ["p1", "max_gap", "at least 0"]),
    (with_plc("timeout = 0"), ["p1", "timeout", "greater than 0"]),
    ("plc = 3\n", ["[[plc]]"]),
    ("[other]\n", ["unknown top-level", "other"]),
]


@pytest.mark.parametrize(("text", "words"), ERRORS)
def test_validation_errors(text: str, words: list[str]) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(text, source="cfg.toml")
    message = str(err.value)
    for word in words:
        assert word in message, message


def test_description_is_read_and_optional() -> None:
    tags = (
        'pump = { address = "M10", type = "bool", description = "Feed pump 2 running\tP-102" }\n'
        'level = "D0"\n'
        'temp = { address = "D2", description = "Öltemperatur °C 油温" }\n'
    )
    pump, level, temp = parse_config(with_plc("", tags=tags)).plcs[0].tags
    assert pump.description == "Feed pump 2 running\tP-102"
    assert level.description is None
    assert temp.description == "Öltemperatur °C 油温"


def test_python_built_description_is_checked_too() -> None:
    good = vt.INT16
    ok = PlcConfig("p", "e71+tcp://127.0.0.1:1", (TagConfig("a", "D0", good, description="x"),))
    assert PollConfig((ok,)).plcs[0].tags[0].description == "x"
    for bad in ("", "a\nb", 5):
        tag = TagConfig("a", "D0", good, description=bad)  # type: ignore[arg-type]
        with pytest.raises(ConfigError, match="tag 'a': description"):
            PollConfig((PlcConfig("p", "e71+tcp://127.0.0.1:1", (tag,)),))


def test_python_built_config_is_validated_too() -> None:
    plc = PlcConfig("p", "e71+tcp://127.0.0.1:1", ())
    with pytest.raises(ConfigError, match="used twice"):
        PollConfig((plc, plc))
    with pytest.raises(ConfigError, match="interval"):
        PollConfig((plc,), {"default": 0})
    with pytest.raises(ConfigError, match="bad url"):
        PollConfig((PlcConfig("q", "nope", ()),))


def test_load_config_file(tmp_path: object) -> None:
    from pathlib import Path

    path = Path(str(tmp_path)) / "plant.toml"
    path.write_text(GOOD)
    assert len(load_config(path).plcs) == 2
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(path.with_name("missing.toml"))


def test_the_shipped_example_config_is_valid() -> None:
    from pathlib import Path

    config = load_config(Path(__file__).resolve().parent.parent / "plcstack/examples/plant.toml")
    assert [p.name for p in config.plcs] == ["press1", "oven2"]
    assert dict(config.groups) == {"default": 1.0, "fast": 0.2}


# -- bad input never crashes: only ConfigError, whatever the file holds ---------------------------

_VALUES = st.one_of(
    st.integers(-5, 5),
    st.floats(allow_nan=True),
    st.booleans(),
    st.sampled_from(["D0", "M0", "DB10.DW0", "int16", "fast", "big", "", "e71+tcp://h:1", "x"]),
)
_KEYS = st.sampled_from(
    ["name", "url", "group", "tags", "address", "type", "count", "interval", "max_gap", "timeout",
     "word_order", "concurrency", "queue", "fast", "a", "b"]
)  # fmt: skip


def _toml(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if value == value and abs(value) != float("inf") else "nan"
    if isinstance(value, str):
        return '"' + value + '"'
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + " }"
    return str(value)


@settings(max_examples=200, deadline=None)
@given(
    poll=st.dictionaries(_KEYS, _VALUES, max_size=3),
    plcs=st.lists(
        st.tuples(
            st.dictionaries(_KEYS, _VALUES, max_size=4),
            st.dictionaries(_KEYS, st.one_of(_VALUES, st.dictionaries(_KEYS, _VALUES, max_size=3))),
        ),
        max_size=3,
    ),
)
def test_any_structure_gives_a_config_or_a_config_error(
    poll: dict[str, object], plcs: list[tuple[dict[str, object], dict[str, object]]]
) -> None:
    text = "[poll]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in poll.items())
    for fields, tags in plcs:
        text += "[[plc]]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in fields.items())
        if "tags" not in fields:
            text += "[plc.tags]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in tags.items())
    try:
        parse_config(text)
    except ConfigError as exc:
        assert str(exc)


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_mutated_example_gives_a_config_or_a_config_error(data: st.DataObject) -> None:
    lines = GOOD.splitlines()
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(lines) - 1))
        action = data.draw(st.sampled_from(["drop", "garble", "dup"]))
        if action == "drop":
            del lines[i]
        elif action == "dup":
            lines.insert(i, lines[i])
        else:
            j = data.draw(st.integers(0, max(0, len(lines[i]) - 1)))
            lines[i] = lines[i][:j] + data.draw(st.text(max_size=3)) + lines[i][j + 1 :]
        if not lines:
            break
    with contextlib.suppress(ConfigError):
        parse_config("\n".join(lines))
