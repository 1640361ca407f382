"""``[web]``: where the console listens and which environment variable holds the write token.

```toml
[web]
listen = "127.0.0.1:8080"         # the default: loopback only (the page names every PLC);
                                  # port 0 = any free port
write_token_env = "PLCSTACK_WEB_TOKEN"   # writes are off unless this variable is set, non-empty
trend_seconds = 300               # how far back each tag's trend reaches (default 300)
hosts = ["gateway01", "gateway01.plant.local"]   # names the console answers to besides
                                  # localhost, IP addresses and this machine's own name
max_clients = 256                 # connections at once (a browser tab opens up to six)
max_clients_per_host = 192        # of them from one host (default: 3/4 of max_clients)
first_request_timeout = 10        # seconds a new connection has to send a complete request
idle_timeout = 75                 # seconds a connection may wait between requests (0: never)
```

The token itself never sits in the file: a config is copied, committed and mailed around; an
environment variable is set by the service manager of the one machine that runs the gateway.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

from plcstack.checks import Listen, Table
from plcstack.transports.guard import LIMIT_KEYS, Limits, parse_limits

__all__ = ["DEFAULT_LISTEN", "DEFAULT_PORT", "WebSettings", "parse_web"]

DEFAULT_LISTEN = Listen("127.0.0.1", 8080)
DEFAULT_PORT = DEFAULT_LISTEN.port
#: trend reach: one point per second at most, so this is also the ring's length per tag
DEFAULT_TREND_SECONDS = 300
MAX_TREND_SECONDS = 3600
_KEYS = {"listen", "host", "port", "write_token_env", "trend_seconds", "hosts", *LIMIT_KEYS}
#: connections at once: browsers open up to six per console tab, and 64 event streams are
#: served (``events.MAX_CLIENTS``); more is a flood. Idle: between two requests of a
#: connection (aiohttp's default, an hour, let a silent socket hold its slot that long); an
#: event stream is not idle, its request is complete.
DEFAULT_LIMITS = Limits(max_clients=256, idle_timeout=75.0)
#: a host name as a browser sends it in ``Host`` (letters, digits, dots, hyphens, underscores)
_HOST_NAME = re.compile(r"[A-Za-z0-9_]([A-Za-z0-9_.-]*[A-Za-z0-9_])?")


@dataclass(frozen=True)
class WebSettings:
    host: str = DEFAULT_LISTEN.host
    port: int = DEFAULT_LISTEN.port
    #: name of the environment variable holding the bearer token (None: writes are off)
    write_token_env: str | None = None
    trend_seconds: int = DEFAULT_TREND_SECONDS
    #: more names the console answers to (``Host``), besides localhost, IP addresses, its own
    #: ``host`` and this machine's name: a request for any other is refused (DNS rebinding)
    hosts: tuple[str, ...] = ()
    #: connections at once and per host, the first-request and idle deadlines
    limits: Limits = DEFAULT_LIMITS

    @property
    def listen(self) -> Listen:
        return Listen(self.host, self.port)

    def write_token(self) -> str | None:
        """The token from the environment now, or None when writes are off."""
        if self.write_token_env is None:
            return None
        return os.environ.get(self.write_token_env) or None


def parse_web(table: object) -> WebSettings:
    """Check ``[web]``; a :class:`ConfigError` names the key and what it must be."""
    t = Table.of(table, "web")
    t.keys(_KEYS)
    listen = t.listen(DEFAULT_LISTEN)
    env = t.raw("write_token_env")
    if env is not None and (not isinstance(env, str) or not env or "=" in env):
        raise t.error("write_token_env", f"must name an environment variable, not {env!r}")
    trend = t.integer("trend_seconds", DEFAULT_TREND_SECONDS, 10, MAX_TREND_SECONDS)
    hosts = t.raw("hosts", [])
    if not isinstance(hosts, list) or not all(
        isinstance(h, str) and _HOST_NAME.fullmatch(h) for h in hosts
    ):
        raise t.error(
            "hosts",
            'must be a list of host names (e.g. ["gateway01", "gateway01.plant.local"]),'
            f" not {hosts!r}",
        )
    limits = parse_limits(t, DEFAULT_LIMITS)
    return WebSettings(
        listen.host, listen.port, env, trend, tuple(h.lower() for h in hosts), limits
    )
