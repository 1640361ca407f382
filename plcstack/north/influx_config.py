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
from urllib.parse import quote

from plcstack.checks import Table
from plcstack.errors import ConfigError
from plcstack.north.buffer import buffer_keys
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


def parse_influx(table: object, *, base: Path | None = None) -> InfluxSettings:
    """The ``[influx]`` table (``base``: the TOML file's directory, for relative paths), read
    by the one set of checks (:class:`~plcstack.checks.Table`): durations take units
    (``batch_wait = "500ms"``), sizes too (``buffer_max = "1 GiB"``)."""
    t = Table.of(table, "influx", base=base)
    t.keys(_KEYS)
    measurement = t.text("measurement", DEFAULT_MEASUREMENT)
    layout = t.choice("layout", DEFAULT_LAYOUT, LAYOUTS)
    url = t.optional_url("url", ("http", "https"))
    if url is None:
        extra = [key for key in _WRITER_KEYS if key in t]
        if extra:
            also = f" (as do {', '.join(extra[1:])})" if len(extra) > 1 else ""
            raise t.error(
                extra[0],
                f'needs url = "http://HOST:PORT" (the InfluxDB the writer sends to){also};'
                " without url [influx] only shapes --format influx",
            )
        return InfluxSettings(measurement, layout)
    if "database" not in t:
        raise t.error("url", 'needs database = "NAME" (the InfluxDB database)')
    username_env, password_env = t.optional_text("username_env"), t.optional_text("password_env")
    if (username_env is None) != (password_env is None):
        key = "username_env" if username_env is not None else "password_env"
        raise t.error(key, "and its partner go together: username_env and password_env")
    ca_file = t.file("ca_file")
    if ca_file is not None and url.scheme != "https":
        raise t.error("ca_file", "needs an https:// url")
    return InfluxSettings(
        measurement=measurement,
        layout=layout,
        url=url.text,
        database=t.text("database", ""),
        retention_policy=t.optional_text("retention_policy"),
        username_env=username_env,
        password_env=password_env,
        ca_file=ca_file,
        batch_size=t.integer("batch_size", 5000, 1, 100_000),
        batch_wait=t.seconds(
            "batch_wait", 1.0, hi=60, zero="each line goes as soon as the writer is free"
        ),
        timeout=t.seconds("timeout", 10.0, lo=0.5, hi=300),
        reconnect_max=t.seconds("reconnect_max", 30.0, lo=0.1, hi=3600),
        **buffer_keys(t),
    )
