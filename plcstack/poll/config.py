"""The poller's configuration: PLCs, scan groups and tags, from TOML or built in Python.

```toml
[poll]
concurrency = 32        # optional cap on requests in flight across all PLCs (default: none;
                        # a scan that finds every slot taken waits its turn in a task)
queue = 10000           # samples held for a slow consumer; beyond that the oldest are dropped
batch_wait = 0.01       # seconds a batch for the north side gathers after its first sample
max_gap = 8             # unused points one merged request may carry between two tags
timeout = 2.0           # request deadline in seconds (a URL's ?timeout= wins)
connect_timeout = 3.0
backoff_max = 30.0      # longest wait between reconnect attempts to a dead PLC (seconds)
interval = 1.0          # interval of the scan group "default" (at least 0.001 s)

[groups]                # more scan groups: name = interval in seconds
fast = 0.1

[[plc]]
name = "press1"
url = "e71+tcp://10.0.0.5:5000"
group = "fast"          # scan group of this PLC's tags unless a tag names one
word_order = "little"   # int32/float32 point order; default: little for E71, big for S5
max_gap = 4

[plc.tags]
counter = "D100"                                          # type raw, count 1
temp = { address = "D102", type = "float32", group = "default" }
alarms = { address = "M0", type = "bool", count = 16 }
level = { address = "D110", type = "int16", scale = [0, 4000, 0.0, 100.0], unit = "%" }
door = { address = "D120.3", type = "bool" }              # bit 3 of D120 (S5: "DB10.DW5.3")
setpoint = { address = "D130", type = "int16", writable = true }   # north-side servers may write
pump = { address = "M10", type = "bool", description = "Feed pump 2 running" }
valve = { address = "M11", type = "bool", labels = ["closed", "open"] }   # shown as the words
mode = { address = "D140", type = "int16", labels = { 0 = "stopped", 1 = "running" } }
flow = { address = "D150", type = "float32", unit = "m³/h", decimals = 1 }
```

Tag types are the value types of :mod:`plcstack.values` by name (``int16``, ``float32``, ``kg``,
``kt``, ``bcd16``, ``string:10``, ...). ``scale = [raw_lo, raw_hi, eng_lo, eng_hi]`` maps a number
linearly onto engineering units (writes map back). ``description`` is free text for people (the
OPC UA Description attribute, a Sparkplug metric property, the web console); the poller ignores it,
as it ignores ``decimals`` and ``labels`` (how the web console shows a value: see
:mod:`plcstack.poll.display`).

Other top-level tables (``[opcua]``, ``[mqtt]``, ``[metrics]``, ``[report]``, ``[influx]``,
``[web]``, ``[modbus]``) belong to the north side, which parses them itself: this module checks
that they are tables and hands them to the parser its caller gives
(``plcstack.north.config.load_config`` reads the file once for both layers).

Every problem is a :class:`ConfigError` naming the PLC, the tag and, where it can be found, the
TOML line, so a typo in a 500-PLC file is found at once and before anything is sent.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from plcstack.errors import AddressError, ConfigError, unknown_names
from plcstack.poll.display import Labels, decimals_problem, labels_problem, parse_labels
from plcstack.url import parse_url
from plcstack.values import (
    RAW,
    TYPES,
    ByteOrder,
    Scale,
    ValueType,
    WordOrder,
    default_byte_order,
    default_word_order,
    value_type,
)

__all__ = [
    "MIN_INTERVAL",
    "ConfigError",
    "PlcConfig",
    "PollConfig",
    "TagConfig",
    "load_config",
    "parse_config",
    "toml_line",
]

DEFAULT_GROUP = "default"
DEFAULT_INTERVAL = 1.0
#: shortest scan interval (seconds). A scan is at least one request per PLC; below a millisecond
#: the "interval" only measures how fast a dead PLC can be turned into bad samples (1e-300 gave
#: 15,000 a second of them), never how fast a PLC answers.
MIN_INTERVAL = 0.001
#: deepest nesting of tables and arrays a config may use; ours needs 4 ([[plc]] > tags > tag)
MAX_TOML_DEPTH = 32
#: no global cap by default: each PLC already has one request in flight at most, and a cap lets
#: a crowd of dead or slow PLCs (each holding a slot for a whole timeout) delay the healthy ones
DEFAULT_CONCURRENCY: int | None = None
DEFAULT_QUEUE = 10_000
#: how long the north side's batch gathers after its first scan (``Poller.scans(wait=)``):
#: with a thousand PLCs a wake-up per loop pass cost the consumer more than the requests did
#: (about 9 us per request); 10 ms is nothing against a historian's or a broker's
#: pace, and each sample keeps its own times
DEFAULT_BATCH_WAIT = 0.01
#: the longest batch_wait taken: more only fills the buffer (and delays every sample)
MAX_BATCH_WAIT = 1.0
DEFAULT_MAX_GAP = 8
#: top-level tables read by north-side servers from the same file (plcstack.north)
NORTH_SECTIONS = (
    "opcua", "mqtt", "metrics", "report", "influx", "web", "modbus", "audit", "history", "trace",
)  # fmt: skip


@dataclass(frozen=True)
class TagConfig:
    """One tag: ``count`` values of ``type`` starting at ``address``, scanned in ``group``.

    ``address`` may name a bit of a word (``D100.3``, ``DB10.DW5.3``) for ``type`` bool; such a
    tag is read-only (writing one bit of a word would be a read-modify-write that races the PLC).
    ``scale`` maps the raw number linearly onto engineering units (the sample carries a float).
    """

    name: str
    address: str
    type: ValueType[Any] = RAW
    count: int = 1
    group: str = DEFAULT_GROUP
    scale: Scale | None = None
    #: whether north-side servers (OPC UA) may write this tag; the Python API's ``write_tag`` is
    #: not limited by it (the program that owns the poller decides for itself)
    writable: bool = False
    #: engineering unit of the value (``"°C"``, ``"bar"``), for north-side servers (OPC UA
    #: EngineeringUnits); the poller itself does not use it
    unit: str | None = None
    #: what the tag means, for people (``"Feed pump 2 running"``): north-side servers show it
    #: (OPC UA Description, a Sparkplug metric property, the web console); tag lists imported
    #: from engineering tools carry it; the poller itself does not use it
    description: str | None = None
    #: where the Modbus server serves the tag (``"hr:100"``, ``"ir:0"``, ``"co:5"``, ``"di:0"``;
    #: see plcstack.north.modbus); the poller itself does not use it
    modbus: str | None = None
    #: digits after the point when people see the value (plcstack.poll.display)
    decimals: int | None = None
    #: names of the states of a bool or integer tag, ``((0, "stopped"), (1, "running"))``
    labels: Labels | None = None
    #: the tag's line in the TOML file, when a north side's errors about it need one (a tag
    #: with a ``modbus`` key); None for tags built in Python
    line: int | None = field(default=None, compare=False)


@dataclass(frozen=True)
class PlcConfig:
    """One PLC: its URL, its tags and how to poll it."""

    name: str
    url: str
    tags: tuple[TagConfig, ...]
    max_gap: int = DEFAULT_MAX_GAP
    word_order: WordOrder | None = None
    timeout: float | None = None
    connect_timeout: float | None = None
    #: cap of the reconnect backoff (None: the client's default, 30 s)
    backoff_max: float | None = None

    @property
    def order(self) -> WordOrder:
        if self.word_order is not None:
            return self.word_order
        return default_word_order(parse_url(self.url).scheme)

    @property
    def byte_order(self) -> ByteOrder:
        """Order of the characters in a word (text types): the PLC family's."""
        return default_byte_order(parse_url(self.url).scheme)


