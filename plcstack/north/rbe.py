"""Report-by-exception: pass on a tag's sample only when it says something new.

Applied once, between the poller and every sink (MQTT, Influx, OPC UA, stdout), so each sink
sees the same decisions. It filters each scan: a scan keeps the samples that are reported (the
same PLC, group and times), and a scan none of whose samples is reported is not passed on. Per
tag, a sample is reported when any of these holds:

* it is the tag's first sample, or its quality changed (good <-> bad), or a bad sample's error
  text changed (a PLC that goes from "timeout" to "refused" is news);
* a good value moved beyond the deadband from the *last reported* value (not the last polled one,
  so a slow drift is reported once it adds up): ``deadband`` is absolute, ``deadband_percent`` is
  a percentage of the last reported value's magnitude; with both 0, any change counts
  (``on_change``); for a list, any element counts; bools and a change of type always count;
* ``max_silence`` seconds (by sample time) have passed since the tag was last reported: the value
  goes out anyway, so a consumer can tell "unchanged" from "gone".

With ``on_change = false`` every sample is reported (a sink-level off switch). A NaN is compared
as "different from everything but NaN", so a register stuck at NaN is not reported every scan.

Memory: one small entry per configured tag (bounded by the configuration, not by traffic).
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from plcstack.checks import Table
from plcstack.errors import ConfigError, check_keys
from plcstack.poll.samples import Quality, Sample, Scan

__all__ = ["PASS_ALL", "Report", "ReportByException", "ReportPolicy", "ReportRules", "parse_report"]


@dataclass(frozen=True, slots=True)
class ReportPolicy:
    on_change: bool = True
    deadband: float = 0.0
    deadband_percent: float = 0.0
    max_silence: float | None = None


#: every sample reported: what a config without ``[report]`` gets
PASS_ALL = ReportPolicy(on_change=False)


@dataclass(slots=True)
class _Last:
    value: Any
    quality: Quality
    error: str | None
    time: float


def _moved(old: Any, new: Any, policy: ReportPolicy) -> bool:
    if type(old) is not type(new):
        return True
    if isinstance(new, list):
        return len(old) != len(new) or any(
            _moved(a, b, policy) for a, b in zip(old, new, strict=True)
        )
    if isinstance(new, bool) or not isinstance(new, int | float):
        return bool(old != new)
    if isinstance(new, float) and (math.isnan(new) or math.isnan(old)):
        return not (math.isnan(new) and math.isnan(old))
    if old == new:
        return False
    band = max(policy.deadband, abs(old) * policy.deadband_percent / 100.0)
    if band <= 0:
        return True
    diff = abs(new - old)
    return not math.isfinite(diff) or diff > band


class ReportByException:
    """Filters samples per tag by its :class:`ReportPolicy` (see the module docstring)."""

    def __init__(
        self,
        policy: ReportPolicy
        | Mapping[tuple[str, str], ReportPolicy]
        | Callable[[str, str], ReportPolicy],
    ) -> None:
        self._policy_of = policy
        self._policies: dict[tuple[str, str], ReportPolicy] = {}
        self._last: dict[tuple[str, str], _Last] = {}
        self.passed = 0
        self.suppressed = 0

    def policy(self, plc: str, tag: str) -> ReportPolicy:
        key = (plc, tag)
        p = self._policies.get(key)
        if p is None:
            source = self._policy_of
            if isinstance(source, ReportPolicy):
                p = source
            elif isinstance(source, Mapping):
                p = source.get(key, PASS_ALL)
            else:
                p = source(plc, tag)
            self._policies[key] = p
        return p

    def accept(self, s: Sample) -> bool:
        """Whether ``s`` is reported; updates the tag's state when it is."""
        key = (s.plc, s.tag)
        policy = self.policy(s.plc, s.tag)
        last = self._last.get(key)
        report = (
            not policy.on_change
            or last is None
            or last.quality is not s.quality
            or (policy.max_silence is not None and s.source_time - last.time >= policy.max_silence)
            or (s.quality is Quality.BAD and last.error != s.error)
            or (s.quality is Quality.GOOD and _moved(last.value, s.value, policy))
        )
        if report:
            self.passed += 1
            if policy.on_change:
                self._last[key] = _Last(s.value, s.quality, s.error, s.source_time)
        else:
            self.suppressed += 1
        return report

    def forget(self, plcs: Collection[str]) -> None:
        """Drop what is kept of the tags of ``plcs`` (removed or changed by a reload): their
        next samples are reported as the first ones are."""
        if not plcs:
            return
        for kept in (self._last, self._policies):
            for key in [k for k in kept if k[0] in plcs]:
                del kept[key]

    def filter(self, scans: Iterable[Scan]) -> list[Scan]:
        """The scans with only their reported samples; a scan with none is left out, a scan
        with all of them is passed on as it is."""
        out: list[Scan] = []
        accept = self.accept
        for scan in scans:
            samples = scan.samples
            kept = tuple(s for s in samples if accept(s))
            if len(kept) == len(samples):
                out.append(scan)
            elif kept:
                out.append(scan.with_samples(kept))
        return out


