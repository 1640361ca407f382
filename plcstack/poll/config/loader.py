"""The poll tables of a TOML file (``[poll]``, ``[groups]``, ``[[plc]]``) as a :class:`PollConfig`.

The file is read once by the one loader (:func:`plcstack.config.load_config`), which hands the
poll tables here and every other table to the parser that owns it; :func:`parse_poll_config`
reads a text of poll tables alone (the tag-list converters check what they wrote with it).

Every problem is a :class:`ConfigError` naming the PLC, the tag and ``FILE:LINE``, so a typo in
a 500-PLC file is found at once and before anything is sent.
"""

from __future__ import annotations

import math
import re
from collections.abc import Collection, Mapping
from typing import Any

from plcstack.checks import NAME_RULE, name_problem
from plcstack.errors import AddressError, ConfigError, unknown_names
from plcstack.poll.config.model import (
    DEFAULT_BATCH_WAIT,
    DEFAULT_CONCURRENCY,
    DEFAULT_GROUP,
    DEFAULT_INTERVAL,
    DEFAULT_MAX_GAP,
    DEFAULT_QUEUE,
    MIN_INTERVAL,
    PlcConfig,
    PollConfig,
    TagConfig,
    batch_wait_problem,
    text_problem,
)
from plcstack.poll.display import decimals_problem, parse_labels
from plcstack.tomlfile import TomlFile, toml_key
from plcstack.url import parse_url
from plcstack.values import TYPES, Scale, WordOrder, value_type

__all__ = ["POLL_TABLES", "PollTables", "parse_poll_config"]

#: the top-level keys this module reads
POLL_TABLES = ("poll", "groups", "plc")
_POLL_KEYS = frozenset(
    {
        "concurrency",
        "queue",
        "batch_wait",
        "max_gap",
        "timeout",
        "connect_timeout",
        "backoff_max",
        "interval",
    }
)
_PLC_KEYS = frozenset(
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
    }
)
_TAG_KEYS = frozenset(
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
    }
)
_PLC_HEADER = re.compile(r"\s*\[\[\s*plc\s*\]\]")
_LINE_KEY = re.compile(r"""\s*(?:"([^"]*)"|'([^']*)'|([\w\-]+))\s*=""")


def parse_poll_config(text: str, *, source: str = "<config>") -> PollConfig:
    """A TOML text of poll tables only (``[poll]``, ``[groups]``, ``[[plc]]``) as a
    :class:`PollConfig`; any other top-level table is an unknown key. A whole configuration
    file (with ``[mqtt]``, ``[opcua]``, ...) is read by :func:`plcstack.config.load_config`."""
    file = TomlFile.parse(text, source)
    return PollTables(file).load()


class PollTables:
    """Reads the poll tables of one parsed file; ``others`` are the top-level tables other
    layers read (named in the "unknown top-level key" message, otherwise left alone)."""

    def __init__(self, file: TomlFile, others: Collection[str] = ()) -> None:
        self.file = file
        self.lines = file.lines
        self.source = file.source
        self.others = tuple(others)
        self.plc_index = -1
        self.plc_name: str | None = None
        #: the line index of every [[plc]] header, and each section's key -> line
        self._starts = [i for i, line in enumerate(self.lines) if _PLC_HEADER.match(line)]
        self._keys: dict[int, dict[str, int]] = {}

    # -- where in the file ----------------------------------------------------------------------
    def _section(self) -> tuple[int, int]:
        starts = self._starts
        if self.plc_index < 0 or self.plc_index >= len(starts):
            return 0, len(self.lines)
        lo = starts[self.plc_index]
        hi = starts[self.plc_index + 1] if self.plc_index + 1 < len(starts) else len(self.lines)
        return lo, hi

    def line_of(self, key: str | None) -> int | None:
        """The line of ``key`` in the current ``[[plc]]`` section (its first ``key =`` line),
        else of the section's header. tomllib keeps no positions: good enough to point a
        person at the right place."""
        lo, hi = self._section()
        if key is None or self.plc_index < 0:
            if self.plc_index >= 0:
                return lo + 1
            if key is None:
                return None
        keys = self._keys.get(self.plc_index)
        if keys is None:
            keys = {}
            for i in range(lo, hi):
                m = _LINE_KEY.match(self.lines[i])
                if m:
                    keys.setdefault(m.group(1) or m.group(2) or m.group(3), i + 1)
            self._keys[self.plc_index] = keys
        return keys.get(key or "", lo + 1 if self.plc_index >= 0 else None)

    def error(
        self, message: str, key: str | None = None, *, path: str | None = None
    ) -> ConfigError:
        """A ConfigError with ``(FILE:LINE)``; the line is that of ``key`` in the current
        [[plc]] section, or of the dotted top-level ``path``."""
        line = self.file.line(path) if path is not None else self.line_of(key)
        return ConfigError(f"{message} ({self.file.at(line)})", plc=self.plc_name, key=path)

    # -- values ---------------------------------------------------------------------------------
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

    def _check_keys(
        self,
        table: Mapping[str, Any],
        allowed: Collection[str],
        where: str,
        line_key: str | None = None,
    ) -> None:
        """Every key of ``table`` is one of ``allowed``; else the error names each unknown key
        with the allowed one it is closest to (``adress (did you mean address?)``)."""
        unknown = sorted(set(table) - set(allowed))
        if unknown:
            names = unknown_names(unknown, allowed)
            raise self.error(f"{where}unknown key(s) {names}", line_key or unknown[0])

    # -- the tables -----------------------------------------------------------------------------
    def check_top(self) -> None:
        """Every top-level key is a poll table or one of ``others``."""
        data = self.file.data
        top = {*POLL_TABLES, *self.others}
        unknown = sorted(set(data) - top)
        if unknown:
            expected = "poll, groups, plc" + (
                f" or {', '.join(self.others)}" if self.others else ""
            )
            raise self.error(
                f"unknown top-level key(s) {unknown_names(unknown, top)}; expected {expected}",
                path=unknown[0],
            )

    def load(self) -> PollConfig:
        self.check_top()
        data = self.file.data
        poll = data.get("poll", {})
        if not isinstance(poll, dict):
            raise self.error("[poll] must be a table", path="poll")
        self._check_keys(poll, _POLL_KEYS, "[poll]: ")
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
            problem = name_problem("scan group", name)
            if problem:
                raise self.error(problem, path=toml_key("groups", name))
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
            tuple(plcs),
            groups,
            concurrency,
            queue,
            batch_wait=batch_wait,
            source=self.source,
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
        if "name" not in raw:
            raise self.error(f'missing name (e.g. name = "press1"); {NAME_RULE}')
        name = raw["name"]
        problem = name_problem("PLC", name)
        if problem:
            raise self.error(problem, "name")
        self.plc_name = name
        if not isinstance(url, str):
            raise self.error('missing url (e.g. url = "e71+tcp://10.0.0.5:5000")', "url")
        self._check_keys(raw, _PLC_KEYS, "")
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
            line=self.line_of(None),
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
        problem = name_problem("tag", name)
        if problem:
            raise self.error(problem, name if name.strip() else "tags")
        if isinstance(spec, str):
            spec = {"address": spec}
        if not isinstance(spec, dict):
            raise self.error(
                f'{where}: expected "ADDRESS" or {{ address = ..., type = ..., count = ... }}',
                name,
            )
        self._check_keys(spec, _TAG_KEYS, f"{where}: ", name)
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
            line=self.line_of(name),
        )
