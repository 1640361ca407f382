"""The embedded history: every tag's values on the gateway itself, in one SQLite file.

``[history]`` in the poll configuration records each sample the poller delivers (after
report-by-exception) and answers ``GET /api/history`` of the web console, downsampled for long
ranges; no server, no extra package. ``settings`` (the table), ``blocks`` (the compact
encoding), ``store`` (the file), ``writer`` (its thread), ``downsample`` (min/max per bucket),
``sink`` (:class:`History`, the north-side sink and its queries). Costs: ``docs/history.md``.
"""

from plcstack.north.history.settings import HistorySettings, parse_history
from plcstack.north.history.sink import History, HistoryBusy

__all__ = ["History", "HistoryBusy", "HistorySettings", "parse_history"]