def _policy(table: Mapping[str, Any], base: ReportPolicy, where: str) -> ReportPolicy:
    allowed = {"on_change", "deadband", "deadband_percent", "max_silence", "plc", "tag"}
    check_keys(table, allowed, "report" if where == "[report]" else "report.rule", where=where)
    values: dict[str, Any] = {
        "on_change": base.on_change,
        "deadband": base.deadband,
        "deadband_percent": base.deadband_percent,
        "max_silence": base.max_silence,
    }
    for key in ("deadband", "deadband_percent", "max_silence"):
        if key in table:
            v = table[key]
            if (
                isinstance(v, bool)
                or not isinstance(v, int | float)
                or not math.isfinite(v)
                or v < 0
            ):
                raise ConfigError(f"{where}: {key} must be a number >= 0, got {v!r}")
            values[key] = float(v)
    if "max_silence" in table and values["max_silence"] == 0:
        raise ConfigError(f"{where}: max_silence must be greater than 0")
    if "on_change" in table:
        if not isinstance(table["on_change"], bool):
            raise ConfigError(f"{where}: on_change must be true or false")
        values["on_change"] = table["on_change"]
    return ReportPolicy(**values)


@dataclass(frozen=True, slots=True)
class ReportRules:
    """``[[report.rule]]``s: the first rule whose globs match a tag gives its policy, else
    ``base`` (the ``[report]`` table's own keys). Compared by value, so a reload can tell
    whether the table changed."""

    base: ReportPolicy
    #: (plc glob, tag glob, policy), in the file's order
    rules: tuple[tuple[str, str, ReportPolicy], ...]

    def __call__(self, plc: str, tag: str) -> ReportPolicy:
        for plc_glob, tag_glob, policy in self.rules:
            if fnmatch.fnmatchcase(plc, plc_glob) and fnmatch.fnmatchcase(tag, tag_glob):
                return policy
        return self.base


#: what ``[report]`` sets: one policy for every tag, or rules
Report = ReportPolicy | ReportRules


def parse_report(table: object) -> Report:
    """The ``[report]`` table -> one policy, or rules ``(plc, tag) -> ReportPolicy``.

    ```toml
    [report]                     # defaults for every tag
    deadband = 0.0
    max_silence = 60
    [[report.rule]]              # first matching rule wins; plc and tag are shell globs
    plc = "oven*"
    tag = "temperature"
    deadband = 0.5
    ```

    Without a ``[report]`` table every sample is reported.
    """
    if table is None:
        return PASS_ALL
    values = Table.of(table, "report").values
    rules_raw = values.get("rule", [])
    base = _policy({k: v for k, v in values.items() if k != "rule"}, ReportPolicy(), "[report]")
    if not isinstance(rules_raw, list):
        raise ConfigError("[report] rule must be an array of tables ([[report.rule]])")
    rules: list[tuple[str, str, ReportPolicy]] = []
    for i, rule in enumerate(rules_raw):
        where = f"[[report.rule]] #{i + 1}"
        if not isinstance(rule, Mapping):
            raise ConfigError(f"{where} must be a table")
        plc, tag = rule.get("plc", "*"), rule.get("tag", "*")
        if not isinstance(plc, str) or not isinstance(tag, str):
            raise ConfigError(f"{where}: plc and tag must be strings (shell globs)")
        rules.append((plc, tag, _policy(rule, base, where)))
    if not rules:
        return base
    return ReportRules(base, tuple(rules))
