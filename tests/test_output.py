"""The printing rules of plcstack.output: float32 at float32 precision, NaN/inf in JSON."""

from __future__ import annotations

import json
import math
import struct

from hypothesis import given
from hypothesis import strategies as st

from plcstack.output import float32_short, json_safe


def _f32(x: float) -> float:
    value: float = struct.unpack("<f", struct.pack("<f", x))[0]
    return value


def test_float32_examples() -> None:
    assert float32_short(_f32(3.14)) == 3.14
    assert repr(float32_short(_f32(-2.5e3))) == "-2500.0"
    assert repr(float32_short(_f32(0.1))) == "0.1"
    assert float32_short(_f32(1e-40)) == 1e-40  # subnormal
    assert float32_short(0.1) == 0.1  # not a float32 value: unchanged
    assert float32_short(1e300) == 1e300
    assert math.isnan(float32_short(math.nan))


@given(st.floats(width=32, allow_nan=False, allow_infinity=False))
def test_float32_short_round_trips_and_is_shortest(x: float) -> None:
    short = float32_short(x)
    assert _f32(short) == x
    digits = len(repr(short).lstrip("-").split("e")[0].replace(".", "").strip("0"))
    if digits > 1:  # one digit fewer does not read back to the same float32
        assert _f32(float(f"{x:.{digits - 1}g}")) != x or short == x


def test_json_rule_for_non_finite() -> None:
    values = [1.5, math.nan, math.inf, -math.inf, (12, 255), "ab"]
    text = json.dumps(json_safe(values), allow_nan=False)
    assert text == '[1.5, "NaN", "Infinity", "-Infinity", [12, 255], "ab"]'
