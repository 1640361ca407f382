"""Merging and splitting with the real protocol clients' hooks (locate/address_at/max_points).

No I/O: clients are created from URLs and never opened. A protocol whose client is not in this
tree yet is skipped.
"""

from __future__ import annotations

import importlib.util

import pytest

from plcstack import values as vt
from plcstack.clients import connect
from plcstack.clients.base import Client
from plcstack.poll.config import TagConfig
from plcstack.poll.plan import build_plan
from plcstack.url import parse_url
from plcstack.values import default_word_order

URLS = {
    "e71": "e71+tcp://127.0.0.1:5000",
    "s5lan": "s5lan://127.0.0.1:5010",
    "fetchwrite": "fetchwrite://127.0.0.1:2000",
    "as511": "as511+tcp://127.0.0.1:7777",
}


def client_for(name: str) -> Client:
    if importlib.util.find_spec(f"plcstack.clients.{name}") is None:
        pytest.skip(f"{name} client is not in this tree yet")
    return connect(URLS[name])


def tag(name: str, address: str, type: str = "raw", count: int = 1) -> TagConfig:
    return TagConfig(name, address, vt.value_type(type), count)


def shape(client: Client, tags: list[TagConfig], gap: int) -> list[tuple[str, int]]:
    return [(r.address, r.count) for r in build_plan(client, tags, max_gap=gap).requests]


E71_CASES = [
    # three types in consecutive registers: one frame
    ([tag("u", "D100", "uint16"), tag("i", "D101", "int16"), tag("f", "D102", "float32")], 0,
     [("D100", 4)]),
    # too far apart for the gap
    ([tag("a", "D0"), tag("b", "D300")], 8, [("D0", 1), ("D300", 1)]),
    # one tag over the 256-point frame limit: two frames
    ([tag("big", "D0", count=300)], 0, [("D0", 256), ("D256", 44)]),
    # bits: 16 + gap + 1 in one bit-unit read
    ([tag("alarms", "M0", "bool", 16), tag("run", "M20", "bool")], 8, [("M0", 21)]),
    # different devices never merge
    ([tag("x", "X0", "bool"), tag("y", "Y0", "bool"), tag("w", "W0"), tag("d", "D0")], 100,
     [("X0", 1), ("Y0", 1), ("W0", 1), ("D0", 1)]),
]  # fmt: skip


@pytest.mark.parametrize(("tags", "gap", "expected"), E71_CASES)
def test_e71_merging(tags: list[TagConfig], gap: int, expected: list[tuple[str, int]]) -> None:
    assert shape(client_for("e71"), tags, gap) == expected


S5_CASES = [
    ([tag("u", "DB10.DW0", "uint16"), tag("i", "DB10.DW1", "int16"),
      tag("f", "DB10.DW2", "float32")], 0, [("DB10.DW0", 4)]),
    ([tag("a", "DB10.DW0"), tag("b", "DB11.DW0")], 100, [("DB10.DW0", 1), ("DB11.DW0", 1)]),
    # flag words step by two bytes: MW0 and MW2 are neighbours, MW1 is another grid
    ([tag("a", "MW0"), tag("b", "MW2")], 0, [("MW0", 2)]),
    ([tag("a", "MW0"), tag("b", "MW1")], 100, [("MW0", 1), ("MW1", 1)]),
    # bytes: int16 over flag bytes is two points, so MB0..MB5 is one read
    ([tag("a", "MB0", "uint8"), tag("b", "MB1", "uint8"), tag("c", "MB4", "int16")], 2,
     [("MB0", 6)]),
    ([tag("i", "EB0", "uint8"), tag("q", "AB0", "uint8")], 100, [("EB0", 1), ("AB0", 1)]),
]  # fmt: skip


def _s5(name: str) -> list[object]:
    return [pytest.param(name, *case, id=f"{name}-{i}") for i, case in enumerate(S5_CASES)]


@pytest.mark.parametrize(
    ("protocol", "tags", "gap", "expected"),
    [p for n in ("s5lan", "fetchwrite", "as511") for p in _s5(n)],
)
def test_s5_merging(
    protocol: str, tags: list[TagConfig], gap: int, expected: list[tuple[str, int]]
) -> None:
    assert shape(client_for(protocol), tags, gap) == expected


@pytest.mark.parametrize("protocol", list(URLS))
def test_frame_limit_splits_a_long_tag(protocol: str) -> None:
    client = client_for(protocol)
    address = "D0" if protocol == "e71" else "DB10.DW0"
    area, _ = client.locate(address)
    limit = client.max_points(area)
    plan = build_plan(client, [tag("big", address, count=limit + 10)])
    assert [r.count for r in plan.requests] == [limit, 10]
    assert plan.requests[1].address == client.address_at(area, limit)
    reply = [list(range(limit)), list(range(limit, limit + 10))]
    (result,) = plan.split(reply, default_word_order(parse_url(URLS[protocol]).scheme))
    assert result.value == list(range(limit + 10))


@pytest.mark.parametrize("protocol", list(URLS))
def test_split_uses_the_family_word_order(protocol: str) -> None:
    client = client_for(protocol)
    first = "D0" if protocol == "e71" else "DB10.DW0"
    area, index = client.locate(first)
    tags = [
        tag("n", first, "int16"),
        tag("f", client.address_at(area, index + 1), "float32"),
        tag("l", client.address_at(area, index + 3), "int32"),
    ]
    plan = build_plan(client, tags)
    assert len(plan.requests) == 1 and plan.requests[0].count == 5
    scheme = parse_url(URLS[protocol]).scheme
    reply = {
        "e71": [0xFFFF, 0x0000, 0x3FC0, 0x0002, 0x0001],  # MELSEC: low word first
    }.get(protocol, [0xFFFF, 0x3FC0, 0x0000, 0x0001, 0x0002])  # S5: high word first
    values = [r.value for r in plan.split([reply], default_word_order(scheme))]
    assert values == [-1, 1.5, 0x00010002]


@pytest.mark.parametrize(
    ("url", "address", "bits"),
    [
        ("e71+tcp://h:1", "M0", 1),
        ("e71+tcp://h:1", "X1F", 1),
        ("e71+tcp://h:1", "D0", 16),
        ("s5lan://h:1", "MB0", 8),
        ("s5lan://h:1", "MW0", 16),
        ("fetchwrite://h:1", "MB0", 8),
        ("fetchwrite://h:1", "EB0", 8),
        ("fetchwrite://h:1", "DB1.DW0", 16),
        ("as511+tcp://h:1", "MB0", 8),
        ("as511+tcp://h:1", "DB1.DW0", 16),
    ],
)
def test_every_client_states_its_point_width(url: str, address: str, bits: int) -> None:
    client = connect(url)
    area, _ = client.locate(address)
    assert client.point_bits(area) == bits
