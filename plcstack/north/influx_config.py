"""The ``[influx]`` table: the line format, and where the Influx writer sends it.

```toml
[influx]
measurement = "plc"                   # measurement name (default "plc")
layout = "fields"                     # a field per tag (default); "typed": a field per type
url = "http://influx.plant:8086"      # InfluxDB 1.x: the writer posts to URL/write (https too)
database = "plant"                    # needed with url
retention_policy = "autogen"          # optional (the database's default otherwise)
username_env = "INFLUX_USER"          # credentials come from the environment, never the file
password_env = "INFLUX_PASSWORD"
ca_file = "/etc/ssl/influx-ca.pem"    # https with a private CA
batch_size = 5000                     # lines per request at most
batch_wait = 1.0                      # seconds a line may wait for more to fill its batch
timeout = 10.0                        # seconds per request
reconnect_max = 30.0                  # longest wait between two attempts while InfluxDB fails
buffer_path = "/var/lib/plcstack/influx.sqlite"   # store-and-forward on disk, as [mqtt]'s
buffer_memory = 4194304               # bytes in memory before spilling to disk
buffer_max = 268435456                # total backlog budget; the oldest beyond it are dropped
```

Without ``url`` the table only shapes ``plcstack poll --format influx``. Relative ``buffer_path``
and ``ca_file`` are taken relative to the TOML file, as ``[mqtt]`` takes its paths.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit

from plcstack.checks import Table
from plcstack.errors import ConfigError, check_keys
from plcstack.north.influx import DEFAULT_LAYOUT, DEFAULT_MEASUREMENT, LAYOUTS

__all__ = ["InfluxSettings", "parse_influx"]

_KEYS = (
    "measurement", "layout", "url", "database", "retention_policy", "username_env",
    "password_env", "ca_file", "batch_size", "batch_wait", "timeout", "reconnect_max",
    "buffer_path", "buffer_memory", "buffer_max",
)  # fmt: skip
#: keys that mean something only with ``url``
_WRITER_KEYS = _KEYS[3:]


@dataclass(frozen=True)
class InfluxSettings:
    """The ``[influx]`` table; ``url`` None: no writer, only the stdout format."""

    measurement: str = DEFAULT_MEASUREMENT
    layout: str = DEFAULT_LAYOUT
    url: str | None = None
    database: str = ""
    retention_policy: str | None = None
    username_env: str | None = None
    password_env: str | None = None
    ca_file: str | None = None
    batch_size: int = 5000
    batch_wait: float = 1.0
    timeout: float = 10.0
    reconnect_max: float = 30.0
    buffer_path: str | None = None
    buffer_memory: int = 4 << 20
    buffer_max: int = 256 << 20

    @property
    def write_url(self) -> str:
        """``URL/write?db=...&precision=ns`` (``&rp=`` with a retention policy)."""
        base = (self.url or "").rstrip("/")
        query = f"db={quote(self.database, safe='')}&precision=ns"
        if self.retention_policy:
            query += f"&rp={quote(self.retention_policy, safe='')}"
        return f"{base}/write?{query}"

    def credentials(self, env: Mapping[str, str] | None = None) -> tuple[str, str] | None:
        """(username, password) from the named environment variables, read now; None without
        ``username_env``. A variable that is not set is a :class:`ConfigError` naming it."""
        if self.username_env is None or self.password_env is None:
            return None
        env = os.environ if env is None else env
        values = []
        for key, var in (("username", self.username_env), ("password", self.password_env)):
            value = env.get(var)
            if value is None:
                raise ConfigError(
                    f"[influx] {key}_env names the environment variable {var!r}, which is not"
                    " set; set it in the service's environment"
                )
            values.append(value)
        return values[0], values[1]


def parse_influx(table: Any, *, base: Path | None = None) -> InfluxSettings:
    """The ``[influx]`` table (``base``: the TOML file's directory, for relative paths); a
    :class:`~plcstack.checks.Table` of the one loader brings its own."""
    if isinstance(table, Table):
        table, base = table.values, table.base
    if not isinstance(table, dict):
        raise ConfigError("[influx] must be a table")
    check_keys(table, _KEYS, "influx")

    def text(key: str, default: str | None) -> str | None:
        value = table.get(key, default)
        if value is not None and (not isinstance(value, str) or not value.strip()):
            raise ConfigError(f"[influx] {key} must be a non-empty string")
        return value

    def integer(key: str, default: int, lo: int, hi: int) -> int:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise ConfigError(f"[influx] {key} must be an integer in {lo}..{hi}, got {value!r}")
        return value

    def seconds(key: str, default: float, lo: float, hi: float) -> float:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or not lo <= value <= hi:
            raise ConfigError(f"[influx] {key} must be {lo:g}..{hi:g} seconds, got {value!r}")
        return float(value)

    def file(key: str) -> str | None:
        value = text(key, None)
        if value is None or base is None or Path(value).is_absolute():
            return value
        return str(base / value)

    measurement = text("measurement", DEFAULT_MEASUREMENT) or DEFAULT_MEASUREMENT
    layout = table.get("layout", DEFAULT_LAYOUT)
    if layout not in LAYOUTS:
        raise ConfigError(
            f"[influx] layout must be {' or '.join(f'{chr(34)}{x}{chr(34)}' for x in LAYOUTS)},"
            f" not {layout!r}",
            key="influx.layout",
        )
    url = text("url", None)
    if url is None:
        extra = [key for key in _WRITER_KEYS if key in table]
        if extra:
            raise ConfigError(
                f'[influx] {", ".join(extra)} need url = "http://HOST:PORT" (the InfluxDB the'
                " writer sends to); without url [influx] only shapes --format influx"
            )
        return InfluxSettings(measurement, layout)
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        raise ConfigError(f"[influx] url has a bad port: {url!r}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname or parts.query:
        raise ConfigError(
            f"[influx] url must be http://HOST:PORT or https://HOST:PORT (InfluxDB 1.x; the"
            f" writer adds /write and its query), got {url!r}"
        )
    if parts.username or parts.password:
        raise ConfigError(
            "[influx] url must not carry credentials: name environment variables with"
            " username_env and password_env"
        )
    del port
    database = text("database", None)
    if database is None:
        raise ConfigError('[influx] url needs database = "NAME" (the InfluxDB database)')
    username_env, password_env = text("username_env", None), text("password_env", None)
    if (username_env is None) != (password_env is None):
        raise ConfigError("[influx] username_env and password_env go together (HTTP basic auth)")
    ca_file = file("ca_file")
    if ca_file is not None and parts.scheme != "https":
        raise ConfigError("[influx] ca_file needs an https:// url")
    return InfluxSettings(
        measurement=measurement,
        layout=layout,
        url=url,
        database=database,
        retention_policy=text("retention_policy", None),
        username_env=username_env,
        password_env=password_env,
        ca_file=ca_file,
        batch_size=integer("batch_size", 5000, 1, 100_000),
        batch_wait=seconds("batch_wait", 1.0, 0.0, 60.0),
        timeout=seconds("timeout", 10.0, 0.5, 300.0),
        reconnect_max=seconds("reconnect_max", 30.0, 0.1, 3600.0),
        buffer_path=file("buffer_path"),
        buffer_memory=integer("buffer_memory", 4 << 20, 0, 1 << 40),
        buffer_max=integer("buffer_max", 256 << 20, 1024, 1 << 44),
    )
