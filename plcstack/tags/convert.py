"""Imported tags checked against the PLC family and written as a ``[[plc]]`` TOML block.

The address check is the poller's own: the tags are planned on the client of ``--url`` (built,
never connected), so an address the PLC family cannot hold (``DB10.DW5`` on a MELSEC URL,
``D99999``, ``int16`` on a bit device) is refused here with the row it came from, not later by
``poll``.
The TOML written is parsed back with :func:`plcstack.poll.config.parse_poll_config` before anyone
sees it: what the import prints is a config ``plcstack poll`` accepts.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field

from plcstack.errors import AddressError
from plcstack.poll.config import (
    DEFAULT_GROUP,
    DEFAULT_INTERVAL,
    ConfigError,
    PlcConfig,
    TagConfig,
    parse_poll_config,
)
from plcstack.poll.engine import default_client_factory
from plcstack.poll.plan import build_plan
from plcstack.tags.table import TagListError
from plcstack.tomlfile import toml_string
from plcstack.url import parse_url
from plcstack.values import RAW

__all__ = ["ImportedTags", "check_tags", "group_name", "interval_ms", "to_toml"]


@dataclass(frozen=True)
class ImportedTags:
    """The tags of one file for one PLC, each with the line it came from."""

    source: str
    plc: str
    url: str
    tags: tuple[TagConfig, ...]
    lines: tuple[int, ...]
    #: scan groups other than ``default``: name -> interval in seconds
    groups: Mapping[str, float] = field(default_factory=dict)


def group_name(ms: int, default_ms: int = round(DEFAULT_INTERVAL * 1000)) -> str:
    """The scan group of a scan rate: ``default`` at the default interval, else ``scan_<ms>ms``."""
    return DEFAULT_GROUP if ms == default_ms else f"scan_{ms}ms"


def interval_ms(seconds: float) -> int | None:
    """A group interval as whole milliseconds (a Kepware scan rate), or None if it is not one."""
    ms = seconds * 1000
    return round(ms) if math.isfinite(ms) and abs(ms - round(ms)) < 1e-6 else None


_PREFIX = re.compile(r"^(tag '(?:[^'\\]|\\.)*'(?: at \S+)?: )+")


def check_tags(imported: ImportedTags, column: str = "Address") -> None:
    """Plan every tag on the client of the URL; the first refusal names its row and ``column``."""
    try:
        client = default_client_factory(PlcConfig(imported.plc, imported.url, ()))
    except AddressError as exc:
        raise TagListError(f"--url {imported.url}: {exc.message}") from None
    try:
        for tag, line in zip(imported.tags, imported.lines, strict=True):
            try:
                build_plan(client, [tag])
            except AddressError as exc:
                why = _PREFIX.sub("", exc.message) + _hint(tag.address, imported.url)
                raise TagListError.at(
                    imported.source, line, column, f"{tag.address} ({tag.type.name}): {why}"
                ) from None
    finally:
        client.transport.abort()


def _hint(address: str, url: str) -> str:
    """The likely cause when an address is of the other family than the URL."""
    melsec = parse_url(url).scheme.startswith("e71")
    if melsec and _S5_LIKE.match(address):
        return f" (an S5 address, but {url} is a MELSEC PLC)"
    if not melsec and _MELSEC_LIKE.match(address):
        return f" (a MELSEC address, but {url} is an S5 PLC)"
    return ""


_S5_LIKE = re.compile(r"^\s*(D[BX]\d+[.:]|[MEAIQF][BWY]\d+\s*$)", re.IGNORECASE)
_MELSEC_LIKE = re.compile(r"^\s*(D|W|R|X|Y|TN|CN)[0-9A-F]+\s*$", re.IGNORECASE)


# -- TOML ---------------------------------------------------------------------------------------

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def toml_key(key: str) -> str:
    return key if _BARE.match(key) else toml_string(key)


def toml_number(value: float) -> str:
    if isinstance(value, bool) or not math.isfinite(value):
        raise ValueError(f"not a finite number: {value!r}")
    return str(value) if isinstance(value, int) else repr(float(value))


def tag_line(tag: TagConfig) -> str:
    """One tag as ``name = { address = ..., ... }`` (keys only where not the default)."""
    fields = [f"address = {toml_string(tag.address)}"]
    if tag.type is not RAW:
        fields.append(f"type = {toml_string(tag.type.name)}")
    if tag.count != 1:
        fields.append(f"count = {tag.count}")
    if tag.group != DEFAULT_GROUP:
        fields.append(f"group = {toml_string(tag.group)}")
    if tag.writable:
        fields.append("writable = true")
    if tag.scale is not None:
        s = tag.scale
        numbers = ", ".join(toml_number(v) for v in (s.raw_lo, s.raw_hi, s.eng_lo, s.eng_hi))
        fields.append(f"scale = [{numbers}]")
    if tag.unit is not None:
        fields.append(f"unit = {toml_string(tag.unit)}")
    if tag.description is not None:
        fields.append(f"description = {toml_string(tag.description)}")
    return f"{toml_key(tag.name)} = {{ {', '.join(fields)} }}"


def to_toml(imported: ImportedTags) -> str:
    """``[groups]`` (when a tag needs one) and the ``[[plc]]`` block, checked by parsing it."""
    parts: list[str] = []
    if imported.groups:
        parts.append("[groups]")
        for name, seconds in sorted(imported.groups.items(), key=lambda kv: (kv[1], kv[0])):
            parts.append(f"{toml_key(name)} = {toml_number(seconds)}")
        parts.append("")
    parts += [
        "[[plc]]",
        f"name = {toml_string(imported.plc)}",
        f"url = {toml_string(imported.url)}",
        "",
        "[plc.tags]",
        *(tag_line(tag) for tag in imported.tags),
    ]
    text = "\n".join(parts) + "\n"
    try:
        parse_poll_config(text, source=imported.source)
    except ConfigError as exc:
        raise TagListError(
            f"{imported.source}: the converted tags are not a valid config: {exc}"
        ) from None
    return text
