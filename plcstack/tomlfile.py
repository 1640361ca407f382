"""A TOML file's text, parsed once, and the lines of its keys (tomllib keeps no positions).

Every error and notice about the configuration names ``FILE:LINE``; the parsers of the tables
say which key they mean (a dotted TOML path, :attr:`~plcstack.errors.ConfigError.key`) and this
finds its line. The text is parsed with a bound on nesting (a hostile file of 500 nested arrays
made tomllib's recursion escape as a traceback).
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from plcstack.errors import ConfigError

__all__ = ["MAX_TOML_DEPTH", "TomlFile", "toml_key", "toml_line", "toml_string"]

#: deepest nesting of tables and arrays a config may use; ours needs 4 ([[plc]] > tags > tag)
MAX_TOML_DEPTH: Final = 32
#: one part of a dotted key: bare, or quoted (then any character but the quote)
_PART: Final = r"""(?:"[^"]*"|'[^']*'|[\w\-]+(?:\[\d+\])?)"""
_HEADER: Final = re.compile(r"\s*\[\[?([^\[\]]+)\]\]?\s*(?:#.*)?$")
_KEY: Final = re.compile(rf"\s*({_PART}(?:\s*\.\s*{_PART})*)\s*=")
#: ``name[N]``: the N-th table (from 0) of the array of tables ``[[name]]``
_INDEXED: Final = re.compile(r"(.+)\[(\d+)\]")


@dataclass(frozen=True)
class TomlFile:
    """One configuration text: where it came from, its lines and what tomllib made of it."""

    source: str
    text: str
    data: dict[str, Any]
    lines: list[str] = field(repr=False)

    @classmethod
    def parse(cls, text: str, source: str = "<config>") -> TomlFile:
        """Parse ``text``; :class:`ConfigError` naming ``source`` for text that is not TOML
        or nests deeper than :data:`MAX_TOML_DEPTH`."""
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{source}: not valid TOML: {exc}") from None
        except RecursionError:
            # tomllib recurses per nesting level; 500 levels escaped as a traceback (exit 1)
            raise ConfigError(
                f"{source}: tables or arrays nested too deeply to parse "
                "(a poll config needs 4 levels)"
            ) from None
        if _depth(data) > MAX_TOML_DEPTH:
            raise ConfigError(
                f"{source}: tables or arrays nested more than {MAX_TOML_DEPTH} deep "
                "(a poll config needs 4 levels)"
            )
        return cls(source, text, data, text.splitlines())

    @classmethod
    def read(cls, path: str | Path) -> TomlFile:
        """Read and parse a file; :class:`ConfigError` naming it if it cannot be read."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"cannot read {path}: {exc.strerror or exc}") from None
        except UnicodeDecodeError as exc:
            raise ConfigError(
                f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})"
            ) from None
        return cls.parse(text, str(path))

    @property
    def base(self) -> Path | None:
        """The directory relative paths in the file are taken from (None: text given
        without a file)."""
        if self.source.startswith("<"):
            return None
        return Path(self.source).parent

    def line(self, path: str) -> int | None:
        """The line of a dotted TOML path (see :func:`toml_line`)."""
        return toml_line(self.lines, path)

    def at(self, line: int | None) -> str:
        """``FILE:LINE`` (``FILE`` without a line)."""
        return f"{self.source}:{line}" if line else self.source

    def error(self, exc: ConfigError) -> ConfigError:
        """``exc`` with ``(FILE:LINE)`` of its key added to its message."""
        line = self.line(exc.key) if exc.key else None
        return ConfigError(f"{exc.message} ({self.at(line)})", key=exc.key, plc=exc.plc)


def toml_line(lines: list[str], path: str) -> int | None:
    """The 1-based line of a dotted top-level TOML path (``"opcua.endpiont"``, ``"mqt"``,
    ``"report.rule.x"``) in a file's lines: the first ``key =`` line or ``[table]`` /
    ``[[table]]`` header that names it exactly, else the one that names the longest part of it
    (the table of an unknown key, or the line that opens an inline table). tomllib keeps no
    positions; every table's "unknown key" error (:class:`ConfigError` ``key``) is pointed at
    its line with this.

    The first part may name one table of an array of tables by its index: ``"gateway[1].listen"``
    is the ``listen`` of the second ``[[gateway]]``, found between its header and the next
    ``[[gateway]]``."""
    want = _toml_path(path)
    index: int | None = None
    if want and (m := _INDEXED.fullmatch(want[0])):
        want[0], index = m.group(1), int(m.group(2))
    best, best_len = None, 0
    table: list[str] = []
    seen = -1  # the [[array]] tables of want[0] met so far
    for i, line in enumerate(lines):
        if header := _HEADER.match(line):
            table = _toml_path(header.group(1))
            if index is not None and line.strip().startswith("[[") and table == want[:1]:
                seen += 1
            names = table
        elif key := _KEY.match(line):
            names = table + _toml_path(key.group(1))
        else:
            continue
        if index is not None and seen != index:
            continue
        if names == want:
            return i + 1
        common = len(names) if want[: len(names)] == names else 0
        if common > best_len:
            best, best_len = i + 1, common
    return best


def _toml_path(dotted: str) -> list[str]:
    """``'a . "b.c" . d'`` -> ``["a", "b.c", "d"]``: a dotted key's parts, quotes taken off."""
    return [part.strip("\"'") for part in re.findall(_PART, dotted)]


def toml_key(*parts: str) -> str:
    """The dotted path of ``parts``, each quoted unless it is a bare key (``groups."a/b"``)."""
    return ".".join(
        p if re.fullmatch(r"[\w\-]+", p) else '"' + p.replace('"', "") + '"' for p in parts
    )


_ESCAPES: Final = {
    '"': '\\"',
    "\\": "\\\\",
    "\b": "\\b",
    "\t": "\\t",
    "\n": "\\n",
    "\f": "\\f",
    "\r": "\\r",
}


def toml_string(text: str) -> str:
    """A TOML basic string: quotes, backslashes and every control character escaped."""
    out = []
    for char in text:
        if char in _ESCAPES:
            out.append(_ESCAPES[char])
        elif ord(char) < 0x20 or ord(char) == 0x7F:
            out.append(f"\\u{ord(char):04X}")
        else:
            out.append(char)
    return '"' + "".join(out) + '"'


def _depth(value: Any) -> int:
    """Nesting depth of parsed TOML, without recursion (so any depth tomllib accepted is safe)."""
    deepest = 0
    stack: list[tuple[Any, int]] = [(value, 1)]
    while stack:
        item, level = stack.pop()
        if isinstance(item, dict):
            children: Any = item.values()
        elif isinstance(item, list):
            children = item
        else:
            continue
        deepest = max(deepest, level)
        if level <= MAX_TOML_DEPTH:  # one level beyond the limit is enough to refuse
            stack.extend((child, level + 1) for child in children)
    return deepest