@dataclass(frozen=True)
class PollConfig:
    """Everything the :class:`~plcstack.poll.engine.Poller` needs."""

    plcs: tuple[PlcConfig, ...]
    groups: Mapping[str, float] = field(default_factory=lambda: {DEFAULT_GROUP: DEFAULT_INTERVAL})
    concurrency: int | None = DEFAULT_CONCURRENCY
    queue: int = DEFAULT_QUEUE
    #: the north side's tables ([mqtt], [opcua], ...) as read from the TOML, parsed by the
    #: north side (``plcstack.north.config``)
    north: Mapping[str, Any] = field(default_factory=dict, compare=False)
    #: seconds the north side's batches gather (see :data:`DEFAULT_BATCH_WAIT`)
    batch_wait: float = DEFAULT_BATCH_WAIT
    #: the file it was read from (``file:line`` in the north side's errors); None if built in
    #: Python
    source: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        validate(self)


# -- validation shared by TOML and Python-built configs --------------------------------------


def batch_wait_problem(wait: object) -> str | None:
    """What is wrong with a ``batch_wait`` value, or None: the one rule, for the TOML loader
    (which adds the file and line) and for configs built in Python."""
    if (
        isinstance(wait, bool)
        or not isinstance(wait, int | float)
        or not (0 <= wait <= MAX_BATCH_WAIT)
    ):
        return (
            f"poll.batch_wait must be a number of seconds from 0 to {MAX_BATCH_WAIT:g}, "
            f"not {wait!r}"
        )
    return None


