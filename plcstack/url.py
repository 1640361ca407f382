"""PLC URLs: one string names the protocol, the transport, the peer and the options.

``e71+tcp://10.0.0.5:5000?code=ascii`` reads better in a config file than five keyword arguments,
and the same string works in the CLI, the poller's TOML and the Python API.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qsl, urlsplit

from plcstack.errors import AddressError

if TYPE_CHECKING:
    from plcstack.clients.base import Client

__all__ = ["SCHEMES", "PlcUrl", "connect", "parse_url"]

#: scheme -> (client class as "module:Class", needs host:port, needs a device path)
SCHEMES: dict[str, tuple[str, bool, bool]] = {
    "e71+tcp": ("plcstack.clients.e71:E71Client", True, False),
    "e71+udp": ("plcstack.clients.e71:E71Client", True, False),
    "s5lan": ("plcstack.clients.s5lan:S5LanClient", True, False),
    "fetchwrite": ("plcstack.clients.fetchwrite:FetchWriteClient", True, False),
    "as511": ("plcstack.clients.as511:AS511Client", False, True),
    "as511+tcp": ("plcstack.clients.as511:AS511Client", True, False),
}

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


@dataclass(frozen=True)
class PlcUrl:
    """A parsed PLC URL. ``options`` holds the query string; typed getters validate it."""

    raw: str
    scheme: str
    host: str | None = None
    port: int | None = None
    path: str | None = None
    options: dict[str, str] = field(default_factory=dict)

    @property
    def transport(self) -> str:
        """``tcp``, ``udp`` or ``serial``: the part after ``+`` or the protocol's only transport."""
        if "+" in self.scheme:
            return self.scheme.split("+", 1)[1]
        return "serial" if self.scheme == "as511" else "tcp"

    def check_options(self, allowed: set[str] | frozenset[str]) -> None:
        """Reject unknown query options: a typo like ``?db_strat=byte`` must not pass silently."""
        unknown = sorted(set(self.options) - set(allowed))
        if unknown:
            raise AddressError(
                f"unknown option(s) {', '.join(unknown)}; this scheme takes: "
                f"{', '.join(sorted(allowed)) or 'none'}",
                plc=self.raw,
            )

    def get_str(self, name: str, default: str, choices: tuple[str, ...] | None = None) -> str:
        value = self.options.get(name, default)
        if choices is not None and value not in choices:
            raise AddressError(
                f"option {name}={value!r} is not one of {', '.join(choices)}", plc=self.raw
            )
        return value

    def get_bool(self, name: str, default: bool) -> bool:
        if name not in self.options:
            return default
        value = self.options[name].lower()
        if value in _TRUE:
            return True
        if value in _FALSE:
            return False
        raise AddressError(
            f"option {name}={value!r} is not a boolean (1/0, true/false)", plc=self.raw
        )

    def get_int(self, name: str, default: int, lo: int | None = None, hi: int | None = None) -> int:
        if name not in self.options:
            return default
        try:
            value = int(self.options[name], 0)
        except ValueError:
            raise AddressError(
                f"option {name}={self.options[name]!r} is not an integer", plc=self.raw
            ) from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise AddressError(f"option {name}={value} is outside {lo}..{hi}", plc=self.raw)
        return value

    def get_float(self, name: str, default: float, lo: float = 0.0) -> float:
        if name not in self.options:
            return default
        try:
            value = float(self.options[name])
        except ValueError:
            raise AddressError(
                f"option {name}={self.options[name]!r} is not a number", plc=self.raw
            ) from None
        if not math.isfinite(value):
            # "inf" and "nan" parse as floats; no option of ours means anything infinite
            raise AddressError(f"option {name}={value} must be a finite number", plc=self.raw)
        if not value > lo:
            raise AddressError(f"option {name}={value} must be greater than {lo}", plc=self.raw)
        return value


def parse_url(url: str) -> PlcUrl:
    """Parse and check a PLC URL; every problem is an :class:`AddressError` naming the URL."""
    if not isinstance(url, str) or "://" not in url:
        raise AddressError(
            f"not a PLC URL (expected SCHEME://..., schemes: {', '.join(SCHEMES)})", plc=str(url)
        )
    try:
        parts = urlsplit(url)
    except ValueError as exc:  # e.g. "Invalid IPv6 URL" for an unbalanced '[' in the host
        raise AddressError(f"malformed URL: {exc}", plc=url) from None
    scheme = parts.scheme.lower()
    if scheme not in SCHEMES:
        raise AddressError(
            f"unknown scheme {scheme!r}; known schemes: {', '.join(SCHEMES)}", plc=url
        )
    _, needs_host, needs_path = SCHEMES[scheme]
    options: dict[str, str] = {}
    try:
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError:
        raise AddressError(f"malformed query string {parts.query!r}", plc=url) from None
    for key, value in pairs:
        if key in options:
            raise AddressError(f"option {key!r} given twice", plc=url)
        options[key] = value
    if needs_host:
        try:
            port = parts.port
        except ValueError:
            raise AddressError("port is not a number in 1..65535", plc=url) from None
        if not parts.hostname:
            raise AddressError("missing host (expected SCHEME://HOST:PORT)", plc=url)
        if port is None or port == 0:
            # No protocol here has a port every installation uses; guessing one would only
            # produce a confusing timeout against the wrong service.
            raise AddressError("missing port (expected SCHEME://HOST:PORT)", plc=url)
        if parts.path not in ("", "/"):
            raise AddressError(f"unexpected path {parts.path!r} after HOST:PORT", plc=url)
        return PlcUrl(url, scheme, parts.hostname, port, None, options)
    if needs_path:
        if parts.netloc:
            raise AddressError(
                "a serial URL has no host; write as511:///dev/ttyS0 (three slashes)", plc=url
            )
        if not parts.path or parts.path == "/":
            raise AddressError("missing device path (e.g. as511:///dev/ttyS0)", plc=url)
        return PlcUrl(url, scheme, None, None, parts.path, options)
    raise AssertionError("scheme table entry needs host or path")  # pragma: no cover


def client_class(scheme: str) -> type[Client]:
    """Import the client class for ``scheme``; a protocol not built yet is a clear error."""
    target = SCHEMES[scheme][0]
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            raise AddressError(
                f"scheme {scheme!r} is not built in this version of plcstack"
            ) from None
        raise
    cls: type[Client] = getattr(module, class_name)
    return cls


def connect(url: str, **options: Any) -> Client:
    """Create the client for ``url``. Use it as ``async with connect(url) as plc:``.

    Keyword options override the URL's query options (``timeout=2.0`` etc.); the connection is
    opened by ``async with`` or ``await plc.open()``, not here, so creating a client never blocks.
    """
    parsed = parse_url(url)
    return client_class(parsed.scheme).from_url(parsed, **options)
