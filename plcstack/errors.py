"""The one exception hierarchy of plcstack.

Every failure a caller can see is a :class:`PlcError`, so a gateway can catch one type per PLC and
keep polling the others. Messages are built to be read by an automation engineer at 3 a.m.: they
name the PLC (its URL), the request, and for PLC error codes the meaning from the protocol manual.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping, Sequence

__all__ = [
    "AddressError",
    "ConfigError",
    "ConnectFailed",
    "ConnectionLost",
    "LocalProtocolError",
    "OptionError",
    "PlcError",
    "PlcErrorResponse",
    "PlcTimeout",
    "RemoteProtocolError",
    "ValueDecodeError",
    "ValueEncodeError",
    "check_keys",
    "unknown_names",
]


class PlcError(Exception):
    """Base of every error plcstack raises.

    ``plc`` and ``request`` are optional because the codecs, which know neither the PLC's URL nor
    the caller's wording, raise these too; the client layer fills them in with :meth:`bind`.
    """

    def __init__(self, message: str, *, plc: str | None = None, request: str | None = None) -> None:
        self.message = message
        self.plc = plc
        self.request = request
        super().__init__(message)

    def bind(self, *, plc: str | None = None, request: str | None = None) -> PlcError:
        """Attach the PLC and request this error belongs to (first binding wins) and return self."""
        if self.plc is None:
            self.plc = plc
        if self.request is None:
            self.request = request
        return self

    def __str__(self) -> str:
        parts = [p for p in (self.plc, self.request) if p]
        parts.append(self.message)
        return ": ".join(parts)


class AddressError(PlcError, ValueError):
    """A URL, address, count or value is not valid for this protocol; nothing was sent."""


class ConfigError(AddressError):
    """A configuration file or table is invalid (the message names the file and line where
    they are known); nothing was sent to any PLC.

    An :class:`AddressError` so the CLI exits with the usage code 2, like any other bad input.
    Every layer that parses a table of the configuration raises it. ``key`` is the dotted TOML
    path of what is wrong (``"opcua.endpiont"``, ``"mqt"``) when the raiser knows it: the file
    loader, which alone has the text, turns it into the line to point at.
    """

    def __init__(
        self,
        message: str,
        *,
        key: str | None = None,
        plc: str | None = None,
        request: str | None = None,
    ) -> None:
        self.key = key
        super().__init__(message, plc=plc, request=request)


class OptionError(AddressError):
    """A connection option (URL query or keyword) is unknown or has a bad value; nothing was
    sent. ``option`` names it, so ``connect(url, tiemout=3)`` says which word is wrong."""

    def __init__(
        self, message: str, *, option: str, plc: str | None = None, request: str | None = None
    ) -> None:
        self.option = option
        super().__init__(message, plc=plc, request=request)


class ValueEncodeError(AddressError):
    """A value cannot be represented in its type (NaN as KG, 10000 as BCD16, a string too
    long); refused before anything was sent."""


class ValueDecodeError(PlcError):
    """The points read are not a valid value of the requested type (a BCD digit above 9):
    the PLC holds something else there, or the type is wrong. The connection is fine."""


class LocalProtocolError(PlcError):
    """Our own caller misused a codec or client (e.g. a second request while one is in flight)."""


class RemoteProtocolError(PlcError):
    """The peer sent bytes that do not follow the protocol. The connection is closed."""


class PlcErrorResponse(PlcError):
    """The PLC (or its communication module) answered the request with an error code.

    ``code`` is the protocol's own number (an E71 end code, an S5-LAN Err value, ...), ``meaning``
    the documented explanation; both go into the message so logs are self-explaining.
    """

    def __init__(
        self,
        code: int,
        meaning: str,
        *,
        plc: str | None = None,
        request: str | None = None,
        code_text: str | None = None,
    ) -> None:
        self.code = code
        self.meaning = meaning
        self.code_text = code_text if code_text is not None else f"{code:02X}H"
        super().__init__(
            f"PLC answered with error code {self.code_text}: {meaning}", plc=plc, request=request
        )


class PlcTimeout(PlcError, TimeoutError):
    """No (complete) answer within the deadline.

    The connection has been closed, so a late answer can never be taken for the reply to the next
    request. For a write, the outcome is unknown and the message says so.
    """


class ConnectionLost(PlcError, ConnectionError):
    """The connection dropped, or could not be used, while a request needed it."""


class ConnectFailed(ConnectionLost):
    """A connection could not be (re)established.

    A subclass of :class:`ConnectionLost` so code that only cares about "the PLC is not reachable"
    catches both, while a caller that wants to tell "never got in" from "dropped mid-request" can.
    """


def unknown_names(unknown: Sequence[str], known: Iterable[str]) -> str:
    """``"mqt (did you mean mqtt?), colour"``: unknown names, each with the known one it is
    closest to, for every "unknown key/table/option" message (a typo costs a lookup otherwise)."""
    choices = sorted(set(known))
    parts = []
    for name in unknown:
        close = difflib.get_close_matches(name, choices, n=1, cutoff=0.6)
        parts.append(f"{name} (did you mean {close[0]}?)" if close else name)
    return ", ".join(parts)


def check_keys(
    table: Mapping[str, object],
    known: Iterable[str],
    path: str,
    *,
    where: str | None = None,
    hint: str = "",
) -> None:
    """Every key of the TOML table at ``path`` (``"opcua"``, ``"opcua.users.bob"``) is known;
    else one :class:`ConfigError` ``[path]: unknown key(s) prot (did you mean port?)`` whose
    ``key`` is the first unknown one, so the file loader adds its line. ``where`` replaces
    ``[path]`` at the start (``[[report.rule]] #2``), ``hint`` ends the message (what to do)."""
    allowed = set(known)
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ConfigError(
            f"{where or f'[{path}]'}: unknown key(s) {unknown_names(unknown, allowed)}{hint}",
            key=f"{path}.{unknown[0]}",
        )