#: longest tag description taken: a paragraph, not a manual (OPC UA clients show it in one line)
MAX_DESCRIPTION = 1024


def text_problem(key: str, value: object) -> str | None:
    """What is wrong with a tag's free-text field (``description``), or None: the one rule for
    the TOML loader and for configs built in Python. Control characters other than tab are
    refused so the text prints on one line in logs, CSV and the OPC UA browse tree."""
    if value is None:
        return None
    if not isinstance(value, str) or not value.strip():
        return f"{key} must be a non-empty string, not {value!r}"
    if len(value) > MAX_DESCRIPTION:
        return f"{key} must be at most {MAX_DESCRIPTION} characters, not {len(value)}"
    bad = next((c for c in value if (ord(c) < 32 and c != "\t") or ord(c) == 127), None)
    if bad is not None:
        return f"{key} must not contain control characters (found {bad!r})"
    return None


def validate(config: PollConfig) -> None:
    """Check a config built in Python the same way the TOML loader does."""
    if config.concurrency is not None and config.concurrency < 1:
        raise ConfigError("poll.concurrency must be at least 1")
    if config.queue < 1:
        raise ConfigError("poll.queue must be at least 1")
    problem = batch_wait_problem(config.batch_wait)
    if problem:
        raise ConfigError(problem)
    for name, interval in config.groups.items():
        if not (
            isinstance(interval, int | float)
            and math.isfinite(interval)
            and interval >= MIN_INTERVAL
        ):
            raise ConfigError(
                f"scan group {name!r}: interval must be a number of seconds "
                f"of at least {MIN_INTERVAL:g}, not {interval!r}"
            )
    seen: set[str] = set()
    for plc in config.plcs:
        if plc.name in seen:
            raise ConfigError(f"PLC name {plc.name!r} is used twice", plc=plc.name)
        seen.add(plc.name)
        try:
            parse_url(plc.url)
        except AddressError as exc:
            raise ConfigError(f"bad url: {exc}", plc=plc.name) from None
        if plc.max_gap < 0:
            raise ConfigError("max_gap must be 0 or more", plc=plc.name)
        for name in ("timeout", "connect_timeout", "backoff_max"):
            value = getattr(plc, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be greater than 0", plc=plc.name)
        tag_names: set[str] = set()
        for tag in plc.tags:
            where = f"tag {tag.name!r}"
            if tag.name in tag_names:
                raise ConfigError(f"{where} is defined twice", plc=plc.name)
            tag_names.add(tag.name)
            if tag.count < 1:
                raise ConfigError(f"{where}: count must be at least 1", plc=plc.name)
            if not isinstance(tag.type, ValueType):
                raise ConfigError(f"{where}: type must be a ValueType", plc=plc.name)
            if tag.scale is not None and tag.type.kind not in ("int", "float"):
                raise ConfigError(
                    f"{where}: scale needs a numeric type, not {tag.type.name}", plc=plc.name
                )
            problem = (
                text_problem("description", tag.description)
                or decimals_problem(tag.decimals)
                or labels_problem(tag.labels, tag.type)
            )
            if problem:
                raise ConfigError(f"{where}: {problem}", plc=plc.name)
            if tag.group not in config.groups:
                raise ConfigError(
                    f"{where}: unknown scan group {tag.group!r} "
                    f"(groups: {', '.join(sorted(config.groups))})",
                    plc=plc.name,
                )


# -- TOML ---------------------------------------------------------------------------------------


#: a parser of the tables another layer owns (``[mqtt]``, ``[opcua]``, ...), given them as read
#: from the file; raises :class:`ConfigError`, which the loader points at the table's line
TablesParser = Callable[[Mapping[str, Any]], object]


def load_config(path: str | Path, *, tables: TablesParser | None = None) -> PollConfig:
    """Read and validate a TOML file (once): the poll tables here; the other layers' tables
    are checked to be tables and handed to ``tables`` (the north side's parser:
    ``plcstack.north.config.load_config`` reads a file for both)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from None
    return parse_config(text, source=str(path), tables=tables)


def parse_config(
    text: str, *, source: str = "<config>", tables: TablesParser | None = None
) -> PollConfig:
    """Parse and validate TOML text; errors name the PLC, the tag and the line if found.
    ``tables``: see :func:`load_config`."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:
        # tomllib recurses per nesting level; 500 levels escaped as a traceback (exit 1)
        raise ConfigError(
            f"{source}: tables or arrays nested too deeply to parse (a poll config needs 4 levels)"
        ) from None
    if _depth(data) > MAX_TOML_DEPTH:
        raise ConfigError(
            f"{source}: tables or arrays nested more than {MAX_TOML_DEPTH} deep "
            "(a poll config needs 4 levels)"
        )
    return _Loader(text, source).load(data, tables)


def toml_line(lines: Sequence[str], path: str) -> int | None:
    """The 1-based line of a dotted top-level TOML path (``"opcua.endpiont"``, ``"mqt"``,
    ``"report.rule.x"``) in a file's lines: the first ``key =`` line or ``[table]`` /
    ``[[table]]`` header that names it exactly, else the one that names the longest part of it
    (the table of an unknown key, or the line that opens an inline table). tomllib keeps no
    positions; every table's "unknown key" error (:class:`ConfigError` ``key``) is pointed at
    its line with this."""
    want = _toml_path(path)
    best, best_len = None, 0
    table: list[str] = []
    for i, line in enumerate(lines):
        if header := re.match(r"\s*\[\[?([^\[\]]+)\]\]?\s*(?:#.*)?$", line):
            table = _toml_path(header.group(1))
            names = table
        elif key := re.match(r"\s*([\w\-\s.\"']+?)\s*=", line):
            names = table + _toml_path(key.group(1))
        else:
            continue
        if names == want:
            return i + 1
        common = len(names) if want[: len(names)] == names else 0
        if common > best_len:
            best, best_len = i + 1, common
    return best


def _toml_path(dotted: str) -> list[str]:
    """``'a . "b" . c'`` -> ``["a", "b", "c"]`` (a dot inside quotes is rare enough to ignore)."""
    return [part.strip().strip("\"'") for part in dotted.split(".")]


def _depth(value: Any) -> int:
    """Nesting depth of parsed TOML, without recursion (so any depth tomllib accepted is safe)."""
    deepest = 0
    stack: list[tuple[Any, int]] = [(value, 1)]
    while stack:
        item, level = stack.pop()
        if isinstance(item, dict):
            children: Any = item.values()
        elif isinstance(item, list):
            children = item
        else:
            continue
        deepest = max(deepest, level)
        if level <= MAX_TOML_DEPTH:  # one level beyond the limit is enough to refuse
            stack.extend((child, level + 1) for child in children)
    return deepest


class _Loader:
    def __init__(self, text: str, source: str) -> None:
        self.lines = text.splitlines()
        self.source = source
        self.plc_index = -1
        self.plc_name: str | None = None

    # Where in the file: tomllib keeps no positions, so find the line by its key, searching only
    # inside the current [[plc]] section. Good enough to point a person at the right place.
    def _line_of(self, key: str | None) -> int | None:
        starts = [i for i, line in enumerate(self.lines) if re.match(r"\s*\[\[\s*plc\s*\]\]", line)]
        if self.plc_index < 0 or self.plc_index >= len(starts):
            lo, hi = 0, len(self.lines)
        else:
            lo = starts[self.plc_index]
            hi = starts[self.plc_index + 1] if self.plc_index + 1 < len(starts) else len(self.lines)
        if key is None:
            return lo + 1 if self.plc_index >= 0 else None
        pattern = re.compile(r'\s*(?:["\']?' + re.escape(key) + r'["\']?)\s*=')
        for i in range(lo, hi):
            if pattern.match(self.lines[i]):
                return i + 1
        return lo + 1 if self.plc_index >= 0 else None

    def error(
        self, message: str, key: str | None = None, *, path: str | None = None
    ) -> ConfigError:
        """A ConfigError with ``(file:line)``; the line is that of ``key`` in the current
        [[plc]] section, or of the dotted top-level ``path``."""
        line = toml_line(self.lines, path) if path is not None else self._line_of(key)
        where = f"{self.source}:{line}" if line else self.source
        return ConfigError(f"{message} ({where})", plc=self.plc_name)

    def _number(self, table: Mapping[str, Any], key: str, default: float, what: str) -> float:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(f"{what} {key} must be a number, not {value!r}", key)
        if not (math.isfinite(value) and value > 0):
            raise self.error(f"{what} {key} must be greater than 0, got {value!r}", key)
        is_interval = what.endswith("interval") or (what == "poll" and key == "interval")
        if is_interval and value < MIN_INTERVAL:
            raise self.error(
                f"{what} {key} must be at least {MIN_INTERVAL:g} s (the documented lower "
                f"bound for scan intervals), got {value!r}",
                key,
            )
        return float(value)

    def _int(self, table: Mapping[str, Any], key: str, default: int, lo: int, what: str) -> int:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(f"{what} {key} must be an integer, not {value!r}", key)
        if value < lo:
            raise self.error(f"{what} {key} must be at least {lo}, got {value}", key)
        return value

    @staticmethod
    def _unknown(table: Mapping[str, Any], allowed: set[str]) -> list[str]:
        return sorted(set(table) - allowed)

    def _check_keys(
        self, table: Mapping[str, Any], allowed: set[str], where: str, line_key: str | None = None
    ) -> None:
        """Every key of ``table`` is one of ``allowed``; else the error names each unknown key
        with the allowed one it is closest to (``adress (did you mean address?)``)."""
        unknown = self._unknown(table, allowed)
        if unknown:
            names = unknown_names(unknown, allowed)
            raise self.error(f"{where}unknown key(s) {names}", line_key or unknown[0])

    def load(self, data: dict[str, Any], tables: TablesParser | None) -> PollConfig:
        top = {"poll", "groups", "plc", *NORTH_SECTIONS}
        unknown = self._unknown(data, top)
        if unknown:
            raise self.error(
                f"unknown top-level key(s) {unknown_names(unknown, top)}; expected poll, groups,"
                f" plc or {', '.join(NORTH_SECTIONS)}",
                path=unknown[0],
            )
        for section in NORTH_SECTIONS:
            if section in data and not isinstance(data[section], dict):
                raise self.error(f"[{section}] must be a table", path=section)
        # the other layers' tables ([mqtt], [opcua], ...): parsed by their owner now, when it
        # is given, so a typo stops before any send, with the line of its table
        north = {key: data[key] for key in NORTH_SECTIONS if key in data}
        if tables is not None:
            try:
                tables(north)
            except ConfigError as exc:
                raise self.error(exc.message, path=exc.key or next(iter(north))) from None
        poll = data.get("poll", {})
        if not isinstance(poll, dict):
            raise self.error("[poll] must be a table", "poll")
        self._check_keys(
            poll,
            {
                "concurrency",
                "queue",
                "batch_wait",
                "max_gap",
                "timeout",
                "connect_timeout",
                "backoff_max",
                "interval",
            },
            "[poll]: ",
        )
        concurrency = (
            self._int(poll, "concurrency", 1, 1, "poll")
            if "concurrency" in poll
            else DEFAULT_CONCURRENCY
        )
        queue = self._int(poll, "queue", DEFAULT_QUEUE, 1, "poll")
        batch_wait = poll.get("batch_wait", DEFAULT_BATCH_WAIT)
        problem = batch_wait_problem(batch_wait)
        if problem:
            raise self.error(problem, "batch_wait")
        max_gap = self._int(poll, "max_gap", DEFAULT_MAX_GAP, 0, "poll")
        timeout = self._number(poll, "timeout", 2.0, "poll") if "timeout" in poll else None
        connect_timeout = (
            self._number(poll, "connect_timeout", 3.0, "poll")
            if "connect_timeout" in poll
            else None
        )
        backoff_max = (
            self._number(poll, "backoff_max", 30.0, "poll") if "backoff_max" in poll else None
        )
        groups: dict[str, float] = {
            DEFAULT_GROUP: self._number(poll, "interval", DEFAULT_INTERVAL, "poll")
        }
        raw_groups = data.get("groups", {})
        if not isinstance(raw_groups, dict):
            raise self.error("[groups] must be a table of name = interval (seconds)", "groups")
        for name in raw_groups:
            groups[name] = self._number(raw_groups, name, 0, f"scan group {name!r}: interval")
        raw_plcs = data.get("plc", [])
        if not isinstance(raw_plcs, list):
            raise self.error("plc must be an array of tables: write [[plc]]", "plc")
        plcs: list[PlcConfig] = []
        names: set[str] = set()
        for index, raw in enumerate(raw_plcs):
            self.plc_index = index
            self.plc_name = None
            plc = self._plc(raw, groups, max_gap, timeout, connect_timeout, backoff_max)
            if plc.name in names:
                raise self.error(f"PLC name {plc.name!r} is used twice", "name")
            names.add(plc.name)
            plcs.append(plc)
        self.plc_index, self.plc_name = -1, None
        if not plcs:
            raise self.error("no PLC configured: add a [[plc]] table with name, url and tags")
        return PollConfig(
            tuple(plcs), groups, concurrency, queue, north, batch_wait, source=self.source
        )

    def _plc(
        self,
        raw: Any,
        groups: Mapping[str, float],
        max_gap: int,
        timeout: float | None,
        connect_timeout: float | None,
        backoff_max: float | None,
    ) -> PlcConfig:
        if not isinstance(raw, dict):
            raise self.error("each [[plc]] must be a table")
        url = raw.get("url")
        name = raw.get("name", url)
        if not isinstance(name, str) or not name:
            raise self.error("PLC name must be a non-empty string", "name")
        self.plc_name = name
        if not isinstance(url, str):
            raise self.error('missing url (e.g. url = "e71+tcp://10.0.0.5:5000")', "url")
        self._check_keys(
            raw,
            {
                "name",
                "url",
                "group",
                "tags",
                "max_gap",
                "word_order",
                "timeout",
                "connect_timeout",
                "backoff_max",
            },
            "",
        )
        try:
            parse_url(url)
        except AddressError as exc:
            raise self.error(f"bad url: {exc.message}", "url") from None
        group = raw.get("group", DEFAULT_GROUP)
        if group not in groups:
            raise self.error(
                f"unknown scan group {group!r} (groups: {', '.join(sorted(groups))})", "group"
            )
        order: WordOrder | None = None
        if "word_order" in raw:
            try:
                order = WordOrder(raw["word_order"])
            except ValueError:
                raise self.error(
                    f'word_order must be "big" or "little", not {raw["word_order"]!r}',
                    "word_order",
                ) from None
        plc_timeout = self._number(raw, "timeout", 0, "") if "timeout" in raw else timeout
        plc_connect = (
            self._number(raw, "connect_timeout", 0, "")
            if "connect_timeout" in raw
            else connect_timeout
        )
        raw_tags = raw.get("tags")
        if isinstance(raw_tags, list):  # [[plc.tags]]: one bracket pair too many
            raise self.error(
                "tags is an array of tables ([[plc.tags]]); write one table [plc.tags] "
                'with a line per tag: name = { address = "ADDRESS", type = "TYPE" }',
                "tags",
            )
        if not isinstance(raw_tags, dict) or not raw_tags:
            raise self.error('no tags: add a [plc.tags] table (name = "ADDRESS")', "tags")
        tags = tuple(
            self._tag(tag_name, spec, group, groups) for tag_name, spec in raw_tags.items()
        )
        self._refuse_writable_bits(url, tags)
        return PlcConfig(
            name=name,
            url=url,
            tags=tags,
            max_gap=self._int(raw, "max_gap", max_gap, 0, ""),
            word_order=order,
            timeout=plc_timeout,
            connect_timeout=plc_connect,
            backoff_max=(
                self._number(raw, "backoff_max", 0, "") if "backoff_max" in raw else backoff_max
            ),
        )

    def _refuse_writable_bits(self, url: str, tags: tuple[TagConfig, ...]) -> None:
        """A bit of a word (``D100.3``) is never written (a read-modify-write of the word would
        race the PLC program), so ``writable = true`` on one is refused here, naming the tag,
        rather than announced to north-side clients and refused at every write."""
        writable = [t for t in tags if t.writable]
        if not writable:
            return
        from plcstack.clients.connect import connect  # the family's bit notation

        try:
            client = connect(url)
        except AddressError:
            return  # the poller reports a URL it cannot use, with the reason
        for tag in writable:
            try:
                _, bit = client.split_bit(tag.address)
            except AddressError:
                continue  # the poller reports the address, with the reason
            if bit is not None:
                raise self.error(
                    f"tag {tag.name!r}: writable = true on a bit of a word ({tag.address}):"
                    " a bit of a word is read-only, since writing one bit of a word would be a"
                    " read-modify-write racing the PLC program; remove writable or write the"
                    " whole word through a tag of its own",
                    tag.name,
                )

    def _tag(self, name: str, spec: Any, group: str, groups: Mapping[str, float]) -> TagConfig:
        where = f"tag {name!r}"
        if not name.strip():
            raise self.error("a tag name must not be empty", "tags")
        if isinstance(spec, str):
            spec = {"address": spec}
        if not isinstance(spec, dict):
            raise self.error(
                f'{where}: expected "ADDRESS" or {{ address = ..., type = ..., count = ... }}',
                name,
            )
        self._check_keys(
            spec,
            {
                "address",
                "type",
                "count",
                "group",
                "scale",
                "writable",
                "unit",
                "description",
                "modbus",
                "decimals",
                "labels",
            },
            f"{where}: ",
            name,
        )
        address = spec.get("address")
        if not isinstance(address, str) or not address.strip():
            raise self.error(f"{where}: missing address", name)
        type_name = spec.get("type", "raw")
        try:
            dtype = value_type(type_name)
        except AddressError:
            raise self.error(
                f"{where}: unknown type {type_name!r} "
                f"(types: {', '.join(TYPES)}, string:N[:space])",
                name,
            ) from None
        scale: Scale | None = None
        if "scale" in spec:
            raw_scale = spec["scale"]
            if not isinstance(raw_scale, list) or len(raw_scale) != 4:
                raise self.error(
                    f"{where}: scale must be [raw_lo, raw_hi, eng_lo, eng_hi], not {raw_scale!r}",
                    name,
                )
            try:
                scale = Scale(*raw_scale)
            except AddressError as exc:
                raise self.error(f"{where}: {exc.message}", name) from None
            if dtype.kind not in ("int", "float"):
                raise self.error(f"{where}: scale needs a numeric type, not {dtype.name}", name)
        count = spec.get("count", 1)
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise self.error(f"{where}: count must be a positive integer, not {count!r}", name)
        tag_group = spec.get("group", group)
        if tag_group not in groups:
            raise self.error(
                f"{where}: unknown scan group {tag_group!r} (groups: {', '.join(sorted(groups))})",
                name,
            )
        writable = spec.get("writable", False)
        if not isinstance(writable, bool):
            raise self.error(f"{where}: writable must be true or false, not {writable!r}", name)
        unit = spec.get("unit")
        if unit is not None and (not isinstance(unit, str) or not unit.strip()):
            raise self.error(f"{where}: unit must be a non-empty string, not {unit!r}", name)
        description = spec.get("description")
        decimals = spec.get("decimals")
        problem = text_problem("description", description) or decimals_problem(decimals)
        if problem:
            raise self.error(f"{where}: {problem}", name)
        try:
            labels = None if "labels" not in spec else parse_labels(spec["labels"], dtype)
        except ValueError as exc:
            raise self.error(f"{where}: {exc}", name) from None
        # the Modbus server's key: its grammar is the north side's to check (with the line:
        # plcstack.north.modbus.config.build_map); here only that it is text
        modbus = spec.get("modbus")
        if modbus is not None and not isinstance(modbus, str):
            raise self.error(f'{where}: modbus must be text such as "hr:100", not {modbus!r}', name)
        return TagConfig(
            name,
            address.strip(),
            dtype,
            count,
            tag_group,
            scale=scale,
            writable=writable,
            unit=unit,
            description=description,
            modbus=modbus,
            decimals=decimals,
            labels=labels,
            line=self._line_of(name) if modbus is not None else None,
        )
