"""Kepware's tag CSV (KEPServerEX "CSV Import/Export"): read into tags, written from a config.

A heading record, then one record per tag. The columns, in the order Kepware writes them:

=================  =============================================================================
Tag Name           the tag's name (duplicates refused)
Address            plcstack's notation or the Kepware driver's (:mod:`.addresses`); ``[N]`` array
Data Type          Boolean bool, Char int8, Byte uint8, Short int16, Word uint16, Long int32,
                   DWord uint32, Float float32, BCD bcd16, LBCD bcd32, String string:N,
                   Default raw; ``<type> Array`` with ``[N]``; any plcstack type name
Respect Data Type  0/1, accepted and not used (plcstack always uses the tag's type)
Client Access      RO read-only, R/W or RW writable; blank read-only; WO refused
Scan Rate          milliseconds: one scan group per distinct rate (:func:`.convert.group_name`)
Scaling            blank/None, Linear (needs the four ranges); Square Root refused
Raw Low ... High   the linear scale ``[raw_lo, raw_hi, eng_lo, eng_hi]``
Scaled Data Type   any numeric Kepware type; a scaled value is a float in plcstack
Clamp Low/High     0 or blank; 1 refused: plcstack's scaling extrapolates (a sensor fault
                   stays visible) and has no clamp to keep it
Eng Units          ``unit``
Description        ``description``
Negate Value       0 or blank (newer servers); 1 refused
=================  =============================================================================

Delimiter: comma, or semicolon (Kepware's option); encoding UTF-8 (with or without BOM),
UTF-16 with BOM, else Windows-1252. The writer puts plcstack's notation in ``Address`` and the
plcstack type name in ``Data Type`` where Kepware has none (``kg``, ``string:8:space``), so
what it writes is read back to the same tags.
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Mapping
from typing import Any

from plcstack.errors import AddressError
from plcstack.poll.config import DEFAULT_GROUP, PlcConfig, TagConfig, text_problem
from plcstack.tags.addresses import family, native_address, split_array, split_string_length
from plcstack.tags.convert import ImportedTags, check_tags, group_name, interval_ms
from plcstack.tags.table import Row, TagListError, decode, rows, sniff_delimiter
from plcstack.url import parse_url
from plcstack.values import (
    BCD16,
    BCD32,
    BOOL,
    FLOAT32,
    INT8,
    INT16,
    INT32,
    RAW,
    UINT8,
    UINT16,
    UINT32,
    Endian,
    Scale,
    ValueType,
    default_byte_order,
    string,
    value_type,
)

__all__ = ["COLUMNS", "KEPWARE_TYPES", "read_kepware", "write_kepware"]

#: the heading record, in Kepware's order
COLUMNS = (
    "Tag Name",
    "Address",
    "Data Type",
    "Respect Data Type",
    "Client Access",
    "Scan Rate",
    "Scaling",
    "Raw Low",
    "Raw High",
    "Scaled Low",
    "Scaled High",
    "Scaled Data Type",
    "Clamp Low",
    "Clamp High",
    "Eng Units",
    "Description",
)
#: columns read as well: newer servers write "Negate Value"; older help pages "Eng. Units"
_EXTRA = ("Negate Value",)
_ALIASES = {"eng. units": "Eng Units"}
_KNOWN = {c.lower(): c for c in (*COLUMNS, *_EXTRA)} | _ALIASES

#: Kepware data type -> plcstack value type
KEPWARE_TYPES: dict[str, ValueType[Any]] = {
    "Boolean": BOOL,
    "Char": INT8,
    "Byte": UINT8,
    "Short": INT16,
    "Word": UINT16,
    "Long": INT32,
    "DWord": UINT32,
    "Float": FLOAT32,
    "BCD": BCD16,
    "LBCD": BCD32,
    "Default": RAW,
}
_BY_LOWER = {k.lower(): v for k, v in KEPWARE_TYPES.items()}
_NAME_OF = {v.name: k for k, v in KEPWARE_TYPES.items()}
#: Kepware's numeric types, accepted as a "Scaled Data Type"
_SCALED = {"char", "byte", "short", "word", "long", "dword", "float", "double", "bcd", "lbcd"}
_INTEGER = re.compile(r"^[+-]?\d+$")
_FREE_TEXT = ("Description", "Eng Units")


class _Reader:
    def __init__(self, source: str, plc: str, url: str) -> None:
        self.source, self.plc, self.url = source, plc, url
        self.family = family(url)
        self.byte_order = default_byte_order(parse_url(url).scheme)
        self.columns: dict[str, int] = {}
        self.row = Row(0, ())

    def fail(self, column: str | None, why: str) -> TagListError:
        return TagListError.at(self.source, self.row.line, column, why)

    def cell(self, column: str) -> str:
        index = self.columns.get(column)
        if index is None or index >= len(self.row.cells):
            return ""
        text = self.row.cells[index]
        # free text is kept as written (round trips); structural cells lose stray spaces
        return text if column in _FREE_TEXT else text.strip()

    def header(self, row: Row) -> None:
        self.row = row
        for index, name in enumerate(row.cells):
            known = _KNOWN.get(name.strip().lower())
            if known is None:
                raise self.fail(
                    None,
                    f"unknown column {name!r} in the heading record (columns read: "
                    f"{', '.join(COLUMNS)}, {', '.join(_EXTRA)})",
                )
            if known in self.columns:
                raise self.fail(known, "appears twice in the heading record")
            self.columns[known] = index
        for needed in ("Tag Name", "Address"):
            if needed not in self.columns:
                raise self.fail(None, f"the heading record has no {needed!r} column")

    def number(self, column: str) -> float:
        text = self.cell(column)
        try:
            value = int(text) if _INTEGER.match(text) else float(text)
        except ValueError:
            raise self.fail(column, f"expected a number, not {text!r}") from None
        return value

    def flag(self, column: str) -> bool:
        text = self.cell(column)
        if text not in ("", "0", "1"):
            raise self.fail(column, f"expected 0 or 1, not {text!r}")
        return text == "1"

    def dtype(self) -> tuple[ValueType[Any], str, int]:
        """The value type, the address in plcstack's notation and the count."""
        text = self.cell("Data Type") or "Default"
        address, count = split_array(self.cell("Address"))
        is_array = text.lower().endswith(" array")
        if is_array != (count is not None):
            raise self.fail(
                "Data Type" if is_array else "Address",
                "an array needs both a '<type> Array' data type and an '[N]' after the address",
            )
        if count is not None and count < 1:
            raise self.fail("Address", f"array length must be at least 1, not {count}")
        base = text[: -len(" array")].strip() if is_array else text
        if base.lower() == "string":
            found = split_string_length(address)
            if found is None:
                raise self.fail(
                    "Address", f"a String needs its length after the address (e.g. {address}.20)"
                )
            address, length, order = found
            mine = "H" if self.byte_order is Endian.BIG else "L"
            if order and order != mine:
                raise self.fail(
                    "Address",
                    f"{order}: this PLC family stores strings {'high' if mine == 'H' else 'low'}"
                    f" byte first ({mine})",
                )
            try:
                return string(length), native_address(address, self.family), count or 1
            except AddressError as exc:
                raise self.fail("Address", exc.message) from None
        vtype = _BY_LOWER.get(base.lower())
        if vtype is None:
            try:
                vtype = value_type(base)
            except AddressError:
                raise self.fail(
                    "Data Type",
                    f"unknown type {text!r} (Kepware types read: {', '.join(KEPWARE_TYPES)},"
                    " String; or a plcstack type such as int16, kg, string:8)",
                ) from None
        return vtype, native_address(address, self.family), count or 1

    def scale(self, vtype: ValueType[Any]) -> Scale | None:
        mode = self.cell("Scaling")
        for column in ("Clamp Low", "Clamp High"):
            if self.flag(column):
                raise self.fail(
                    column,
                    "plcstack's scaling does not clamp (values beyond the range extrapolate, "
                    "so a sensor fault stays visible); set it to 0 to import the tag",
                )
        if self.flag("Negate Value"):
            raise self.fail("Negate Value", "negated values are not supported; set it to 0")
        if mode.lower() in ("", "none"):
            return None
        if mode.lower() == "square root":
            raise self.fail(
                "Scaling",
                "Square Root scaling is not supported (plcstack scales linearly); "
                "use Linear or scale in the client",
            )
        if mode.lower() != "linear":
            raise self.fail("Scaling", f"expected None, Linear or Square Root, not {mode!r}")
        if vtype.kind not in ("int", "float"):
            raise self.fail("Scaling", f"scaling needs a numeric type, not {vtype.name}")
        scaled = self.cell("Scaled Data Type")
        if scaled and scaled.lower() not in _SCALED:
            raise self.fail("Scaled Data Type", f"expected a numeric Kepware type, not {scaled!r}")
        ranges = [self.number(c) for c in ("Raw Low", "Raw High", "Scaled Low", "Scaled High")]
        try:
            return Scale(*ranges)
        except AddressError as exc:
            raise self.fail("Raw Low", exc.message) from None

    def writable(self) -> bool:
        access = self.cell("Client Access").upper()
        if access in ("", "RO"):
            return False
        if access in ("R/W", "RW"):
            return True
        if access == "WO":
            raise self.fail("Client Access", "write-only tags cannot be polled; use R/W")
        raise self.fail("Client Access", f"expected RO or R/W, not {access!r}")

    def group(self, groups: dict[str, float]) -> str:
        text = self.cell("Scan Rate")
        if not text:
            return DEFAULT_GROUP
        if not _INTEGER.match(text) or int(text) < 1:
            raise self.fail("Scan Rate", f"expected whole milliseconds (1 or more), not {text!r}")
        name = group_name(int(text))
        if name != DEFAULT_GROUP:
            groups[name] = int(text) / 1000
        return name

    def text(self, column: str, key: str) -> str | None:
        value = self.cell(column) if self.cell(column).strip() else None
        problem = text_problem(key, value)
        if problem:
            raise self.fail(column, problem)
        return value

    def tag(self, groups: dict[str, float]) -> TagConfig:
        name = self.cell("Tag Name")
        if not name:
            raise self.fail("Tag Name", "a tag needs a name")
        if not self.cell("Address"):
            raise self.fail("Address", "a tag needs an address")
        vtype, address, count = self.dtype()
        self.flag("Respect Data Type")
        return TagConfig(
            name,
            address,
            vtype,
            count,
            self.group(groups),
            scale=self.scale(vtype),
            writable=self.writable(),
            unit=self.text("Eng Units", "unit"),
            description=self.text("Description", "description"),
        )


