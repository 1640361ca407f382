"""diff(old, new): what a reload has to do, PLC by PLC and table by table.

Properties: a configuration diffed with itself is empty; the PLCs of the new configuration are
exactly the unchanged ones of the old plus the added, reconnected and replanned ones, and the
removed are the old ones it no longer has; each PLC is classified by what changed in it.
"""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from plcstack.config import Config, diff, parse_config
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.diff import plc_changes
from plcstack.values import FLOAT32, INT16

NAMES = ["press1", "press2", "oven1", "oven2", "kiln"]
URLS = ["e71+tcp://10.0.0.5:5000", "e71+tcp://10.0.0.6:5000", "e71+tcp://10.0.0.5:5000?timeout=3"]
TAGS = [
    TagConfig("strokes", "D100"),
    TagConfig("temp", "D102", FLOAT32),
    TagConfig("temp", "D104", FLOAT32),
    TagConfig("level", "D110", INT16, group="fast"),
    TagConfig("speed", "D120", INT16, unit="rpm"),
]


@st.composite
def plcs(draw: st.DrawFn, name: str) -> PlcConfig:
    chosen = draw(st.lists(st.sampled_from(TAGS), min_size=1, max_size=3))
    tags = tuple({t.name: t for t in chosen}.values())  # one of each name
    return PlcConfig(
        name,
        draw(st.sampled_from(URLS)),
        tags,
        max_gap=draw(st.sampled_from([4, 8])),
        timeout=draw(st.sampled_from([None, 1.0])),
    )


@st.composite
def configs(draw: st.DrawFn) -> PollConfig:
    names = draw(st.lists(st.sampled_from(NAMES), min_size=1, max_size=5, unique=True))
    groups = {"default": 1.0, "fast": draw(st.sampled_from([0.1, 0.2]))}
    queue = draw(st.sampled_from([1000, 10_000]))
    return PollConfig(tuple(draw(plcs(n)) for n in names), groups, queue=queue)


@given(configs())
def test_a_configuration_diffed_with_itself_is_empty(config: PollConfig) -> None:
    changes = plc_changes(config, config)
    assert changes.empty and changes.unchanged == tuple(p.name for p in config.plcs)
    assert diff(Config(config), Config(config)).empty


@given(configs(), configs())
def test_the_changes_lead_from_the_old_configuration_to_the_new(
    old: PollConfig, new: PollConfig
) -> None:
    changes = plc_changes(old, new)
    before = {p.name: p for p in old.plcs}
    # applying the change to the old PLCs gives the new ones
    after = {n: before[n] for n in changes.unchanged}
    for plc in (*changes.added, *changes.reconnected, *changes.replanned):
        assert plc.name not in after  # each PLC in one set only
        after[plc.name] = plc
    assert after == {p.name: p for p in new.plcs}
    assert {p.name for p in changes.removed} == set(before) - set(after)
    # and each is where it belongs
    for plc in changes.added:
        assert plc.name not in before
    for plc in changes.reconnected:
        was = before[plc.name]
        assert (was.url, was.timeout) != (plc.url, plc.timeout)
    for plc in changes.replanned:
        was = before[plc.name]
        assert (was.url, was.timeout) == (plc.url, plc.timeout)
        intervals = (
            {t.group: old.groups[t.group] for t in was.tags},
            {t.group: new.groups[t.group] for t in plc.tags},
        )
        assert was != plc or intervals[0] != intervals[1]
    for name in changes.unchanged:
        plc = before[name]
        assert {t.group: old.groups[t.group] for t in plc.tags} == {
            t.group: new.groups[t.group] for t in plc.tags
        }
    assert ("queue" in changes.poller) == (old.queue != new.queue)


PLANT = """
[groups]
fast = 0.1

[web]
listen = "127.0.0.1:8080"

[[plc]]
name = "press1"
url = "e71+tcp://10.0.0.5:5000"
tags = { strokes = "D100", temp = { address = "D102", type = "float32" } }

[[plc]]
name = "press2"
url = "e71+tcp://10.0.0.6:5000"
tags = { strokes = "D100" }

[[plc]]
name = "oven1"
url = "s5lan://10.0.0.7:5010"
tags = { temp = { address = "DB10.DW0", type = "kg", group = "fast" } }
"""


def _changed(new_text: str) -> tuple[list[str], list[str], list[str], list[str], list[str]]:
    d = diff(parse_config(PLANT), parse_config(new_text))
    p = d.plcs
    return (
        [x.name for x in p.added],
        [x.name for x in p.removed],
        [x.name for x in p.reconnected],
        [x.name for x in p.replanned],
        list(d.tables),
    )


def test_a_file_edited_as_a_plant_engineer_edits_it() -> None:
    assert _changed(PLANT) == ([], [], [], [], [])
    # comments, blank lines and the order of keys are no change
    assert _changed("# line 1\n" + PLANT.replace("\n\n", "\n\n\n")) == ([], [], [], [], [])
    # a new tag: replanned on the open connection
    more = PLANT.replace('tags = { strokes = "D100" }', 'tags = { strokes = "D100", s = "D9" }')
    assert _changed(more) == ([], [], [], ["press2"], [])
    # a new IP address: a new connection
    moved = PLANT.replace("10.0.0.6:5000", "10.0.0.16:5000")
    assert _changed(moved) == ([], [], ["press2"], [], [])
    # a deadline is part of the connection
    slow = PLANT.replace(
        'url = "s5lan://10.0.0.7:5010"', 'url = "s5lan://10.0.0.7:5010"\ntimeout = 5'
    )
    assert _changed(slow) == ([], [], ["oven1"], [], [])
    # a scan group's interval: the PLCs scanning in it are replanned, no one else
    faster = PLANT.replace("fast = 0.1", "fast = 0.05")
    assert _changed(faster) == ([], [], [], ["oven1"], [])
    # one PLC out, one in; a face's table edited
    swapped = PLANT.replace('name = "press2"', 'name = "press3"').replace(":8080", ":8081")
    assert _changed(swapped) == (["press3"], ["press2"], [], [], ["web"])
    # a face added and one removed
    faces = PLANT.replace("[web]", '[mqtt]\nurl = "mqtt://127.0.0.1:1883"\n\n[metrics]').replace(
        'listen = "127.0.0.1:8080"', ""
    )
    assert _changed(faces) == ([], [], [], [], ["mqtt", "metrics", "web"])


def test_the_summary_is_one_line_for_the_log() -> None:
    new = PLANT.replace('name = "press2"', 'name = "press3"').replace("fast = 0.1", "fast = 0.2")
    d = diff(parse_config(PLANT), parse_config(new))
    assert d.summary() == (
        "1 added (press3), 1 removed (press2), 0 reconnected, 1 replanned (oven1)"
    )
