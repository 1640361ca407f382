"""One option schema per client, shared by the URL query and keyword arguments.

``e71+tcp://h:5000?code=ascii&timeout=1.5`` and ``connect("e71+tcp://h:5000", code="ascii",
timeout=1.5)`` go through the same :class:`Option` objects: the same names, defaults, ranges and
error messages, whichever way an option arrives (a keyword wins over the query). Every problem is
an :class:`~plcstack.errors.OptionError` naming the option and the PLC: an unknown name (a typo
like ``tiemout=3`` says "did you mean timeout?"), a value of the wrong kind or out of range, an
option of another protocol. Nothing is sent before the options are checked.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

from plcstack.durations import check_seconds
from plcstack.errors import AddressError, OptionError
from plcstack.transports.backoff import Backoff
from plcstack.url import PlcUrl

__all__ = [
    "COMMON",
    "Option",
    "choice",
    "flag",
    "integer",
    "keyword_only",
    "resolve",
    "seconds",
]

_TRUE: Final = {"1", "true", "yes", "on"}
_FALSE: Final = {"0", "false", "no", "off"}


@dataclass(frozen=True, slots=True)
class Option:
    """One option: ``parse`` turns URL text into a value, ``check`` validates a value from
    either source and returns it normalised (both raise ``ValueError`` with the reason)."""

    name: str
    default: object
    parse: Callable[[str], object]
    check: Callable[[object], object]
    doc: str
    #: False for options only a keyword can carry (a Backoff object)
    in_url: bool = True

    def value(self, raw: object, *, from_url: bool) -> object:
        """``raw`` checked (and parsed first when it is URL text)."""
        try:
            return self.check(self.parse(raw) if from_url and isinstance(raw, str) else raw)
        except (ValueError, TypeError, AddressError) as exc:
            reason = exc.message if isinstance(exc, AddressError) else str(exc)
            # a check that already names the option (check_seconds does) is not prefixed twice
            prefix = (
                "" if reason.startswith(f"option {self.name}=") else f"option {self.name}={raw!r}: "
            )
            raise OptionError(f"{prefix}{reason}", option=self.name) from None


def _same(text: str) -> object:
    return text


def seconds(name: str, default: float | None, doc: str) -> Option:
    """A duration: a finite number of seconds > 0 (``check_seconds``); ``None`` = not set."""

    def check(value: object) -> object:
        if value is None and default is None:
            return None  # "not set" is a value of this option (e.g. no life acks)
        return check_seconds(name, value)

    return Option(name, default, float, check, doc)


def integer(name: str, default: int | None, lo: int, hi: int, doc: str, *, base: int = 0) -> Option:
    def parse(text: str) -> object:
        return int(text, base)

    def check(value: object) -> object:
        if value is None and default is None:
            return None  # "not set" is a value of this option
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError("not an integer")
        if not lo <= value <= hi:
            raise ValueError(f"outside {lo}..{hi}")
        return value

    return Option(name, default, parse, check, doc)


def choice(name: str, default: object, choices: Sequence[object], doc: str) -> Option:
    """One of ``choices``; an enum member is compared by its ``value``. URL text is matched
    case-insensitively against the text of each choice."""

    def parse(text: str) -> object:
        for c in choices:
            if str(c).lower() == text.lower():
                return c
        return text

    def check(value: object) -> object:
        plain = getattr(value, "value", value)
        if isinstance(plain, bool) or plain not in choices:
            raise ValueError(f"not one of {', '.join(str(c) for c in choices)}")
        return plain

    return Option(name, default, parse, check, doc)


def flag(name: str, default: bool, doc: str) -> Option:
    def parse(text: str) -> object:
        low = text.lower()
        if low in _TRUE:
            return True
        if low in _FALSE:
            return False
        raise ValueError("not a boolean (1/0, true/false, yes/no, on/off)")

    def check(value: object) -> object:
        if value in (0, 1) and isinstance(value, int):
            return bool(value)
        raise ValueError("not a boolean")

    return Option(name, default, parse, check, doc)


def keyword_only(name: str, default: object, kind: type, doc: str) -> Option:
    """An option only Python can give (an object, not text)."""

    def check(value: object) -> object:
        if value is not None and not isinstance(value, kind):
            raise ValueError(f"not a {kind.__name__}")
        return value

    return Option(name, default, _same, check, doc, in_url=False)


#: the options every client takes
COMMON: Final = (
    seconds("timeout", 2.0, "request deadline in seconds"),
    seconds("connect_timeout", 3.0, "deadline of a connection attempt in seconds"),
    keyword_only("backoff", None, Backoff, "reconnect backoff (Python only)"),
)


def _suggest(name: str, known: Sequence[str]) -> str:
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
    return f": did you mean {close[0]}?" if close else ""


def resolve(
    schema: Sequence[Option],
    url: PlcUrl,
    keywords: Mapping[str, object],
    *,
    other: Sequence[str] = (),
) -> dict[str, Any]:
    """Every option of ``schema`` from ``keywords`` (first), the URL query, or its default.

    ``other`` names options of other protocols, so ``code=ascii`` on an S5 URL says that it
    belongs elsewhere rather than only "unknown". Raises :class:`OptionError` bound to the URL.
    """
    by_name = {o.name: o for o in schema}
    known = sorted(by_name)
    try:
        for source, names in (("URL query", url.options), ("keyword", keywords)):
            for name in names:
                option = by_name.get(name)
                if option is not None and (source == "keyword" or option.in_url):
                    continue
                if name in by_name:
                    why = f"option {name} is given in Python only, not in a URL"
                elif name in other:
                    why = f"option {name} does not apply to {url.scheme}://"
                else:
                    why = f"unknown option {name} ({source}){_suggest(name, known)}"
                raise OptionError(
                    f"{why}; {url.scheme}:// takes: " + ", ".join(o.name for o in schema),
                    option=name,
                )
        out: dict[str, Any] = {}
        for option in schema:
            if option.name in keywords:
                out[option.name] = option.value(keywords[option.name], from_url=False)
            elif option.in_url and option.name in url.options:
                out[option.name] = option.value(url.options[option.name], from_url=True)
            else:
                out[option.name] = option.default
        return out
    except OptionError as exc:
        raise exc.bind(plc=url.raw) from None
