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
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from plcstack.errors import ConfigError, check_keys

__all__ = [
    "DEFAULT_MAX_SIZE",
    "DEFAULT_RETENTION",
    "HistorySettings",
    "parse_bytes",
    "parse_duration",
    "parse_history",
]

DEFAULT_PATH = "history.sqlite"
DEFAULT_RETENTION = 7 * 86400.0
DEFAULT_MAX_SIZE = 1 << 30
#: the shortest retention and the smallest size cap that make sense (a checkpoint's worth)
MIN_RETENTION = 600.0
MIN_SIZE = 4 << 20
_KEYS = ("path", "retention", "max_size")

_UNITS_S = {"s": 1, "m": 60, "min": 60, "h": 3600, "d": 86400, "w": 7 * 86400}
_UNITS_B = {
    "b": 1,
    "kb": 1000,
    "mb": 1000**2,
    "gb": 1000**3,
    "tb": 1000**4,
    "kib": 1 << 10,
    "mib": 1 << 20,
    "gib": 1 << 30,
    "tib": 1 << 40,
}
_AMOUNT = re.compile(r"\s*([0-9]+(?:\.[0-9]+)?)\s*([a-zA-Z]*)\s*")


@dataclass(frozen=True)
class HistorySettings:
    #: the SQLite file (relative paths were taken relative to the TOML file when parsed)
    path: Path = Path(DEFAULT_PATH)
    #: seconds a point is kept
    retention: float = DEFAULT_RETENTION
    #: bytes the file may use (points beyond are deleted oldest first)
    max_size: int = DEFAULT_MAX_SIZE


def parse_duration(what: str, value: Any) -> float:
    """``"7d"``, ``"12h"``, ``"90m"``, ``"30s"``, ``"2w"`` or a number of seconds."""
    seconds: float | None = None
    if isinstance(value, int | float) and not isinstance(value, bool):
        seconds = float(value)
    elif isinstance(value, str):
        match = _AMOUNT.fullmatch(value)
        if match and match.group(2).lower() in _UNITS_S:
            seconds = float(match.group(1)) * _UNITS_S[match.group(2).lower()]
    if seconds is None or not math.isfinite(seconds) or seconds <= 0:
        raise ConfigError(
            f'{what} must be a duration such as "7d", "12h", "90m" or a number of seconds,'
            f" not {value!r}"
        )
    return seconds


def parse_bytes(what: str, value: Any) -> int:
    """``"1GB"``, ``"500MB"``, ``"2GiB"`` or a number of bytes."""
    size: float | None = None
    if isinstance(value, int) and not isinstance(value, bool):
        size = float(value)
    elif isinstance(value, str):
        match = _AMOUNT.fullmatch(value)
        unit = match.group(2).lower() if match else ""
        if match and (unit or "b") in _UNITS_B:
            size = float(match.group(1)) * _UNITS_B[unit or "b"]
    if size is None or not math.isfinite(size) or size < 1:
        raise ConfigError(
            f'{what} must be a size such as "1GB", "500MB" or a number of bytes, not {value!r}'
        )
    return int(size)


def parse_history(table: Any, *, base: Path | None = None) -> HistorySettings:
    """Check ``[history]``; ``base`` is the TOML file's directory (None: paths as written)."""
    if not isinstance(table, dict):
        raise ConfigError("[history] must be a table")
    check_keys(table, _KEYS, "history")
    path = table.get("path", DEFAULT_PATH)
    if not isinstance(path, str) or not path.strip() or "\x00" in path:
        raise ConfigError(f"[history] path must name a file, not {path!r}", key="history.path")
    file = Path(path).expanduser()
    if base is not None and not file.is_absolute():
        file = base / file
    try:
        retention = parse_duration("[history] retention", table.get("retention", "7d"))
        if retention < MIN_RETENTION:
            raise ConfigError(
                f"[history] retention must be at least {MIN_RETENTION / 60:.0f} minutes,"
                f" not {table['retention']!r}"
            )
    except ConfigError as exc:
        exc.key = "history.retention"
        raise
    try:
        max_size = parse_bytes("[history] max_size", table.get("max_size", DEFAULT_MAX_SIZE))
        if max_size < MIN_SIZE:
            raise ConfigError(
                f"[history] max_size must be at least 4 MiB, not {table['max_size']!r}"
            )
    except ConfigError as exc:
        exc.key = "history.max_size"
        raise
    return HistorySettings(file, retention, max_size)
