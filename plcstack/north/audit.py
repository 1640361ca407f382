"""The audit of writes: one JSON line per write attempt from any north side, in one file.

```toml
[audit]
path = "writes.jsonl"      # relative to the TOML file
max_bytes = 10485760       # rotate when the file would grow past this (default 10 MiB)
backups = 5                # keep writes.jsonl.1 .. writes.jsonl.5 (default 5; 0 = truncate)
```

Each line (keys always present, in this order)::

    {"time": "2026-11-25T21:50:01.123Z", "source": "mqtt", "user": null, "plc": "press1",
     "tag": "setpoint", "value": 1201, "previous": 1200, "result": "ok",
     "may_have_executed": true, "peer": "10.0.0.7:50412"}

``source`` is the north side (``mqtt``, ``sparkplug``, ``opcua``, ``gateway``, ``web``,
``modbus``, ``api``); ``user`` the login name or null; ``tag`` the address for the gateway;
``previous`` the last polled value (null if none was seen yet); ``result`` ``ok`` or the error
code the source answered; ``may_have_executed`` false only when the PLC certainly did not
execute it (refused before sending, or the PLC answered with an error). ``peer`` is the
network address (``host:port``, ``[v6]:port``) of the client connection the write came in on,
which answers "which machine sent this" where ``user`` is null: the HTTP client of the web console
and REST API (a reverse proxy's address when one is in front), the Modbus TCP client, the OPC UA
session's client, the gateway's S5-LAN or FETCH/WRITE client. It is null for MQTT and Sparkplug
writes (the broker delivers a message without its publisher's address) and for a write from
Python. ``peer`` was added last, so a reader that knows the keys before it is unaffected.

A change of the running configuration (a reload on SIGHUP or from the web console, a file
replaced through ``POST /api/config``) is a line of its own kind, told apart by ``"kind":
"config"`` (a write's line has no ``kind``)::

    {"time": "2026-11-25T21:52:10.004Z", "kind": "config", "source": "SIGHUP",
     "file": "/etc/plcstack/plant.toml", "result": "ok",
     "summary": "PLCs added: press9; removed: none; changed: none"}

``source`` says who asked (``SIGHUP``, or the web console with its client's address);
``result`` is ``ok`` (applied) or ``refused`` (the file did not load: nothing changed), and
``summary`` what was applied or the first error.

A line is written and flushed before the answer goes back to the client. Rotation is by size:
before a line would take the file past ``max_bytes``, ``FILE.N`` becomes ``FILE.N+1`` (the
oldest beyond ``backups`` is deleted), ``FILE`` becomes ``FILE.1``, and a new ``FILE`` starts. A
line that cannot be written (disk full, file removed with its directory, permissions) is an
ERROR in the log and counts in ``plcstack_sink_errors_total{sink="audit"}``; it is never
skipped silently, and the write it records is not held back for it. A line cut short (a crash,
or a disk that filled in the middle of it) is ended with a newline before the next one, so every
complete line stays one JSON record; the file is never moved or truncated for what it holds.
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from plcstack.checks import Table
from plcstack.errors import ConfigError
from plcstack.north.health import Condition, Health
from plcstack.output import json_safe

__all__ = ["Audit", "AuditSettings", "parse_audit"]

log = logging.getLogger("plcstack.north.audit")

FIELDS = (
    "time",
    "source",
    "user",
    "plc",
    "tag",
    "value",
    "previous",
    "result",
    "may_have_executed",
    "peer",
)


@dataclass(frozen=True)
class AuditSettings:
    path: str
    max_bytes: int = 10 << 20
    backups: int = 5


def parse_audit(table: object, *, base: Path | None = None) -> AuditSettings:
    """The ``[audit]`` table; a relative ``path`` is taken relative to ``base`` (the TOML
    file's directory)."""
    t = Table.of(table, "audit", base=base)
    t.keys(("path", "max_bytes", "backups"))
    path = t.file("path")
    if path is None:
        raise ConfigError(
            '[audit] needs path = "FILE" (one JSON line per write attempt)', key="audit"
        )
    max_bytes = t.size("max_bytes", 10 << 20, 4096, 1 << 40)
    backups = t.integer("backups", 5, 0, 1000)
    return AuditSettings(path, max_bytes, backups)


def _ends_a_line(path: Path) -> bool:
    """Does the file end with a newline (or is it no regular file, like ``/dev/full``)?"""
    try:
        with open(path, "rb") as f:
            f.seek(-1, os.SEEK_END)
            return f.read(1) == b"\n"
    except OSError:
        return True


def _iso(now: float) -> str:
    stamp = datetime.datetime.fromtimestamp(now, datetime.UTC)
    return stamp.strftime("%Y-%m-%dT%H:%M:%S.") + f"{stamp.microsecond // 1000:03d}Z"


class Audit:
    """Appends audit lines to one file, rotating it by size; see the module docstring.

    ``on_error`` is called once per line that could not be written (the run's supervisor
    counts it).
    """

    def __init__(self, settings: AuditSettings, on_error: Callable[[], None] | None = None) -> None:
        self.settings = settings
        self.path = Path(settings.path)
        self.on_error = on_error
        self.written = 0
        self.failed = 0
        self._file: TextIO | None = None
        self._size = 0
        #: written before the next line: a newline if the file ends in a line cut short
        self._start = ""
        self._last_error: str | None = None
        #: whether the last line could be written (``/healthz`` names the file while not)
        self.condition = Condition("audit")

    def open(self) -> None:
        """Open (create) the file now: :class:`ConfigError` naming it if that is impossible, so
        a run does not start with an audit it cannot keep."""
        try:
            self._open()
        except OSError as exc:
            raise ConfigError(
                f"[audit] cannot write {str(self.path)!r}: {exc.strerror or exc}"
            ) from None

    def _open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 - kept open
        self._size = self._file.tell()
        # a line cut short (a crash, a full disk mid-line) is ended before the next record:
        # glued to it, that record would be lost to every JSON reader too
        self._start = "" if not self._size or _ends_a_line(self.path) else "\n"

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def record(
        self,
        *,
        source: str,
        user: str | None,
        plc: str,
        tag: str,
        value: Any,
        previous: Any,
        result: str,
        may_have_executed: bool,
        peer: str | None,
        now: float,
    ) -> bool:
        """Append and flush one line; False (logged, counted) if it could not be written."""
        entry = {
            "time": _iso(now),
            "source": source,
            "user": user,
            "plc": plc,
            "tag": tag,
            "value": json_safe(value),
            "previous": json_safe(previous),
            "result": result,
            "may_have_executed": may_have_executed,
            "peer": peer,
        }
        return self._append(entry)

    def config_change(self, *, source: str, file: str, ok: bool, summary: str, now: float) -> bool:
        """Append and flush the line of one change of the running configuration (see the
        module docstring); False (logged, counted) if it could not be written."""
        entry = {
            "time": _iso(now),
            "kind": "config",
            "source": source,
            "file": file,
            "result": "ok" if ok else "refused",
            "summary": summary,
        }
        return self._append(entry)

    def _append(self, entry: dict[str, Any]) -> bool:
        line = json.dumps(entry, ensure_ascii=False, default=repr) + "\n"
        size = len(line.encode("utf-8"))
        try:
            if self._file is None:
                self._open()
            elif self._size + size > self.settings.max_bytes and self._size > 0:
                self._rotate()
            assert self._file is not None
            self._file.write(self._start + line)
            self._file.flush()
        except OSError as exc:
            self._failed(exc, entry)
            return False
        self._size += size + len(self._start)
        self._start = ""
        self.written += 1
        self._last_error = None
        self.condition.clear()
        return True

    def _rotate(self) -> None:
        self.close()
        keep = self.settings.backups
        if keep == 0:
            self.path.unlink(missing_ok=True)
        else:
            oldest = self.path.with_name(f"{self.path.name}.{keep}")
            oldest.unlink(missing_ok=True)
            for n in range(keep - 1, 0, -1):
                older = self.path.with_name(f"{self.path.name}.{n}")
                if older.exists():
                    os.replace(older, self.path.with_name(f"{self.path.name}.{n + 1}"))
            os.replace(self.path, self.path.with_name(f"{self.path.name}.1"))
        self._open()

    def _failed(self, exc: OSError, entry: dict[str, Any]) -> None:
        self.failed += 1
        if self.on_error is not None:
            self.on_error()
        # the file may be half-broken (a removed directory, a full disk): open it anew next time
        if self._file is not None:
            with contextlib.suppress(OSError):
                self._file.close()
            self._file = None
        reason = f"{exc.strerror or exc}"
        log.error(
            "audit: cannot write %s (%s); this record is not in the audit: %s",
            self.path,
            reason,
            json.dumps(entry, default=repr),
        )
        self._last_error = reason
        self.condition.fail(f"cannot write {self.path} ({reason}); writes are not audited")

    def health(self) -> Health:
        """Unhealthy from a line that could not be written until one is written again."""
        return self.condition.health(figures=(("lines not written", self.failed),))