def read_kepware(data: bytes, source: str, *, plc: str, url: str) -> ImportedTags:
    """The tags of a Kepware CSV for the PLC ``plc`` at ``url``; :class:`TagListError` names
    the first row that cannot be converted."""
    try:
        reader = _Reader(source, plc, url)
    except AddressError as exc:
        raise TagListError(f"--url {url}: {exc.message}") from None
    text = decode(data, source, fallback="cp1252")
    records = rows(text, source, sniff_delimiter(text, ",;"))
    first = next(records, None)
    if first is None:
        raise TagListError.at(source, None, None, "empty: no heading record and no tags")
    reader.header(first)
    tags: list[TagConfig] = []
    lines: list[int] = []
    groups: dict[str, float] = {}
    seen: dict[str, int] = {}
    for row in records:
        reader.row = row
        tag = reader.tag(groups)
        if tag.name in seen:
            raise reader.fail("Tag Name", f"{tag.name!r} is also the name of row {seen[tag.name]}")
        seen[tag.name] = row.line
        tags.append(tag)
        lines.append(row.line)
    if not tags:
        raise TagListError.at(source, None, None, "no tags after the heading record")
    imported = ImportedTags(source, plc, url, tuple(tags), tuple(lines), groups)
    check_tags(imported)
    return imported


