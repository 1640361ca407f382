"""``[web]``: where the console listens and which environment variable holds the write token.

```toml
[web]
port = 8080                       # 0 = any free port (default 8080)
host = "127.0.0.1"                # default: loopback only (the page names every PLC)
write_token_env = "PLCSTACK_WEB_TOKEN"   # writes are off unless this variable is set, non-empty
trend_seconds = 300               # how far back each tag's trend reaches (default 300)
hosts = ["gateway01", "gateway01.plant.local"]   # names the console answers to besides
                                  # localhost, IP addresses and this machine's own name
```

The token itself never sits in the file: a config is copied, committed and mailed around; an
environment variable is set by the service manager of the one machine that runs the gateway.
"""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass
from typing import Any

from plcstack.errors import check_keys
from plcstack.poll.config import ConfigError

__all__ = ["DEFAULT_PORT", "WebSettings", "parse_web", "with_port"]

DEFAULT_PORT = 8080
#: trend reach: one point per second at most, so this is also the ring's length per tag
DEFAULT_TREND_SECONDS = 300
MAX_TREND_SECONDS = 3600
_KEYS = {"port", "host", "write_token_env", "trend_seconds", "hosts"}
#: a host name as a browser sends it in ``Host`` (letters, digits, dots, hyphens, underscores)
_HOST_NAME = re.compile(r"[A-Za-z0-9_]([A-Za-z0-9_.-]*[A-Za-z0-9_])?")


@dataclass(frozen=True)
class WebSettings:
    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    #: name of the environment variable holding the bearer token (None: writes are off)
    write_token_env: str | None = None
    trend_seconds: int = DEFAULT_TREND_SECONDS
    #: more names the console answers to (``Host``), besides localhost, IP addresses, its own
    #: ``host`` and this machine's name: a request for any other is refused (DNS rebinding)
    hosts: tuple[str, ...] = ()

    def write_token(self) -> str | None:
        """The token from the environment now, or None when writes are off."""
        if self.write_token_env is None:
            return None
        return os.environ.get(self.write_token_env) or None


def parse_web(table: Any) -> WebSettings:
    """Check ``[web]``; a :class:`ConfigError` names the key and what it must be."""
    if not isinstance(table, dict):
        raise ConfigError("[web] must be a table")
    check_keys(table, _KEYS, "web")
    host = table.get("host", "127.0.0.1")
    port = table.get("port", DEFAULT_PORT)
    env = table.get("write_token_env")
    trend = table.get("trend_seconds", DEFAULT_TREND_SECONDS)
    if not isinstance(host, str) or not host:
        raise ConfigError("[web] host must be a non-empty string")
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ConfigError(f"[web] port must be 0..65535, got {port!r}")
    if env is not None and (not isinstance(env, str) or not env or "=" in env):
        raise ConfigError(f"[web] write_token_env must name an environment variable, got {env!r}")
    if (
        isinstance(trend, bool)
        or not isinstance(trend, int)
        or not 10 <= trend <= MAX_TREND_SECONDS
    ):
        raise ConfigError(
            f"[web] trend_seconds must be a whole number from 10 to {MAX_TREND_SECONDS},"
            f" got {trend!r}"
        )
    hosts = table.get("hosts", [])
    if not isinstance(hosts, list) or not all(
        isinstance(h, str) and _HOST_NAME.fullmatch(h) for h in hosts
    ):
        raise ConfigError(
            '[web] hosts must be a list of host names (e.g. ["gateway01",'
            f' "gateway01.plant.local"]), got {hosts!r}'
        )
    return WebSettings(host, port, env, trend, tuple(h.lower() for h in hosts))


def with_port(settings: WebSettings | None, port: int | None) -> WebSettings | None:
    """``--web-port`` over ``[web]``: the port replaced (or a console with defaults started)."""
    if port is None:
        return settings
    if not 0 <= port <= 65535:
        raise ValueError(f"--web-port must be 0..65535, got {port}")
    return dataclasses.replace(settings or WebSettings(), port=port)
