"""PLC URLs: one string names the protocol, the transport, the peer and the options.

``e71+tcp://10.0.0.5:5000?code=ascii`` reads better in a config file than five keyword arguments,
and the same string works in the CLI, the poller's TOML and the Python API.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field
from urllib.parse import parse_qsl, urlsplit

from plcstack.errors import AddressError

__all__ = ["URL_FORMS", "PlcUrl", "parse_url"]

#: scheme -> (needs host:port, needs a device path): the URL's syntax only. Which client serves
#: a scheme is the table in :mod:`plcstack.clients.connect` (this module imports no client).
URL_FORMS: dict[str, tuple[bool, bool]] = {
    "e71+tcp": (True, False),
    "e71+udp": (True, False),
    "s5lan": (True, False),
    "fetchwrite": (True, False),
    "as511": (False, True),
    "as511+tcp": (True, False),
}


@dataclass(frozen=True)
class PlcUrl:
    """A parsed PLC URL. ``options`` holds the query string as text; each client's option
    schema (:mod:`plcstack.clients.options`) checks and converts it."""

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


def _with_scheme(text: object) -> str:
    """What a URL without its scheme was probably meant as: ``10.0.0.5:5000`` or a port alone
    is the peer, and the protocol is the part that is missing."""
    if not isinstance(text, str) or not text or "/" in text:
        return ""
    peer = f"127.0.0.1:{text}" if text.isdigit() else text
    if ":" not in peer or not peer.rsplit(":", 1)[1].isdigit():
        return ""
    return f"; did you mean e71+tcp://{peer} or s5lan://{peer}?"


def _close_schemes(scheme: str) -> str:
    """``e71`` -> ``e71+tcp or e71+udp``: the protocol without its transport, or a typo."""
    close = [s for s in URL_FORMS if s.split("+")[0] == scheme.split("+")[0]]
    close = close or difflib.get_close_matches(scheme, list(URL_FORMS), n=1, cutoff=0.6)
    return f" (did you mean {' or '.join(close)}?)" if close else ""


def parse_url(url: str) -> PlcUrl:
    """Parse and check a PLC URL; every problem is an :class:`AddressError` naming the URL."""
    if not isinstance(url, str) or "://" not in url:
        raise AddressError(
            f"not a PLC URL (expected SCHEME://..., schemes: {', '.join(URL_FORMS)}"
            f"{_with_scheme(url)})",
            plc=str(url),
        )
    try:
        parts = urlsplit(url)
    except ValueError as exc:  # e.g. "Invalid IPv6 URL" for an unbalanced '[' in the host
        raise AddressError(f"malformed URL: {exc}", plc=url) from None
    scheme = parts.scheme.lower()
    if scheme not in URL_FORMS:
        raise AddressError(
            f"unknown scheme {scheme!r}{_close_schemes(scheme)}; known schemes: "
            f"{', '.join(URL_FORMS)}",
            plc=url,
        )
    needs_host, needs_path = URL_FORMS[scheme]
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
