"""The one configuration: a file's poll tables and every face's, typed, read once."""

from __future__ import annotations

from dataclasses import dataclass, field

from plcstack.checks import table_names, toml_array
from plcstack.gateway.faces import FaceSettings
from plcstack.gateway.table import parse_gateway
from plcstack.north.config import NorthConfig
from plcstack.poll.config import PlcConfig, PollConfig

__all__ = ["TABLES", "Config"]


@dataclass(frozen=True)
class Config:
    """Everything one configuration file says: the poller's tables (``poll``: ``[poll]``,
    ``[groups]``, ``[[plc]]``) and the faces' (``north``: ``[mqtt]``, ``[opcua]``, ``[web]``,
    ...).

    A table of a layer beside the north side is a field of its own here, declared with
    :func:`plcstack.checks.toml_table` (the name of its table and the function that reads it);
    a north-side table is one in :class:`~plcstack.north.config.NorthConfig`. The loader, the
    "unknown table" message with its guess and the reload diff follow from the field.
    """

    poll: PollConfig
    north: NorthConfig = field(default_factory=NorthConfig)
    #: ``[[gateway]]``: the native faces (S5-LAN, FETCH/WRITE, E71, AS511) in front of the
    #: file's PLCs, on each PLC's one connection (plcstack.gateway.faces)
    gateway: tuple[FaceSettings, ...] = field(
        default=(), metadata=toml_array("gateway", parse_gateway)
    )
    #: the file it was read from (None: built in Python)
    source: str | None = field(default=None, compare=False)
    #: what the loader said about the file while it loaded (an old spelling, connections it
    #: expects to fail), each with its FILE:LINE; logged at WARNING when it was read
    notices: tuple[str, ...] = field(default=(), compare=False)

    @property
    def plcs(self) -> tuple[PlcConfig, ...]:
        return self.poll.plcs


#: every top-level table another layer than the poller reads, in the order they are checked
TABLES = (*table_names(NorthConfig), *table_names(Config))
