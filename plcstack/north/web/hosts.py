"""Which ``Host`` the console answers: its own names only, so DNS rebinding reads nothing.

A web page on any site can make the browser of a machine on the plant network (the gateway's
own, an engineering laptop) talk to the console by rebinding a name of its own
(``attacker.example``) to the console's address: to the browser the page and the console are
then one origin, and the page reads what the console answers to a ``GET``. The browser still
sends ``Host: attacker.example``, which is how the console tells: it answers only requests for
a name it serves and refuses the others with 421 (Misdirected Request).

Served: no ``Host`` at all (HTTP/1.0 tools), any IP address (a rebinding needs a name), the
names ``localhost`` and ``*.localhost`` (browsers resolve them to loopback themselves), the
address the console binds when it is a name, this machine's host name, and the names listed in
``[web] hosts``; compared without the port and case-insensitively. The refusals are counted and
said once per burst (the first of a burst is one WARNING; a burst ends after
:data:`QUIET_SECONDS` without one), not once per request of a page that keeps trying.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import time
from collections.abc import Callable, Iterable

__all__ = ["QUIET_SECONDS", "HostCheck", "host_name"]

#: seconds without a refused request after which the next one is said again
QUIET_SECONDS = 60.0


def host_name(header: str) -> str:
    """The name in a ``Host`` header: without the port, lower case, no trailing dot; an IPv6
    address without its brackets."""
    value = header.strip().lower()
    if value.startswith("["):
        end = value.find("]")
        return value[1:end] if end > 0 else value
    if value.count(":") == 1:
        value = value.split(":", 1)[0]
    return value.rstrip(".")


def _is_address(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


class HostCheck:
    """Says whether a request's ``Host`` is one the console serves; counts and logs the rest."""

    def __init__(
        self,
        bind: str,
        names: Iterable[str],
        log: logging.Logger,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``bind``: the address the console listens on; ``names``: ``[web] hosts``."""
        own = {"localhost", socket.gethostname().lower()}
        if not _is_address(bind):
            own.add(bind.lower())
        self.names = frozenset(own | {n.lower() for n in names})
        self.log = log
        self.clock = clock
        #: requests refused, in all
        self.refused = 0
        self._burst = 0
        self._last: float | None = None

    def serves(self, header: str | None) -> bool:
        """Is ``header`` (the request's ``Host``, None if it sent none) one of ours?"""
        if header is None:
            return True
        name = host_name(header)
        return name in self.names or name.endswith(".localhost") or _is_address(name)

    def refused_request(self, header: str, peer: str | None, path: str) -> None:
        """Count a refused request; the first of a burst is one WARNING."""
        self.refused += 1
        now = self.clock()
        quiet = self._last is None or now - self._last >= QUIET_SECONDS
        self._last = now
        if not quiet:
            self._burst += 1
            return
        before, self._burst = self._burst, 1
        earlier = f" ({before} refused in the burst before)" if before > 1 else ""
        self.log.warning(
            "web console: refused a request for %s from %s (Host %r is not a name this console"
            " serves: a page on another site may be trying to read it through DNS rebinding;"
            " if the name is yours, add it to [web] hosts); further ones are counted, not"
            " logged, until %.0f s pass without one%s",
            path[:200],
            peer or "a client",
            header[:200],
            QUIET_SECONDS,
            earlier,
        )
