"""``[history]``: where the embedded history is kept, for how long, and how large it may grow.

```toml
[history]
path = "history.sqlite"     # relative to this file (default "history.sqlite")
retention = "7d"            # older points are deleted: "90m", "12h", "7d", "2w" or seconds
max_size = "1GB"            # the oldest points go first beyond it: "500MB", "2GB" or bytes
```

No server, no extra package: an SQLite file next to the configuration. What each key costs
(disk per point, CPU, memory) is said in ``docs/history.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from plcstack.checks import Table

__all__ = ["DEFAULT_MAX_SIZE", "DEFAULT_RETENTION", "HistorySettings", "parse_history"]

DEFAULT_PATH = "history.sqlite"
DEFAULT_RETENTION = 7 * 86400.0
DEFAULT_MAX_SIZE = 1 << 30
#: the shortest retention and the smallest size cap that make sense (a checkpoint's worth)
MIN_RETENTION = 600.0
MIN_SIZE = 4 << 20
_KEYS = ("path", "retention", "max_size")


@dataclass(frozen=True)
class HistorySettings:
    #: the SQLite file (relative paths were taken relative to the TOML file when parsed)
    path: Path = Path(DEFAULT_PATH)
    #: seconds a point is kept
    retention: float = DEFAULT_RETENTION
    #: bytes the file may use (points beyond are deleted oldest first)
    max_size: int = DEFAULT_MAX_SIZE


def parse_history(table: object, *, base: Path | None = None) -> HistorySettings:
    """Check ``[history]``; ``base`` is the TOML file's directory (None: paths as written)."""
    t = Table.of(table, "history", base=base)
    t.keys(_KEYS)
    path = t.file("path", DEFAULT_PATH) or DEFAULT_PATH
    retention = t.seconds("retention", DEFAULT_RETENTION, lo=MIN_RETENTION, hi=math.inf)
    max_size = t.size("max_size", DEFAULT_MAX_SIZE, MIN_SIZE, 1 << 50)
    return HistorySettings(Path(path), retention, max_size)
