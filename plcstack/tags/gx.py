"""Device comments of GX Developer and GX Works2 (MELSEC programming tools), read into tags.

The forms read (see the tags page of the documentation for the sources):

- GX Developer, "export to CSV": a line naming the columns, then ``Device number, Label,
  Comment`` per device, comma-separated, in the Windows code page (Shift-JIS on Japanese
  systems); a device with neither label nor comment is not written by the tool;
- GX Works2, "write to CSV file": a title line, a header line ``"Device Name"<TAB>"Comment"``
  and one quoted, tab-separated line per device, UTF-16 little endian with a byte-order mark.

Either form in either encoding (UTF-8, UTF-16 with BOM, Shift-JIS) and with either delimiter
(tab or comma) is read: the header line is found by its column names (English or Japanese),
any title lines before it are skipped. Each device with a comment or a label becomes a tag:
the comment its ``description``, the label (else the comment) its name by the rule of
:mod:`.names`; bit devices (X, Y, M, L, S, F, B, TS, TC, CS, CC) and bits of words (``D100.F``)
are ``bool``, word devices ``uint16`` or ``word_type``. Nothing is made writable: device
comments do not say which tags the north side may write.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from plcstack.codecs.e71_devices import parse_address
from plcstack.errors import AddressError
from plcstack.poll.config import TagConfig, text_problem
from plcstack.tags.addresses import native_address
from plcstack.tags.convert import ImportedTags, check_tags
from plcstack.tags.names import tag_names
from plcstack.tags.table import Row, TagListError, decode, rows
from plcstack.values import BOOL, UINT16, ValueType

__all__ = ["Skipped", "read_gx"]

_DEVICE = {"device", "device name", "device number", "device no.", "デバイス", "デバイス名"}
_LABEL = {"label", "ラベル"}
_COMMENT = {"comment", "device comment", "コメント", "デバイスコメント"}
#: title lines allowed before the header line
_MAX_TITLE = 5


@dataclass(frozen=True)
class Skipped:
    """A row left out with ``skip_unsupported``: where and why."""

    line: int
    device: str
    why: str


def _columns(row: Row) -> dict[str, int] | None:
    found: dict[str, int] = {}
    for index, cell in enumerate(row.cells):
        key = cell.strip().lower()
        for column, names in (("device", _DEVICE), ("label", _LABEL), ("comment", _COMMENT)):
            if key in names and column not in found:
                found[column] = index
    return found if "device" in found and "comment" in found else None


def _header(text: str, source: str) -> tuple[Iterator[Row], dict[str, int]] | None:
    """The records after the header line and the header's columns: the delimiter is the one
    (tab, then comma) that splits one of the first lines into known column names."""
    for delimiter in "\t,":
        records = rows(text, source, delimiter)
        try:
            for _, row in zip(range(_MAX_TITLE + 1), records, strict=False):
                columns = _columns(row)
                if columns is not None:
                    return records, columns
        except TagListError:
            continue  # not this delimiter's CSV: try the next one
    return None


def _device(text: str) -> tuple[str, bool]:
    """plcstack's notation of a device and whether it holds one bit (a bit of a word
    ``D100.F`` is written as GX Works writes it: one hexadecimal digit)."""
    address = native_address(text, "melsec")
    word, dot, _ = address.partition(".")
    return address, bool(dot) or parse_address(word).device.is_bit


def read_gx(
    data: bytes,
    source: str,
    *,
    plc: str,
    url: str,
    word_type: ValueType[Any] = UINT16,
    skip_unsupported: bool = False,
    skipped: Callable[[Skipped], None] | None = None,
) -> ImportedTags:
    """The commented devices of a GX device-comment CSV as tags of ``plc`` at ``url``.

    ``skip_unsupported`` leaves out (and reports to ``skipped``) devices the PLC family cannot
    hold (a Q-series ``SM400`` in an A-series project); without it they are refused."""
    text = decode(data, source, fallback="cp932")
    found_header = _header(text, source)
    if found_header is None:
        raise TagListError.at(
            source,
            None,
            None,
            'no header line with a device and a comment column (e.g. "Device Name", '
            '"Comment") in its first lines',
        )
    records, columns = found_header

    def cell(row: Row, column: str) -> str:
        index = columns.get(column)
        return row.cells[index].strip() if index is not None and index < len(row.cells) else ""

    entries: list[tuple[str, str, int]] = []
    found: list[tuple[str, ValueType[Any], str | None, int]] = []
    seen: dict[str, int] = {}
    for row in records:
        device_text, label, comment = cell(row, "device"), cell(row, "label"), cell(row, "comment")
        if not label and not comment:
            continue
        try:
            address, is_bit = _device(device_text)
        except AddressError as exc:
            if skip_unsupported:
                if skipped is not None:
                    skipped(Skipped(row.line, device_text, exc.message))
                continue
            raise TagListError.at(source, row.line, "Device", exc.message) from None
        if address in seen:
            raise TagListError.at(
                source, row.line, "Device", f"{address} is also the device of row {seen[address]}"
            )
        seen[address] = row.line
        problem = text_problem("comment", comment or None)
        if problem:
            raise TagListError.at(source, row.line, "Comment", problem)
        entries.append((address, label or comment, row.line))
        found.append((address, BOOL if is_bit else word_type, comment or None, row.line))
    if not found:
        raise TagListError.at(source, None, None, "no device with a comment or a label")
    names = tag_names(entries, source)
    tags = tuple(
        TagConfig(name, address, vtype, description=description)
        for name, (address, vtype, description, _) in zip(names, found, strict=True)
    )
    imported = ImportedTags(source, plc, url, tags, tuple(line for *_, line in found))
    check_tags(imported, column="Device")
    return imported
