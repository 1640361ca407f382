"""``connect(url)``: the scheme table and the one entry point that builds a client from a URL.

The table maps each URL scheme to its client class by direct import (no import strings), and
``connect`` lists every option of every protocol as an explicit keyword, so an editor completes
them and mypy checks their types. Options are checked by the client's schema
(:mod:`plcstack.clients.options`) whether they come from the query or a keyword; a keyword the
scheme does not take, a misspelt one included (``tiemout=3``), is an
:class:`~plcstack.errors.OptionError` naming it, not a ``TypeError``.
"""

from __future__ import annotations

import enum
import inspect
from typing import Final

from plcstack.clients.as511 import AS511Client
from plcstack.clients.base import Client
from plcstack.clients.e71 import E71Client
from plcstack.clients.fetchwrite import FetchWriteClient
from plcstack.clients.options import resolve
from plcstack.clients.s5lan import S5LanClient
from plcstack.transports.backoff import Backoff
from plcstack.url import parse_url

__all__ = ["SCHEMES", "connect"]

#: URL scheme -> client class (the URL forms are checked by :func:`plcstack.url.parse_url`)
SCHEMES: Final[dict[str, type[Client]]] = {
    "e71+tcp": E71Client,
    "e71+udp": E71Client,
    "s5lan": S5LanClient,
    "fetchwrite": FetchWriteClient,
    "as511": AS511Client,
    "as511+tcp": AS511Client,
}


class _Unset(enum.Enum):
    """Marks a keyword not given (``None`` is a value: "no write port", "default timer")."""

    UNSET = "unset"


UNSET: Final = _Unset.UNSET

#: every option name of every protocol, so one that belongs elsewhere is named as such
_ALL_OPTIONS: Final = frozenset(
    o.name for cls in SCHEMES.values() for o in (*cls.OPTIONS, *AS511Client.SERIAL_OPTIONS)
)


def connect(
    url: str,
    *,
    timeout: float | _Unset = UNSET,
    connect_timeout: float | _Unset = UNSET,
    backoff: Backoff | _Unset | None = UNSET,
    # E71 (e71+tcp, e71+udp)
    code: str | _Unset = UNSET,
    pc: int | _Unset = UNSET,
    monitoring_timer: int | _Unset | None = UNSET,
    rab_ascii_sub_chars: int | _Unset = UNSET,
    # S5-LAN-LINK (s5lan)
    header_byte_order: str | _Unset = UNSET,
    # AS511 (as511, as511+tcp)
    baud: int | _Unset = UNSET,
    parity: str | _Unset = UNSET,
    stopbits: float | _Unset = UNSET,
    char_timeout: float | _Unset = UNSET,
    response_timeout: float | _Unset | None = UNSET,
    nak_backoff: float | _Unset = UNSET,
    cache: bool | _Unset = UNSET,
    # FETCH/WRITE (fetchwrite)
    mk: bool | _Unset = UNSET,
    db_start: str | _Unset = UNSET,
    write_port: int | _Unset | None = UNSET,
    life_ack: float | _Unset | None = UNSET,
    life_timeout: float | _Unset | None = UNSET,
    mk_seq: bool | _Unset = UNSET,
    # S5-LAN, AS511, FETCH/WRITE
    strict: bool | _Unset = UNSET,
    **unknown: object,
) -> Client:
    """The client for ``url``; use it as ``async with connect(url) as plc:``.

    Keywords override the URL's query options. The connection is opened
    by ``async with`` or ``await plc.open()``, not here, so creating a client never blocks.
    Raises :class:`~plcstack.errors.AddressError` for a bad URL and
    :class:`~plcstack.errors.OptionError` for a bad or unknown option; nothing is sent.
    """
    given: dict[str, object] = {
        "timeout": timeout,
        "connect_timeout": connect_timeout,
        "backoff": backoff,
        "code": code,
        "pc": pc,
        "monitoring_timer": monitoring_timer,
        "rab_ascii_sub_chars": rab_ascii_sub_chars,
        "header_byte_order": header_byte_order,
        "baud": baud,
        "parity": parity,
        "stopbits": stopbits,
        "char_timeout": char_timeout,
        "response_timeout": response_timeout,
        "nak_backoff": nak_backoff,
        "cache": cache,
        "mk": mk,
        "db_start": db_start,
        "write_port": write_port,
        "life_ack": life_ack,
        "life_timeout": life_timeout,
        "mk_seq": mk_seq,
        "strict": strict,
    }
    keywords = {name: value for name, value in given.items() if value is not UNSET}
    keywords.update(unknown)
    parsed = parse_url(url)
    cls = SCHEMES[parsed.scheme]
    options = resolve(cls.options_for(parsed), parsed, keywords, other=sorted(_ALL_OPTIONS))
    return cls.create(parsed, options)


class _PerScheme:
    """A default that differs by scheme, as ``help(connect)`` shows it."""

    def __init__(self, text: str) -> None:
        self.text = text

    def __repr__(self) -> str:
        return self.text


def _shown_signature() -> inspect.Signature:
    """``connect``'s signature with each option's real default (from the client schemas) in
    place of the not-given marker, so ``help(plcstack.connect)`` says ``timeout: float = 2.0``.
    Only what ``help()`` and editors show changes; calls still tell "not given" from ``None``."""
    defaults: dict[str, dict[str, object]] = {}
    for scheme, cls in SCHEMES.items():
        serial = AS511Client.SERIAL_OPTIONS if cls is AS511Client else ()
        for option in (*cls.OPTIONS, *serial):
            defaults.setdefault(option.name, {})[scheme] = option.default
    signature = inspect.signature(connect)
    parameters = []
    for parameter in signature.parameters.values():
        per_scheme = defaults.get(parameter.name)
        if parameter.kind is inspect.Parameter.KEYWORD_ONLY and per_scheme:
            values = list(per_scheme.values())
            if all(v == values[0] for v in values):
                default: object = values[0]
            else:
                default = _PerScheme(
                    " / ".join(f"{scheme}: {value!r}" for scheme, value in per_scheme.items())
                )
            annotation = str(parameter.annotation).replace(" | _Unset", "")
            parameter = parameter.replace(default=default, annotation=annotation)
        parameters.append(parameter)
    return signature.replace(parameters=parameters)


connect.__signature__ = _shown_signature()  # type: ignore[attr-defined]
