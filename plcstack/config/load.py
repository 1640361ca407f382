"""Reading a configuration file: once, every table by its owner, every error with FILE:LINE.

The text is parsed once (:class:`~plcstack.tomlfile.TomlFile`). The top-level keys are checked
first (an unknown one gets a "did you mean"), then each face's table is read by the function
its :class:`~plcstack.config.model.Config` field names, then the poll tables. A mistake
anywhere is one :class:`~plcstack.errors.ConfigError` naming the file and line; an old spelling
that still loads is one WARNING line with its file and line, and stays in
:attr:`Config.notices <plcstack.config.model.Config.notices>`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from plcstack.checks import Notice, read_tables
from plcstack.config.model import TABLES, Config
from plcstack.errors import ConfigError
from plcstack.gateway.table import check_faces
from plcstack.north.config import parse_north
from plcstack.north.modbus.config import build_map
from plcstack.poll.checks import check_plans, shared_connections
from plcstack.poll.config import PollTables
from plcstack.tomlfile import TomlFile

__all__ = ["load_config", "parse_config", "read_config"]

log = logging.getLogger("plcstack.config")


def load_config(path: str | Path) -> Config:
    """Read a configuration file once and check all of it: the poll tables and every face's
    table, so a typo anywhere stops before anything is sent. Relative paths in it are taken
    relative to the file's directory."""
    return read_config(TomlFile.read(path))


def parse_config(text: str, *, source: str = "<config>") -> Config:
    """:func:`load_config` of a text (``source`` names it in messages; relative paths are
    taken as written)."""
    return read_config(TomlFile.parse(text, source))


def read_config(file: TomlFile) -> Config:
    """The :class:`Config` of a parsed file; its notices are logged once, at WARNING."""
    notices: list[Notice] = []
    poll_tables = PollTables(file, others=TABLES)
    poll_tables.check_top()
    try:
        north = parse_north(file.data, base=file.base, notices=notices)
        own = read_tables(Config, file.data, base=file.base, notices=notices)
    except ConfigError as exc:
        raise file.error(exc) from None
    poll = poll_tables.load()
    try:
        check_faces(own.get("gateway", ()), [(plc.name, plc.url) for plc in poll.plcs])
    except ConfigError as exc:
        raise file.error(exc) from None
    tags = check_plans(poll)  # every address on its family's client, with FILE:LINE
    if any(tag.modbus is not None for plc in poll.plcs for tag in plc.tags):
        build_map(tags, source=file.source)  # overlaps refused at load, by every command
    notices += [Notice(None, message, line) for line, message in shared_connections(poll)]
    said = tuple(
        f"{n.message} ({file.at(n.line or (file.line(n.key) if n.key else None))})" for n in notices
    )
    for line in said:
        log.warning("%s", line)
    return Config(poll, north, source=file.source, notices=said, **own)
