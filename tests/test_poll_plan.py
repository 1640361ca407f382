"""Read plans (merging and splitting) and tag value types."""

from __future__ import annotations

import math
import struct
from typing import Any

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from plcstack import values as vt
from plcstack.errors import AddressError, PlcTimeout, RemoteProtocolError
from plcstack.poll.config import TagConfig
from plcstack.poll.plan import build_plan
from plcstack.values import WordOrder
from tests.poll_fakes import FakeClient

BIG, LITTLE = WordOrder.BIG, WordOrder.LITTLE

#: the types whose decoders take the struct fast paths (and RAW/BOOL)
PLAIN_TYPES = [
    vt.value_type(n)
    for n in ("raw", "bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "float32")
]


def tag(name: str, address: str, type: str = "raw", count: int = 1) -> TagConfig:
    return TagConfig(name, address, vt.value_type(type), count)


def shape(plan: object) -> list[tuple[str, int]]:
    return [(r.address, r.count) for r in plan.requests]  # type: ignore[attr-defined]


# -- merging: table-driven ------------------------------------------------------------------------
MERGE_CASES = [
    # (tags, max_gap, expected requests)
    ([tag("a", "D100"), tag("b", "D101")], 0, [("D100", 2)]),
    ([tag("a", "D100"), tag("b", "D102")], 0, [("D100", 1), ("D102", 1)]),
    ([tag("a", "D100"), tag("b", "D102")], 1, [("D100", 3)]),
    ([tag("a", "D100"), tag("b", "D110")], 8, [("D100", 1), ("D110", 1)]),
    ([tag("a", "D100"), tag("b", "D109")], 8, [("D100", 10)]),
    # order in the config does not matter
    ([tag("b", "D109"), tag("a", "D100"), tag("c", "D104")], 8, [("D100", 10)]),
    # types widen spans: float32 = 2 words, so D100..D101 then D102 adjacent
    ([tag("f", "D100", "float32"), tag("n", "D102", "int16")], 0, [("D100", 3)]),
    # overlapping tags share points
    ([tag("a", "D100", count=10), tag("b", "D105", count=2)], 0, [("D100", 10)]),
    # different areas are never merged
    ([tag("a", "D100"), tag("m", "M100", "bool")], 100, [("D100", 1), ("M100", 1)]),
    # the frame limit (64 words here): D0..D69 is no frame, so two requests of one point
    ([tag("a", "D0"), tag("b", "D69")], 100, [("D0", 1), ("D69", 1)]),
    # a tag never straddles two frames unless it is longer than one
    ([tag("a", "D0"), tag("b", "D62", "int32"), tag("c", "D63")], 100, [("D0", 64)]),
    ([tag("a", "D0"), tag("b", "D63", "int32")], 100, [("D0", 1), ("D63", 2)]),
    ([tag("a", "D0"), tag("b", "D63")], 100, [("D0", 64)]),
    # one tag longer than a frame: split over frames, next tag joins the tail
    (
        [tag("big", "D0", count=150), tag("x", "D151")],
        1,
        [("D0", 64), ("D64", 64), ("D128", 24)],
    ),
    # bytes: int32 over an 8-bit area is four points
    ([tag("l", "B10", "int32"), tag("c", "B14", "uint8")], 0, [("B10", 5)]),
    # bit tags on a bit area: 16 bools are 16 points
    ([tag("alarms", "M0", "bool", 16), tag("run", "M20", "bool")], 4, [("M0", 21)]),
]


@pytest.mark.parametrize(("tags", "gap", "expected"), MERGE_CASES)
def test_merge(tags: list[TagConfig], gap: int, expected: list[tuple[str, int]]) -> None:
    plan = build_plan(FakeClient(), tags, max_gap=gap)
    assert shape(plan) == expected


def test_client_without_merge_hooks_reads_tag_by_tag() -> None:
    tags = [tag("a", "D100"), tag("b", "D101", "int32"), tag("c", "M0", "bool", 3)]
    plan = build_plan(FakeClient(merge=False), tags)
    assert shape(plan) == [("D100", 1), ("D101", 2), ("M0", 3)]


def test_isolated_tags_get_their_own_requests() -> None:
    tags = [tag("a", "D100"), tag("b", "D101"), tag("c", "D102")]
    plan = build_plan(FakeClient(), tags, isolate=frozenset({"b"}))
    assert shape(plan) == [("D100", 1), ("D101", 1), ("D102", 1)]


def test_bad_address_names_tag_and_plc() -> None:
    with pytest.raises(AddressError) as err:
        build_plan(FakeClient("fake://p1"), [tag("speed", "Q7")])
    assert "speed" in str(err.value) and "fake://p1" in str(err.value)
    # the last point must exist too
    with pytest.raises(AddressError, match="beyond"):
        build_plan(FakeClient(), [tag("tail", "D998", "int32", 2)])


def test_type_that_cannot_live_in_a_bit_area_is_refused() -> None:
    with pytest.raises(AddressError, match="bit area"):
        build_plan(FakeClient(), [tag("x", "M0", "float32")])


# -- splitting ----------------------------------------------------------------------------------
def test_split_decodes_each_tag_from_merged_replies() -> None:
    client = FakeClient()
    tags = [
        tag("u", "D0", "uint16"),
        tag("i", "D1", "int16"),
        tag("f", "D2", "float32"),
        tag("arr", "D4", "int16", 2),
    ]
    plan = build_plan(client, tags)
    assert shape(plan) == [("D0", 6)]
    f = int.from_bytes(struct.pack(">f", 1.5), "big")
    reply = [0xFFFF, 0xFFFE, f & 0xFFFF, f >> 16, 7, 0x8000]  # MELSEC order: low word first
    results = plan.split([reply], LITTLE)
    assert [(r.tag.name, r.value) for r in results] == [
        ("u", 65535),
        ("i", -2),
        ("f", 1.5),
        ("arr", [7, -32768]),
    ]


def test_split_marks_tags_of_a_failed_request_bad() -> None:
    plan = build_plan(FakeClient(), [tag("a", "D0"), tag("b", "D100"), tag("c", "D101")])
    assert shape(plan) == [("D0", 1), ("D100", 2)]
    results = plan.split([[5], PlcTimeout("late")], BIG)
    assert results[0].value == 5 and results[0].error is None
    assert results[1].value is None and isinstance(results[1].error, PlcTimeout)
    assert results[2].value is None and isinstance(results[2].error, PlcTimeout)


def test_split_refuses_a_short_reply() -> None:
    plan = build_plan(FakeClient(), [tag("a", "D0", count=3)])
    (result,) = plan.split([[1, 2]], BIG)
    assert isinstance(result.error, RemoteProtocolError)


# -- properties ---------------------------------------------------------------------------------
TYPES = ["raw", "int16", "uint16", "int32", "uint32", "float32"]


@st.composite
def tag_sets(draw: st.DrawFn) -> list[TagConfig]:
    n = draw(st.integers(1, 12))
    out = []
    for i in range(n):
        area = draw(st.sampled_from(["D", "M", "B"]))
        if area == "M":
            t, count, start = "bool", draw(st.integers(1, 40)), draw(st.integers(0, 1900))
        else:
            t = draw(st.sampled_from(TYPES))
            count = draw(st.integers(1, 70))
            start = draw(st.integers(0, 200 if area == "B" else 700))
            width = vt.value_type(t).points_per_value(8 if area == "B" else 16) * count
            if start + width > (256 if area == "B" else 1000):
                count, t = 1, "raw"
        out.append(tag(f"t{i}", f"{area}{start}", t, count))
    return out


@settings(max_examples=150, deadline=None)
@given(tags=tag_sets(), gap=st.integers(0, 20), order=st.sampled_from([BIG, LITTLE]))
def test_plan_reads_exactly_what_per_tag_reads_would(
    tags: list[TagConfig], gap: int, order: WordOrder
) -> None:
    client = FakeClient()
    # deterministic memory content so every point differs
    for area in ("D", "B"):
        mask = 0xFFFF if area == "D" else 0xFF
        client.memory[area] = {i: (i * 7919 + 13) & mask for i in range(1000)}
    client.memory["M"] = {i: bool((i * 31) % 3) for i in range(2048)}
    plan = build_plan(client, tags, max_gap=gap)
    replies = []
    for r in plan.requests:
        assert 1 <= r.count <= client.limits[str(r.area)]
        area, index = str(r.area), r.start
        mem = client.memory[area]
        replies.append([mem.get(index + k, 0) for k in range(r.count)])
    merged = plan.split(replies, order)
    alone = build_plan(client, tags, max_gap=gap, isolate=frozenset(t.name for t in tags))
    separate_replies = [
        [client.memory[str(r.area)].get(r.start + k, 0) for k in range(r.count)]
        for r in alone.requests
    ]
    separate = alone.split(separate_replies, order)
    # repr: a float32 bit pattern may be a NaN, which is not equal to itself
    assert [(r.tag.name, repr(r.value)) for r in merged] == [
        (r.tag.name, repr(r.value)) for r in separate
    ]
    assert len(plan.requests) <= len(alone.requests)


@settings(max_examples=200, deadline=None)
@given(
    dtype=st.sampled_from([t for t in PLAIN_TYPES if t is not vt.RAW]),
    bits=st.sampled_from([8, 16]),
    order=st.sampled_from([BIG, LITTLE]),
    data=st.data(),
)
def test_encode_decode_round_trip(
    dtype: vt.ValueType[Any], bits: int, order: WordOrder, data: st.DataObject
) -> None:
    if dtype is vt.BOOL:
        value: object = data.draw(st.booleans())
    elif dtype is vt.FLOAT32:
        value = data.draw(st.floats(width=32, allow_nan=False))
    else:
        n = dtype.bits
        lo, hi = (-(1 << (n - 1)), (1 << (n - 1)) - 1) if dtype.signed else (0, (1 << n) - 1)
        value = data.draw(st.integers(lo, hi))
    points = dtype.encode(value, bits, order)
    assert len(points) == dtype.points_per_value(bits)
    assert dtype.decode(points, bits, order) == value


VALUE_CASES = [
    # (type, point bits, order, points, value)
    (vt.INT16, 16, BIG, [0xFFFF], -1),
    (vt.UINT16, 16, BIG, [0xFFFF], 65535),
    (vt.INT32, 16, BIG, [0x0001, 0x0002], 0x00010002),
    (vt.INT32, 16, LITTLE, [0x0002, 0x0001], 0x00010002),
    (vt.INT32, 16, LITTLE, [0xFFFE, 0xFFFF], -2),
    (vt.INT16, 8, BIG, [0x12, 0x34], 0x1234),
    (vt.UINT32, 8, BIG, [0xDE, 0xAD, 0xBE, 0xEF], 0xDEADBEEF),
    (vt.FLOAT32, 16, BIG, [0x3FC0, 0x0000], 1.5),
    (vt.FLOAT32, 16, LITTLE, [0x0000, 0x3FC0], 1.5),
    (vt.INT8, 8, BIG, [0x80], -128),
    (vt.BOOL, 1, BIG, [True], True),
    (vt.BOOL, 16, BIG, [0], False),
]


@pytest.mark.parametrize(("dtype", "bits", "order", "points", "value"), VALUE_CASES)
def test_value_golden(
    dtype: vt.ValueType[Any], bits: int, order: WordOrder, points: list[int], value: object
) -> None:
    assert dtype.decode(points, bits, order) == value
    assert dtype.encode(value, bits, order) == points


@pytest.mark.parametrize(
    ("dtype", "value"),
    [
        (vt.INT16, 40000),
        (vt.UINT16, -1),
        (vt.INT16, 1.5),
        (vt.BOOL, 2),
        (vt.FLOAT32, "x"),
        (vt.FLOAT32, 1e39),
        (vt.INT32, True),
    ],
)
def test_encode_refuses_values_that_do_not_fit(dtype: vt.ValueType[Any], value: object) -> None:
    with pytest.raises(AddressError):
        dtype.encode(value, 16, BIG)


def test_float_nan_decodes() -> None:
    assert math.isnan(vt.FLOAT32.decode([0x7FC0, 0], 16, BIG))


def test_multi_bit_type_over_bool_points_is_a_bad_value_not_garbage() -> None:
    client = FakeClient(merge=False)  # no hooks: the plan cannot know M is a bit area
    plan = build_plan(client, [tag("x", "M0", "int16"), tag("ok", "M1", "bool")])
    bad, good = plan.split([[True], [False]], BIG)
    assert isinstance(bad.error, AddressError) and "bit area" in str(bad.error)
    assert good.value is False


@settings(max_examples=200, deadline=None)
@given(
    dtype=st.sampled_from(list(PLAIN_TYPES)),
    area=st.sampled_from(["D", "B"]),
    order=st.sampled_from([BIG, LITTLE]),
    data=st.data(),
)
def test_split_fast_paths_agree_with_value_by_value_decoding(
    dtype: vt.ValueType[Any], area: str, order: WordOrder, data: st.DataObject
) -> None:
    bits = 16 if area == "D" else 8
    assume(not (bits == 16 and dtype.bits == 8))  # 8-bit types on words are refused
    count = data.draw(st.integers(1, 20))
    n = dtype.points_per_value(bits)
    points = data.draw(
        st.lists(st.integers(0, (1 << bits) - 1), min_size=n * count, max_size=n * count)
    )
    plan = build_plan(FakeClient(), [tag("t", f"{area}0", dtype.name, count)])
    (result,) = plan.split([points], order)
    expected = [dtype.decode(points[i * n : (i + 1) * n], bits, order) for i in range(count)]
    assert repr(result.value) == repr(expected[0] if count == 1 else expected)
