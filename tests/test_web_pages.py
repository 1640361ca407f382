"""The console's parts without a browser: display forms, ``decimals`` and ``labels`` in the
configuration, last known values and their stale marker, the overview's filter, order and pages,
its size at 1000 PLCs, and the overview's event stream (no tags)."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest

from plcstack import values as vt
from plcstack.config import parse_config
from plcstack.errors import ConfigError
from plcstack.north.web.display import TagDisplay
from plcstack.north.web.events import EventHub
from plcstack.north.web.overview import PAGE_SIZE, select
from plcstack.north.web.pages import overview_page
from plcstack.north.web.state import ConsoleState, PlcRow, plc_row
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.samples import Quality, Scan, make_sample
from plcstack.values import Scale

URL = "e71+tcp://127.0.0.1:1"
ARRAY = "[0000h, 0001h, 0002h, 0003h, 0004h, 0005h, 0006h, 0007h, ... (10 values)]"


@pytest.mark.parametrize(
    ("config", "value", "text"),
    [
        (TagConfig("t", "D0", vt.KH), 0x12AF, "12AFh"),
        (TagConfig("t", "D0", vt.KH), 7, "0007h"),
        (TagConfig("t", "D0"), 4660, "1234h"),  # a raw word
        (TagConfig("t", "M0"), True, "on"),  # a raw bit
        (TagConfig("t", "D0", vt.KM), 0x1234, "00010010 00110100"),
        (TagConfig("t", "DB1.DW0", vt.KY), (18, 52), "18,52"),
        (TagConfig("t", "M0", vt.BOOL), False, "off"),
        (TagConfig("t", "M0", vt.BOOL, labels=((0, "closed"), (1, "open"))), True, "open"),
        (TagConfig("t", "D0", vt.INT16, labels=((0, "stop"), (7, "fault"))), 7, "fault"),
        (TagConfig("t", "D0", vt.INT16, labels=((0, "stop"),)), 3, "3"),  # no name: the number
        (TagConfig("t", "D0", vt.INT16, unit="rpm"), -1500, "-1500 rpm"),
        (TagConfig("t", "D0", vt.FLOAT32, unit="°C"), 59.46688461303711, "59.466885 °C"),
        (TagConfig("t", "D0", vt.FLOAT32, unit="°C", decimals=1), 59.46688461303711, "59.5 °C"),
        (TagConfig("t", "D0", vt.FLOAT32, decimals=0), 2.5, "2"),
        (TagConfig("t", "D0", vt.INT16, scale=Scale(0, 4000, 0.0, 100.0)), 51.2, "51.2"),
        (TagConfig("t", "D0", vt.FLOAT32), float("nan"), "NaN"),
        (TagConfig("t", "D0", vt.FLOAT32), float("-inf"), "-inf"),
        (TagConfig("t", "D0", vt.KH, count=10), list(range(10)), ARRAY),
        (TagConfig("t", "D0", vt.string(4)), "AB", "AB"),
        (TagConfig("t", "D0", vt.INT16), None, ""),
    ],
)
def test_display_forms(config: TagConfig, value: Any, text: str) -> None:
    assert TagDisplay(config).text(value) == text


def test_decimals_and_labels_from_toml() -> None:
    config = parse_config(
        '[[plc]]\nname = "p"\nurl = "e71+tcp://127.0.0.1:5000"\n[plc.tags]\n'
        'valve = { address = "M0", type = "bool", labels = ["closed", "open"] }\n'
        'mode = { address = "D0", type = "int16", labels = { 0 = "stopped", 7 = "fault" } }\n'
        'flow = { address = "D2", type = "float32", decimals = 1 }\n'
    )
    valve, mode, flow = config.plcs[0].tags
    assert valve.labels == ((0, "closed"), (1, "open"))
    assert mode.labels == ((0, "stopped"), (7, "fault"))
    assert flow.decimals == 1 and flow.labels is None


@pytest.mark.parametrize(
    ("spec", "problem"),
    [
        ('{ address = "D2", type = "float32", decimals = 12 }', "decimals must be a whole number"),
        ('{ address = "D2", type = "float32", decimals = 1.5 }', "decimals must be a whole"),
        ('{ address = "M0", type = "bool", labels = ["one"] }', "labels of a bool are two"),
        ('{ address = "D0", type = "float32", labels = ["a"] }', "not of a float32"),
        ('{ address = "D0", type = "int16", labels = { x = "a" } }', "'x' is not a whole number"),
        ('{ address = "D0", type = "int16", labels = { 1 = "a", "01" = "b" } }', "named twice"),
        ('{ address = "D0", type = "int16", labels = [""] }', "non-empty string"),
        ('{ address = "D0", type = "int16", labels = "on" }', "labels must be a list"),
    ],
)
def test_decimals_and_labels_errors(spec: str, problem: str) -> None:
    text = f'[[plc]]\nname = "p"\nurl = "e71+tcp://127.0.0.1:5000"\n[plc.tags]\nx = {spec}\n'
    with pytest.raises(ConfigError) as caught:
        parse_config(text, source="plant.toml")
    assert problem in str(caught.value)
    assert "plant.toml:5" in str(caught.value)  # the tag's line


def test_python_configs_are_checked_too() -> None:
    tag = TagConfig("v", "M0", vt.BOOL, labels=((0, "a"), (2, "b")))
    with pytest.raises(ConfigError, match="labels of a bool are two"):
        PollConfig((PlcConfig("p", URL, (tag,)),))


def sample(plc: str, tag: str, value: Any, t: float, error: str | None = None) -> Any:
    quality = Quality.GOOD if error is None else Quality.BAD
    return make_sample(plc, tag, value, quality, t, t + 0.01, error)


def test_the_last_good_value_stays_marked_stale() -> None:
    tags = (TagConfig("temp", "D0", vt.FLOAT32, unit="°C", decimals=1), TagConfig("n", "D2"))
    state = ConsoleState([PlcConfig("p", URL, tags)])
    state.submit([Scan("p", "default", 10.0, 10.1, (sample("p", "temp", 61.5, 10.0),))])
    state.submit([Scan("p", "default", 11.0, 11.1, (sample("p", "temp", 61.5, 11.0),))])
    good = state.latest[("p", "temp")]
    assert state.text(good) == ("61.5 °C", 10.0, None)  # the value holds since 10.0
    dead = "p: timeout after 2.0 s"
    bad = (sample("p", "temp", None, 12.0, dead), sample("p", "n", None, 12.0, dead))
    state.submit([Scan("p", "default", 12.0, 14.0, bad)])
    state.submit([Scan("p", "default", 15.0, 17.0, bad)])
    latest = state.latest[("p", "temp")]
    assert latest.value is None
    assert state.text(latest) == ("61.5 °C", 10.0, 12.0)  # kept; stale since the first bad
    assert state.text(state.latest[("p", "n")]) == ("", None, 12.0)  # never read
    health = state.health["p"]
    assert (health.up, health.bad_tags, health.last_error) == (False, 2, dead)
    assert health.since == 14.0  # when the first failed scan ended
    row = plc_row("p", health, None, 2)
    assert (row["state"], row["since"], row["bad_tags"]) == ("offline", 14.0, 2)
    state.submit([Scan("p", "default", 20.0, 20.1, (sample("p", "temp", 62.0, 20.0),))])
    assert state.text(state.latest[("p", "temp")]) == ("62.0 °C", 20.0, None)
    assert (health.up, health.bad_tags, health.since) == (True, 1, 20.0)
    assert state.counts() == {"offline": 0, "errors": 1, "unknown": 0, "online": 0, "total": 1}


def fleet(n: int, tags: int = 10) -> ConsoleState:
    tag_list = tuple(TagConfig(f"t{i}", f"D{i}", vt.INT16, unit="mm") for i in range(tags))
    return ConsoleState([PlcConfig(f"line{i:04d}", URL, tag_list) for i in range(n)])


def test_overview_filters_sorts_and_pages() -> None:
    state = fleet(200, tags=1)
    for i in range(200):
        s = sample(f"line{i:04d}", "t0", i, 1.0, None if i % 50 else "refused")
        state.submit([Scan(s.plc, "default", 1.0, 1.1, (s,))])
    first = select(state.plcs, state.health)
    assert (first.matched, first.pages, first.page, len(first.names)) == (200, 4, 1, PAGE_SIZE)
    assert first.names[:4] == ["line0000", "line0050", "line0100", "line0150"]  # offline first
    assert select(state.plcs, state.health, query="LINE0137").names == ["line0137"]
    assert select(state.plcs, state.health, query="offline").matched == 4
    assert select(state.plcs, state.health, query="line010 offline").names == ["line0100"]
    by_name = select(state.plcs, state.health, sort="name", page="2")
    assert by_name.names[0] == "line0050" and by_name.first == 51
    assert select(state.plcs, state.health, page="99").page == 4  # the last
    assert select(state.plcs, state.health, page="x", sort="?").page == 1
    assert select(state.plcs, state.health, query="nothing").names == []


def test_the_overview_of_1000_plcs_is_small() -> None:
    state = fleet(1000)
    selection = select(state.plcs, state.health)
    rows = [plc_row(n, state.health[n], None, len(state.plcs[n].tags)) for n in selection.names]
    page = overview_page(state, selection, rows, trend_seconds=300, history=True)
    assert len(page.encode()) < 40_000, len(page.encode())  # a page of rows, not 10,000 tags
    assert page.count("<tr data-plc=") == PAGE_SIZE + 1  # and the row template


async def drain(client: Any) -> list[bytes]:
    """The event names queued for ``client``."""
    names: list[bytes] = []
    while True:
        try:
            data = await asyncio.wait_for(client.next(), 0.05)
        except TimeoutError:
            return names
        names.append(data.split(b"\n", 1)[0])


def _row(name: str) -> PlcRow:
    return {
        "name": name,
        "tags": 2,
        "up": True,
        "state": "online",
        "since": None,
        "last_error": None,
        "error_time": None,
        "bad_tags": 0,
        "requests": 0,
    }


def test_the_overview_stream_carries_the_rows_it_shows() -> None:
    state = fleet(3, tags=2)
    rows = [_row(f"line{i:04d}") for i in range(3)]
    hub = EventHub(state, lambda plc: rows, plcs_every=0.5)

    async def scenario() -> list[Any]:
        client = hub.connect(None, overview=True, names=["line0001", "line0002"])
        assert client is not None
        snapshot = await client.next()
        for row in rows:
            row["requests"] = 1  # every row changes
        hub.push()
        await client.next()  # the snapshot's counts
        pushed = await client.next()
        return [json.loads(data.split(b"data: ")[1]) for data in (snapshot, pushed) if data]

    snapshot, pushed = asyncio.run(scenario())
    assert [r["name"] for r in snapshot] == ["line0001", "line0002"]
    assert [r["name"] for r in pushed] == ["line0001", "line0002"]


def test_the_overview_stream_carries_no_tags() -> None:
    state = fleet(3, tags=2)
    hub = EventHub(state, lambda plc: [_row("line0000")], plcs_every=0.5)

    async def scenario() -> tuple[list[bytes], list[bytes]]:
        overview = hub.connect(None, overview=True)
        everything = hub.connect(None)
        assert overview is not None and everything is not None
        s = sample("line0000", "t0", 5, 1.0)
        state.submit([Scan("line0000", "default", 1.0, 1.1, (s,))])
        hub.push()
        return await drain(overview), await drain(everything)

    overview, everything = asyncio.run(scenario())
    assert overview == [b"event: plcs", b"event: counts", b"event: plcs", b"event: counts"]
    assert everything == [b"event: plcs", b"event: tags", b"event: tags", b"event: plcs"]
