"""Report-by-exception: deadbands, on change, max silence, quality changes, config rules."""

from __future__ import annotations

import math

import pytest

from plcstack.north.rbe import ReportByException, ReportPolicy, ReportRules, parse_report
from plcstack.poll.config import ConfigError
from tests.north_helpers import sample


def run(policy: ReportPolicy, values: list[object], dt: float = 1.0) -> list[object]:
    rbe = ReportByException(policy)
    out = []
    for i, v in enumerate(values):
        s = sample("p", "t", v, t=1000.0 + i * dt, error="down" if v == "ERR" else None)
        if rbe.accept(s):
            out.append(v)
    return out


RULES = (
    {"plc": "oven*", "tag": "temp", "deadband": 0.5},
    {"plc": "*", "tag": "raw*", "on_change": False},
)


def test_absolute_deadband_compares_with_the_last_reported_value() -> None:
    # a slow drift of 0.3 per scan is reported once it adds up beyond 0.5
    values = [10.0, 10.3, 10.6, 10.9, 11.2, 11.0, 9.0]
    assert run(ReportPolicy(deadband=0.5), values) == [10.0, 10.6, 11.2, 9.0]


def test_percent_deadband_scales_with_the_value() -> None:
    values = [1000.0, 1009.0, 1011.0, 10.0, 10.05, 10.2]
    assert run(ReportPolicy(deadband_percent=1.0), values) == [1000.0, 1011.0, 10.0, 10.2]


def test_on_change_and_pass_all() -> None:
    values = [1, 1, 2, 2, True, True, [1, 2], [1, 2], [1, 3]]
    assert run(ReportPolicy(), values) == [1, 2, True, [1, 2], [1, 3]]
    assert run(ReportPolicy(on_change=False), values) == values


def test_max_silence_sends_an_unchanged_value_anyway() -> None:
    assert run(ReportPolicy(max_silence=3.0), [5] * 8) == [5, 5, 5]  # t = 0, 3, 6


def test_quality_changes_and_new_errors_are_always_news() -> None:
    values = [5, "ERR", "ERR", 5, 5]
    assert run(ReportPolicy(deadband=100), values) == [5, "ERR", 5]
    rbe = ReportByException(ReportPolicy())
    assert rbe.accept(sample("p", "t", None, error="timeout"))
    assert not rbe.accept(sample("p", "t", None, error="timeout"))
    assert rbe.accept(sample("p", "t", None, error="refused"))


def test_nan_is_reported_once_not_every_scan() -> None:
    nan = math.nan
    assert len(run(ReportPolicy(deadband=1), [1.0, nan, nan, 1.0])) == 3


def test_rules_from_the_report_table() -> None:
    lookup = parse_report(
        {
            "max_silence": 60,
            "rule": [dict(r) for r in RULES],
        }
    )
    assert isinstance(lookup, ReportRules)  # compared by value: a reload sees no change
    assert lookup == parse_report({"max_silence": 60, "rule": [dict(r) for r in RULES]})
    assert lookup("oven2", "temp") == ReportPolicy(deadband=0.5, max_silence=60.0)
    assert lookup("press", "raw1") == ReportPolicy(on_change=False, max_silence=60.0)
    assert lookup("press", "temp") == ReportPolicy(max_silence=60.0)
    assert parse_report(None) == ReportPolicy(on_change=False)
    for bad, text in [
        ({"deadband": -1}, "deadband"),
        ({"max_silence": 0}, "max_silence"),
        ({"rule": [{"plc": 1}]}, "globs"),
        ({"speed": 1}, "unknown"),
        ({"on_change": "yes"}, "on_change"),
    ]:
        with pytest.raises(ConfigError, match=text):
            parse_report(bad)
