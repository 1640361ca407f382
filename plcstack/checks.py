"""One set of checks for every table of the configuration file.

Every table of a plcstack TOML file (``[poll]``, ``[[plc]]``, ``[mqtt]``, ``[opcua]``, ``[web]``,
...) is read through a :class:`Table`, so the same mistake gets the same words whatever table it
is in: a :class:`~plcstack.errors.ConfigError` whose ``key`` (the dotted TOML path) lets the file
loader add ``FILE:LINE``, a "did you mean" for an unknown key, paths taken relative to the file,
sizes with or without a unit, and one spelling for a listening address, ``listen =
"HOST:PORT"``. An old spelling that still reads leaves a :class:`Notice` that the loader logs
once, as a WARNING with its line; a table read without a loader (the Python API) logs it at once.

The rule for names (PLCs, tags, scan groups) is here too (:func:`name_problem`): one rule, for
every face a name may reach, whichever faces a file configures.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Generic, TypeVar
from urllib.parse import urlsplit

from plcstack.errors import ConfigError, check_keys

__all__ = [
    "NAME_RULE",
    "Listen",
    "Notice",
    "ServerUrl",
    "Table",
    "TableSpec",
    "changed_tables",
    "name_problem",
    "parse_seconds",
    "parse_size",
    "read_tables",
    "table_names",
    "toml_array",
    "toml_table",
]

log = logging.getLogger("plcstack.config")

_T = TypeVar("_T")

_HOST: Final = re.compile(r"[A-Za-z0-9_.\-]+|\[[0-9A-Fa-f:.]+(?:%[A-Za-z0-9_.\-]+)?\]")


@dataclass(frozen=True, slots=True)
class Listen:
    """Where a listening face binds: ``host`` (a name, an IPv4 or an IPv6 address, without
    brackets) and ``port`` (0: any free port)."""

    host: str
    port: int

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"

    @classmethod
    def parse(cls, text: object, *, default_host: str | None = None) -> Listen:
        """``"HOST:PORT"`` (``"[::1]:4840"`` for IPv6) as a :class:`Listen`; a bare ``"PORT"``
        only when ``default_host`` is given (command-line options). ValueError saying the form
        otherwise."""
        form = '"HOST:PORT" (e.g. "127.0.0.1:8080", "0.0.0.0:502", "[::1]:4840")'
        if not isinstance(text, str):
            raise ValueError(f"must be {form}, not {text!r}")
        host, colon, port = text.strip().rpartition(":")
        if not colon:
            host, port = "", text.strip()
            if default_host is None:
                raise ValueError(f"must be {form}, not {text!r}: the port is missing")
            host = default_host
        elif ":" in host and not host.startswith("["):
            raise ValueError(f"must be {form}, not {text!r}: write an IPv6 address in brackets")
        elif not host or not _HOST.fullmatch(host):
            raise ValueError(f"must be {form}, not {text!r}")
        if host.startswith("["):
            host = host[1:-1]
        if not port.isascii() or not port.isdigit() or int(port) > 65535:
            raise ValueError(f"must be {form} with a port 0..65535, not {text!r}")
        return cls(host, int(port))


@dataclass(frozen=True, slots=True)
class ServerUrl:
    """A server's URL as :meth:`Table.url` checked it: the ``text`` as written, its
    ``scheme``, ``host`` (without brackets) and ``port`` (None: the scheme's default)."""

    text: str
    scheme: str
    host: str
    port: int | None


@dataclass(frozen=True, slots=True)
class Notice:
    """Something the loader says once about a file that still loads (an old spelling, PLCs
    that will not all get a connection): the dotted TOML path it is about (or its ``line``,
    when a path cannot say it) and the message."""

    key: str | None
    message: str
    line: int | None = None


#: what a name may not contain, with the face that cannot carry it: the one rule for PLC,
#: tag and scan group names, whatever faces the file configures (a file that gains an
#: [mqtt] table later must not find its names refused then)
NAME_RULE: Final = (
    "a name becomes an MQTT topic level, a Sparkplug device or metric name, an OPC UA browse "
    "name, an Influx tag and a path of the web console's REST API, whichever of them a file "
    "configures"
)
_UNSAFE: Final = {"/": "a slash", "+": "a plus", "#": "a hash"}
#: a PLC name is the first part of its tags' OPC UA NodeIds ("PLC.TAG"): no dot, so no two
#: tags can get one NodeId
_PLC_UNSAFE: Final = {**_UNSAFE, ".": "a dot"}
_UNSAFE_WHY: Final = {
    "/": "a topic level and a path segment end there",
    "+": "an MQTT wildcard",
    "#": "an MQTT wildcard",
    ".": 'an OPC UA NodeId is "PLC.TAG"',
}


def name_problem(kind: str, name: object) -> str | None:
    """What is wrong with the name of a ``kind`` (``"PLC"``, ``"tag"``, ``"scan group"``), or
    None. The rule and its reason are said once, here."""
    if not isinstance(name, str) or not name.strip():
        return f"a {kind} name must be a non-empty string, not {name!r}; {NAME_RULE}"
    unsafe = _PLC_UNSAFE if kind == "PLC" else _UNSAFE
    for char, what in unsafe.items():
        if char in name:
            return (
                f"{kind} name {name!r} contains {what} ({char}: {_UNSAFE_WHY[char]}); "
                f"a {kind} name may not contain {' '.join(unsafe)}, since {NAME_RULE}"
            )
    if name in (".", ".."):
        return f"{kind} name {name!r} is a path step; {NAME_RULE}"
    bad = next((c for c in name if ord(c) < 32 or ord(c) == 127), None)
    if bad is not None:
        return f"{kind} name {name!r} contains the control character {bad!r}; {NAME_RULE}"
    if name != name.strip():
        return f"{kind} name {name!r} begins or ends with a space; {NAME_RULE}"
    return None


_SIZE: Final = re.compile(r"\s*(\d+(?:\.\d+)?)\s*([KMGT]i?B|[kMGT]B|B)?\s*", re.IGNORECASE)
_UNITS: Final = {
    "b": 1,
    "kb": 1000,
    "mb": 1000**2,
    "gb": 1000**3,
    "tb": 1000**4,
    "kib": 1 << 10,
    "mib": 1 << 20,
    "gib": 1 << 30,
    "tib": 1 << 40,
}


def parse_size(value: object) -> int:
    """A number of bytes: an integer, or text with a unit (``"4 MiB"``, ``"500 kB"``,
    ``"1.5 GiB"``; KiB/MiB/GiB/TiB are powers of 1024, kB/MB/GB/TB of 1000). ValueError
    otherwise."""
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    if isinstance(value, str):
        m = _SIZE.fullmatch(value)
        if m:
            number, unit = m.group(1), (m.group(2) or "B").lower()
            if "." not in number:
                return int(number) * _UNITS[unit]
            size = float(number) * _UNITS[unit]
            if size.is_integer():
                return int(size)
    raise ValueError(f'must be a number of bytes (4194304, "4 MiB", "500 kB"), not {value!r}')


_DURATION: Final = re.compile(r"\s*(\d+(?:\.\d+)?)\s*(ms|s|m|min|h|d|w)?\s*", re.IGNORECASE)
_SECONDS: Final = {
    "ms": 0.001,
    "s": 1.0,
    "m": 60.0,
    "min": 60.0,
    "h": 3600.0,
    "d": 86400.0,
    "w": 7 * 86400.0,
}


def parse_seconds(value: object, *, zero: bool = False) -> float:
    """A duration in seconds: a finite number (``2.5``) or a text with a unit (``"500ms"``,
    ``"30s"``, ``"15m"``, ``"12h"``, ``"7d"``, ``"2w"``); greater than 0 (``zero``: or 0).
    ValueError otherwise."""
    seconds: float | None = None
    if isinstance(value, int | float) and not isinstance(value, bool):
        try:
            seconds = float(value)
        except OverflowError:  # an int too large for a float
            seconds = math.inf
    elif isinstance(value, str) and (m := _DURATION.fullmatch(value)) and m.group(2):
        seconds = float(m.group(1)) * _SECONDS[m.group(2).lower()]
    if seconds is None or not math.isfinite(seconds) or seconds < 0 or (seconds == 0 and not zero):
        sign = "0 or more" if zero else "greater than 0"
        raise ValueError(
            f"must be a number of seconds ({sign}) or a duration such as "
            f'"500ms", "30s", "15m", "12h", "7d", not {value!r}'
        )
    return seconds


def _duration(seconds: float) -> str:
    """A bound as people say it: ``10 minutes``, ``0.5 seconds``, ``7 days``."""
    for unit, size in (("day", 86400), ("hour", 3600), ("minute", 60)):
        if seconds >= size and seconds % size == 0:
            count = int(seconds // size)
            return f"{count} {unit}{'s' if count != 1 else ''}"
    return f"{_num(seconds)} second{'s' if seconds != 1 else ''}"


def _bytes(size: int) -> str:
    """A size bound as people write it: ``4 MiB``, ``500 kB``, ``1000 bytes``."""
    for unit in ("TiB", "GiB", "MiB", "KiB", "TB", "GB", "MB", "kB"):
        scale = _UNITS[unit.lower()]
        if size >= scale and size % scale == 0:
            return f"{size // scale} {unit}"
    return f"{size} bytes"


def _num(x: float) -> str:
    """A bound as people write it: ``3600``, ``0.5``, ``1000000000``."""
    return str(int(x)) if float(x).is_integer() else repr(float(x))


class Table:
    """One TOML table being read: its dotted path (``"mqtt"``, ``"opcua.users.bob"``), its
    values, the directory relative paths are taken from, and where its notices go.

    Every getter checks one key and returns its value or raises :class:`ConfigError` with
    ``key`` set to the key's dotted path, so the file loader points at the key's line.
    """

    __slots__ = ("base", "label", "notices", "path", "values")

    def __init__(
        self,
        values: Mapping[str, object],
        path: str,
        *,
        base: Path | None = None,
        notices: list[Notice] | None = None,
        label: str | None = None,
    ) -> None:
        self.values = values
        self.path = path
        #: how messages name the table (``[[gateway]] #2``); default ``[path]``
        self.label = label
        #: the TOML file's directory (relative paths), None: as written
        self.base = base
        #: where deprecation notices go (the loader logs them with their lines); None: logged
        #: at once, without a line
        self.notices = notices

    @classmethod
    def of(
        cls,
        raw: object,
        path: str,
        *,
        base: Path | None = None,
        notices: list[Notice] | None = None,
        label: str | None = None,
    ) -> Table:
        """``raw`` (a table as tomllib reads it, or a Table already) as a :class:`Table`;
        ConfigError ``[path] must be a table`` for anything else."""
        if isinstance(raw, Table):
            return raw
        if not isinstance(raw, Mapping):
            raise ConfigError(f"{label or f'[{path}]'} must be a table", key=path)
        return cls(raw, path, base=base, notices=notices, label=label)

    def sub(self, key: str, raw: object | None = None) -> Table:
        """The nested table at ``key`` (or ``raw``, a table found under it), same base and
        notices."""
        value = self.values.get(key) if raw is None else raw
        return Table.of(value, f"{self.path}.{key}", base=self.base, notices=self.notices)

    # -- errors, keys and notices --------------------------------------------------------------
    @property
    def where(self) -> str:
        return self.label or f"[{self.path}]"

    def error(self, key: str | None, message: str) -> ConfigError:
        """``[path] KEY MESSAGE`` as a ConfigError pointing at ``key`` (the table itself: None)."""
        at = self.path if key is None else f"{self.path}.{key}"
        text = f"{self.where} {message}" if key is None else f"{self.where} {key} {message}"
        return ConfigError(text, key=at)

    def keys(self, known: Iterable[str], *, hint: str = "", where: str | None = None) -> None:
        """Every key is one of ``known``; else one error naming each unknown key with the
        known one it is closest to."""
        check_keys(self.values, known, self.path, where=where or self.label, hint=hint)

    def notice(self, key: str, message: str) -> None:
        """Say ``message`` once about ``key`` (an old spelling that still loads)."""
        at = f"{self.path}.{key}"
        if self.notices is None:
            log.warning("%s", message)
        elif not any(n.key == at and n.message == message for n in self.notices):
            self.notices.append(Notice(at, message))

    def __contains__(self, key: object) -> bool:
        return key in self.values

    def raw(self, key: str, default: object = None) -> object:
        return self.values.get(key, default)

    # -- values ------------------------------------------------------------------------------
    def text(self, key: str, default: str) -> str:
        """A non-empty string."""
        value = self.values.get(key, default)
        if not isinstance(value, str) or not value.strip():
            raise self.error(key, f"must be a non-empty string, not {value!r}")
        return value

    def optional_text(self, key: str) -> str | None:
        """A non-empty string, or None without the key."""
        if key not in self.values:
            return None
        return self.text(key, "")

    def boolean(self, key: str, default: bool) -> bool:
        value = self.values.get(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f"must be true or false, not {value!r}")
        return value

    def integer(self, key: str, default: int, lo: int, hi: int) -> int:
        """A whole number in ``lo..hi``."""
        value = self.values.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise self.error(key, f"must be {lo}..{hi}, not {value!r}")
        return value

    def number(self, key: str, default: float, lo: float, hi: float) -> float:
        """A finite number in ``lo..hi``."""
        value = self.values.get(key, default)
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
            or not lo <= value <= hi
        ):
            raise self.error(key, f"must be a number from {_num(lo)} to {_num(hi)}, not {value!r}")
        return float(value)

    def seconds(
        self, key: str, default: float, *, lo: float = 0.0, hi: float = 86400.0, zero: str = ""
    ) -> float:
        """A duration in ``lo..hi`` seconds: a number of seconds or a text with a unit
        (:func:`parse_seconds`). ``lo`` 0: greater than 0, unless ``zero`` says what 0 means
        (then 0 is taken too)."""
        value = self.values.get(key, default)
        try:
            seconds = parse_seconds(value, zero=zero != "")
        except ValueError as exc:
            raise self.error(key, str(exc) + (f" (0: {zero})" if zero else "")) from None
        if (seconds < lo or seconds > hi) and not (zero and seconds == 0):
            if lo > 0 and math.isinf(hi):
                span = f"at least {_duration(lo)}"
            elif lo > 0:
                span = f"from {_duration(lo)} to {_duration(hi)}"
            else:
                span = f"at most {_duration(hi)}"
            raise self.error(key, f"must be {span}, not {value!r}")
        return seconds

    def size(self, key: str, default: int, lo: int, hi: int) -> int:
        """A number of bytes in ``lo..hi`` (an integer or ``"4 MiB"``: :func:`parse_size`)."""
        value = self.values.get(key, default)
        try:
            size = parse_size(value)
        except ValueError as exc:
            raise self.error(key, str(exc)) from None
        if not lo <= size <= hi:
            raise self.error(key, f"must be {_bytes(lo)} to {_bytes(hi)}, not {value!r}")
        return size

    def choice(self, key: str, default: _T, choices: Collection[_T]) -> _T:
        """One of ``choices``."""
        value = self.values.get(key, default)
        if value not in choices:
            listed = " or ".join(f'"{c}"' if isinstance(c, str) else repr(c) for c in choices)
            raise self.error(key, f"must be {listed}, not {value!r}")
        return value  # type: ignore[return-value]  # one of the choices

    def file(self, key: str, default: str | None = None, *, what: str = "a file") -> str | None:
        """A path (``~`` for the home directory) to ``what`` (a file, a folder), relative ones
        taken relative to the TOML file's directory; ``default`` (taken the same way) without
        the key."""
        value = self.values.get(key, default)
        if value is None:
            return None
        if not isinstance(value, str) or not value.strip() or "\x00" in value:
            raise self.error(key, f"must name {what}, not {value!r}")
        path = Path(value).expanduser()
        if self.base is None or path.is_absolute():
            return str(path)
        return str(self.base / path)

    def url(self, key: str, default: str, schemes: Collection[str]) -> ServerUrl:
        """A server's URL (``mqtt://broker:1883``, ``http://influx:8086``): one of
        ``schemes``, a host, a port that is a port, no query, and no credentials (a file names
        the environment variables that hold them, ``username_env`` and ``password_env``)."""
        value = self.values.get(key, default)
        if not isinstance(value, str) or not value.strip():
            raise self.error(key, f"must be a non-empty string, not {value!r}")
        forms = " or ".join(f"{scheme}://HOST:PORT" for scheme in schemes)
        parts = urlsplit(value)
        host = parts.hostname
        if parts.scheme not in schemes or not host or parts.query or parts.fragment:
            raise self.error(key, f"must be {forms}, not {value!r}")
        try:
            port = parts.port
        except ValueError:
            raise self.error(key, f"has a bad port: {value!r}") from None
        if parts.username is not None or parts.password is not None:
            raise self.error(
                key,
                "must not carry credentials: name the environment variables that hold them"
                " with username_env and password_env",
            )
        return ServerUrl(value, parts.scheme, host, port)

    def optional_url(self, key: str, schemes: Collection[str]) -> ServerUrl | None:
        """:meth:`url`, or None without the key."""
        if key not in self.values:
            return None
        return self.url(key, "", schemes)

    def listen(self, default: Listen) -> Listen:
        """``listen = "HOST:PORT"`` (``default`` without it). The old ``host`` and ``port``
        keys still load (a notice names the new spelling); the caller lists them among its
        known keys if the table ever had them."""
        old = [k for k in ("host", "port") if k in self.values]
        if "listen" in self.values:
            if old:
                raise self.error(
                    old[0], f"and listen both say where to listen: keep listen, drop {old[0]}"
                )
            try:
                return Listen.parse(self.values["listen"])
            except ValueError as exc:
                raise self.error("listen", str(exc)) from None
        if not old:
            return default
        host = self.text("host", default.host)
        port = self.integer("port", default.port, 0, 65535)
        try:
            listen = Listen.parse(f"[{host}]:{port}" if ":" in host else f"{host}:{port}")
        except ValueError:
            raise self.error("host", f"must be a host name or address, not {host!r}") from None
        self.notice(old[0], self.deprecated(" and ".join(old), f'listen = "{listen}"'))
        return listen

    def deprecated(self, old: str, new: str) -> str:
        """The one wording of a deprecation: ``[web] host and port are deprecated: write
        listen = "127.0.0.1:8080" instead (they still load)``."""
        verb = "are" if " and " in old else "is"
        return (
            f"{self.where} {old} {verb} deprecated: write {new} instead"
            " (the old spelling still loads)"
        )


# -- the tables of a configuration dataclass ------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TableSpec(Generic[_T]):
    """A top-level TOML table and the function that reads it (``parse(Table) -> settings``);
    ``array``: an array of tables (``[[name]]``), each read by ``parse``, the field a tuple."""

    name: str
    parse: Callable[[Table], _T]
    array: bool = False


def toml_table(name: str, parse: Callable[[Table], Any]) -> Mapping[str, TableSpec[Any]]:
    """The metadata of a dataclass field read from the top-level table ``[name]`` by
    ``parse``: ``mqtt: MqttSettings | None = field(default=None, metadata=toml_table("mqtt",
    parse_mqtt))``. Adding a table to the configuration is one such field: the loader, the
    "unknown table" message and the reload diff follow it."""
    return {"table": TableSpec(name, parse)}


def toml_array(name: str, parse: Callable[[Table], Any]) -> Mapping[str, TableSpec[Any]]:
    """:func:`toml_table` for an array of tables ``[[name]]``: the field is the tuple of what
    ``parse`` reads from each (``[[gateway]] #2`` in its messages, its own lines)."""
    return {"table": TableSpec(name, parse, array=True)}


def _specs(cls: type[Any]) -> list[tuple[str, TableSpec[Any]]]:
    return [(f.name, f.metadata["table"]) for f in dataclasses.fields(cls) if "table" in f.metadata]


def changed_tables(old: object, new: object) -> tuple[str, ...]:
    """The top-level tables whose values differ between two instances of one configuration
    dataclass (its :func:`toml_table` fields, compared by value)."""
    if type(old) is not type(new):
        raise TypeError(f"cannot compare a {type(old).__name__} with a {type(new).__name__}")
    return tuple(
        spec.name
        for field_name, spec in _specs(type(old))
        if getattr(old, field_name) != getattr(new, field_name)
    )


def table_names(cls: type[Any]) -> tuple[str, ...]:
    """The top-level tables the :func:`toml_table` fields of ``cls`` read."""
    return tuple(spec.name for _, spec in _specs(cls))


def read_tables(
    cls: type[Any],
    data: Mapping[str, object],
    *,
    base: Path | None = None,
    notices: list[Notice] | None = None,
) -> dict[str, Any]:
    """The values of the :func:`toml_table` fields of ``cls`` whose tables are in ``data``
    (field name -> value). A :class:`ConfigError` that does not say where it is gets the
    table's name as its ``key``, so the file loader points at least at the table's header."""
    values: dict[str, Any] = {}
    for field_name, spec in _specs(cls):
        if spec.name not in data:
            continue
        try:
            if spec.array:
                values[field_name] = _read_array(spec, data[spec.name], base, notices)
                continue
            table = Table.of(data[spec.name], spec.name, base=base, notices=notices)
            values[field_name] = spec.parse(table)
        except ConfigError as exc:
            if exc.key is None:
                exc.key = spec.name
            raise
    return values


def _read_array(
    spec: TableSpec[Any], raw: object, base: Path | None, notices: list[Notice] | None
) -> tuple[Any, ...]:
    """Each table of the array ``[[spec.name]]`` read by ``spec.parse``, as a tuple."""
    name = spec.name
    if not isinstance(raw, list):
        raise ConfigError(f"{name} must be an array of tables: write [[{name}]]", key=name)
    items = []
    for index, item in enumerate(raw):
        label = f"[[{name}]] #{index + 1}"
        path = f"{name}[{index}]"
        items.append(spec.parse(Table.of(item, path, base=base, notices=notices, label=label)))
    return tuple(items)
