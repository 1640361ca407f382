"""What changed between two configurations: what a reload has to do, and nothing more.

``diff(old, new)`` says, by PLC name, which PLCs were added, removed, reconnected (URL or a
connection option changed) or replanned (tags, scan groups, intervals: planned again on the
open connection), and which face tables changed (compared by value: ``[mqtt]``, ``[web]``,
``[[gateway]]``, ...). Everything it does not name keeps its connection, schedule and state.
"""

from __future__ import annotations

from dataclasses import dataclass

from plcstack.checks import changed_tables
from plcstack.config.model import Config
from plcstack.poll.diff import PlcChanges, plc_changes

__all__ = ["ConfigDiff", "diff"]


@dataclass(frozen=True)
class ConfigDiff:
    """The difference between two :class:`~plcstack.config.model.Config`."""

    plcs: PlcChanges
    #: the top-level tables of faces whose settings changed (added, removed or edited): the
    #: north side's first, in the order of the configuration's fields
    tables: tuple[str, ...] = ()

    @property
    def empty(self) -> bool:
        return self.plcs.empty and not self.tables

    def summary(self) -> str:
        """One line for the log of an apply."""
        text = self.plcs.summary()
        if self.tables:
            text += f"; tables changed: {', '.join(f'[{t}]' for t in self.tables)}"
        return text


def diff(old: Config, new: Config) -> ConfigDiff:
    """What changed from ``old`` to ``new`` (see the module docstring)."""
    tables = (*changed_tables(old.north, new.north), *changed_tables(old, new))
    return ConfigDiff(plc_changes(old.poll, new.poll), tables)
