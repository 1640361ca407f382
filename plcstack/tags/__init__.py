"""Tag lists from engineering tools: Kepware CSV in and out, GX Developer / GX Works2 comments in.

A plant moving a PLC to plcstack already has its tag list in a Kepware project or in the
programming tool's device comments. These modules turn such a file into tags of
:mod:`plcstack.poll.config` (with types, writability, scaling, units and descriptions) and a
config's tags back into a Kepware CSV for editing in a spreadsheet:

- :mod:`.table` reads a delimited text file whatever its encoding (UTF-8, UTF-16, Shift-JIS,
  Windows-1252) and keeps each record's line number, so every refusal names ``FILE:ROW``;
- :mod:`.kepware` reads and writes Kepware's tag CSV;
- :mod:`.gx` reads device-comment CSVs and derives tag names (:mod:`.names`);
- :mod:`.convert` checks the tags against the PLC family (the poller's own address rules) and
  writes the ``[[plc]]`` TOML block.

Nothing is written until the whole file converted: a bad row is one :class:`TagListError`.
"""

from __future__ import annotations

from plcstack.tags.convert import ImportedTags, check_tags, group_name, to_toml
from plcstack.tags.gx import read_gx
from plcstack.tags.kepware import read_kepware, write_kepware
from plcstack.tags.names import tag_names
from plcstack.tags.table import TagListError

__all__ = [
    "ImportedTags",
    "TagListError",
    "check_tags",
    "group_name",
    "read_gx",
    "read_kepware",
    "tag_names",
    "to_toml",
    "write_kepware",
]