def _kepware_type(tag: TagConfig) -> tuple[str, str]:
    """Data Type and Address cells of ``tag``."""
    name = _NAME_OF.get(tag.type.name)
    address = tag.address
    if name is None and re.fullmatch(r"string:\d+", tag.type.name):
        name = "String"
        address = f"{address}.{tag.type.name.split(':')[1]}"
    name = name or tag.type.name
    if tag.count != 1:
        return f"{name} Array", f"{address} [{tag.count}]"
    return name, address


def _number(value: float) -> str:
    if isinstance(value, float) and value.is_integer() and abs(value) < 2**53:
        return str(int(value))
    return repr(value)


def write_kepware(plc: PlcConfig, groups: Mapping[str, float]) -> str:
    """The Kepware CSV of ``plc``'s tags (``groups``: the config's scan groups)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\r\n")
    writer.writerow(COLUMNS)
    for tag in plc.tags:
        rate = interval_ms(groups[tag.group])
        if rate is None:
            raise TagListError(
                f"PLC {plc.name!r}, tag {tag.name!r}: scan group {tag.group!r} interval "
                f"{groups[tag.group]!r} s is not whole milliseconds (a Kepware scan rate)"
            )
        dtype, address = _kepware_type(tag)
        s = tag.scale
        scaling = (
            ["Linear", *(_number(v) for v in (s.raw_lo, s.raw_hi, s.eng_lo, s.eng_hi)), "Double"]
            if s is not None
            else ["", "", "", "", "", ""]
        )
        writer.writerow(
            [
                tag.name,
                address,
                dtype,
                "1",
                "R/W" if tag.writable else "RO",
                str(rate),
                *scaling,
                "0" if s is not None else "",
                "0" if s is not None else "",
                tag.unit or "",
                tag.description or "",
            ]
        )
    return out.getvalue()
