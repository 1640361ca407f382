"""The history's encodings (plcstack/north/history/blocks.py) and its downsampling.

Golden bytes of a small block, round trips of every kind of value (Hypothesis), the widths that
make the cost per point (a 1 Hz REAL: 6 bytes), arbitrary bytes raising only BlockError, and the
downsampler's promises: at most N points, every peak of the range kept, gaps kept.
"""

from __future__ import annotations

import contextlib
import math
import struct
from array import array
from typing import Any

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from plcstack.north.history.blocks import (
    BAD,
    OTHER,
    BlockError,
    OpenBlock,
    decode_block,
    decode_segment,
    encode_block,
    encode_segment,
    kind_of,
)
from plcstack.north.history.downsample import Downsampler


def block_of(points: list[tuple[int, Any]]) -> OpenBlock:
    """An open block of ``(ms, value)`` points; None is a bad point."""
    block = OpenBlock(1)
    for t, v in points:
        if v is None:
            block.add(t, BAD, 0.0, None)
        else:
            kind, number = kind_of(v)
            block.add(t, kind, number, v)
    return block


def same(a: Any, b: Any) -> bool:
    """Equal, NaN equal to NaN, and of the same type (True is not 1)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float) and math.isnan(a):
        return math.isnan(b)
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return bool(a == b)


def test_golden_block_of_three_counter_points() -> None:
    # three points a second apart, a counter 100, 101, 103: uint16 steps, int8 steps
    t0 = 1_700_000_000_000
    first, last, data = encode_block(block_of([(t0, 100), (t0 + 1000, 101), (t0 + 2000, 103)]))
    assert (first, last) == (t0, t0 + 2000)
    expected = (
        bytes([1, 0x81, 3, 0]) + struct.pack("<II", 3, 0)  # version, uint16|sorted, int8, n, bad
        + struct.pack("<q", t0)  # the first time
        + struct.pack("<HH", 1000, 1000)  # time steps
        + struct.pack("<q", 100) + bytes([1, 2])  # first value, value steps
    )  # fmt: skip
    assert data == expected
    assert decode_block(t0, data) == ([t0, t0 + 1000, t0 + 2000], [100, 101, 103])


def test_a_real_polled_every_second_costs_six_bytes_a_point() -> None:
    t0 = 1_700_000_000_000
    reals = [struct.unpack("<f", struct.pack("<f", 20 + math.sin(i / 9)))[0] for i in range(600)]
    _, _, data = encode_block(block_of([(t0 + 1000 * i, v) for i, v in enumerate(reals)]))
    per_point = (len(data) - 24) / 600
    assert per_point == pytest.approx(6, abs=0.01)  # 2 bytes of time, 4 of float32
    doubles = [20 + math.sin(i / 9) for i in range(600)]  # a scaled value: float64
    _, _, data = encode_block(block_of([(t0 + 1000 * i, v) for i, v in enumerate(doubles)]))
    assert (len(data) - 24) / 600 == pytest.approx(10, abs=0.01)
    flags = [i % 7 == 0 for i in range(600)]
    _, _, data = encode_block(block_of([(t0 + 1000 * i, v) for i, v in enumerate(flags)]))
    assert (len(data) - 24) / 600 == pytest.approx(3, abs=0.01)


def test_bad_points_and_a_clock_set_back() -> None:
    t0 = 1_700_000_000_000
    points = [(t0, 5), (t0 + 1000, None), (t0 + 500, 7), (t0 + 200_000, 9)]
    first, last, data = encode_block(block_of(points))
    assert (first, last) == (t0, t0 + 200_000)
    times, values = decode_block(first, data)
    assert times == [t0, t0 + 500, t0 + 1000, t0 + 200_000]  # in time order
    assert values == [5, 7, None, 9]


values_of_one_kind = st.one_of(
    st.lists(st.booleans()),
    st.lists(st.integers(min_value=-(2**63) + 1, max_value=2**63 - 1)),
    st.lists(st.integers(min_value=-(2**70), max_value=2**70)),
    st.lists(st.floats(allow_nan=True, allow_infinity=True)),
    st.lists(st.floats(width=32)),
    st.lists(st.text(max_size=8)),
    st.lists(st.lists(st.integers(-5, 5) | st.floats(), max_size=3)),
    st.lists(st.integers(-3, 3) | st.floats(-1, 1) | st.booleans() | st.text(max_size=2)),
)


@given(
    values=values_of_one_kind.filter(bool),
    steps=st.lists(st.integers(min_value=-(2**40), max_value=2**40), min_size=200, max_size=200),
    bad=st.sets(st.integers(0, 199)),
    t0=st.integers(min_value=0, max_value=2**50),
)
def test_any_block_decodes_to_what_was_encoded(
    values: list[Any], steps: list[int], bad: set[int], t0: int
) -> None:
    points: list[tuple[int, Any]] = []
    t = t0
    for i, v in enumerate(values):
        points.append((t, None if i in bad else v))
        t += steps[i % len(steps)]
    first, last, data = encode_block(block_of(points))
    times, decoded = decode_block(first, data)
    expected = sorted(points, key=lambda p: p[0])
    assert (first, last) == (expected[0][0], expected[-1][0])
    assert times == [p[0] for p in expected]
    assert all(same(a, b[1]) for a, b in zip(decoded, expected, strict=True)), (decoded, expected)


@given(data=st.binary(max_size=200), t0=st.integers(0, 2**40))
def test_arbitrary_bytes_raise_only_block_error(data: bytes, t0: int) -> None:
    try:
        times, values = decode_block(t0, data)
    except BlockError:
        return
    assert len(times) == len(values)


@given(data=st.binary(max_size=200))
def test_arbitrary_segments_raise_only_block_error(data: bytes) -> None:
    with contextlib.suppress(BlockError):
        decode_segment(data)


def test_a_segment_round_trip() -> None:
    sids = array("I", [1, 2, 1, 3])
    times = array("q", [1000, 1005, 2000, 2001])
    kinds = bytearray([3, BAD, 3, OTHER])
    numbers = array("d", [1.5, 0.0, float("nan"), 0.0])
    data = encode_segment(sids, times, kinds, numbers, [["a", float("inf")]])
    points = decode_segment(data)
    assert [p[:3] for p in points] == [(1, 1000, 3), (2, 1005, BAD), (1, 2000, 3), (3, 2001, OTHER)]
    assert points[0][3] == 1.5 and math.isnan(points[2][3])
    assert points[3][4] == ["a", float("inf")]


def test_a_second_of_words_in_the_journal_costs_eleven_bytes_a_point() -> None:
    n = 10_000
    sids = array("I", range(n))
    times = array("q", [1_700_000_000_000 + i % 1000 for i in range(n)])
    numbers = array("d", [float(i % 30000) for i in range(n)])
    data = encode_segment(sids, times, bytearray([2] * n), numbers, [])
    assert (len(data) - 22) / n == 11  # 2 (series) + 4 (time) + 1 (kind) + 4 (float32)
    assert decode_segment(data)[1234] == (1234, 1_700_000_000_234, 2, 1234.0, None)


@given(
    points=st.lists(
        st.tuples(
            st.integers(0, 2**32 - 1),
            st.integers(-(2**50), 2**50),
            st.sampled_from([BAD, 1, 2, 3, OTHER]),
            st.floats(allow_nan=False) | st.floats(width=32, allow_nan=False),
        ),
        max_size=50,
    )
)
def test_any_segment_decodes_to_what_was_encoded(
    points: list[tuple[int, int, int, float]],
) -> None:
    others = [f"v{i}" for i, p in enumerate(points) if p[2] == OTHER]
    data = encode_segment(
        array("I", [p[0] for p in points]),
        array("q", [p[1] for p in points]),
        bytearray(p[2] for p in points),
        array("d", [p[3] for p in points]),
        others,
    )
    decoded = decode_segment(data)
    assert [d[:4] for d in decoded] == points
    assert [d[4] for d in decoded if d[2] == OTHER] == others


# -- downsampling --------------------------------------------------------------------------------
def test_few_points_come_back_as_they_are() -> None:
    sampler = Downsampler(0, 10_000, 10)
    sampler.add([1000, 2000], [1.5, None])
    sampler.before = (-5, 7)
    assert sampler.result() == [(-5, 7), (1000, 1.5), (2000, None)]


@given(
    values=st.lists(st.floats(-1e6, 1e6) | st.none(), min_size=1, max_size=3000),
    limit=st.integers(4, 200),
    chunk=st.integers(1, 500),
)
# every bucket with a gap besides its extremes: the extremes must still all be there
@example(values=[None, 0.0, None, None, 0.0, 1.0, None, 0.0, -1.0], limit=7, chunk=1)
def test_downsampling_keeps_every_peak_and_the_limit(
    values: list[float | None], limit: int, chunk: int
) -> None:
    times = [i * 10 for i in range(len(values))]
    sampler = Downsampler(0, times[-1], limit)
    for i in range(0, len(values), chunk):
        sampler.add(times[i : i + chunk], values[i : i + chunk])
    out = sampler.result()
    assert len(out) <= limit
    assert [t for t, _ in out] == sorted(t for t, _ in out)
    numbers = [v for v in values if v is not None]
    shown = [v for _, v in out if v is not None]
    if numbers:
        assert max(numbers) in shown and min(numbers) in shown
    if None in values and len(values) > limit - 1:
        assert None in [v for _, v in out]  # an offline stretch stays visible


def test_a_day_at_one_hertz_in_a_thousand_points_keeps_a_one_second_spike() -> None:
    day = 86_400
    values: list[float] = [20.0] * day
    values[43_210] = 95.0
    values[70_000] = -3.0
    sampler = Downsampler(0, (day - 1) * 1000, 1000)
    for i in range(0, day, 600):  # blocks of ten minutes
        sampler.add([t * 1000 for t in range(i, min(day, i + 600))], values[i : i + 600])
    out = sampler.result()
    assert len(out) <= 1000
    assert (43_210_000, 95.0) in out and (70_000_000, -3.0) in out


def test_text_keeps_the_first_and_last_of_each_bucket() -> None:
    sampler = Downsampler(0, 999, 5)  # two buckets
    sampler.add(list(range(0, 1000, 100)), [f"s{i}" for i in range(10)])
    assert sampler.result() == [(0, "s0"), (400, "s4"), (500, "s5"), (900, "s9")]
