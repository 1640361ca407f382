"""The Modbus server's settings (``[modbus]``) and its register map (each tag's ``modbus`` key).

```toml
[modbus]
listen = "127.0.0.1:5020"     # the default: loopback only ("0.0.0.0:502" for the plant network)
unit_id = 1                   # the unit identifier answered; requests to another get 0x0A
word_order = "big"            # two-register values: high word first ("little": low word first)
max_clients = 32              # clients at once; the next one is closed at once (logged once)
max_clients_per_host = 24     # of them from one host (default: 3/4 of max_clients)
first_request_timeout = 10    # seconds a new client has to send its first request (0: no limit)
idle_timeout = 600            # seconds a client may send nothing before it is dropped (0: never)

[[plc]]
name = "press1"
url = "e71+tcp://10.0.0.5:5000"
[plc.tags]
strokes = { address = "D100", type = "uint16", modbus = "hr:0" }
temp = { address = "D102", type = "float32", modbus = "ir:0" }      # ir:0 and ir:1
alarms = { address = "M0", type = "bool", count = 16, modbus = "di:0" }
```

``modbus = "TABLE:ADDRESS"``: ``hr`` holding register, ``ir`` input register, ``co`` coil, ``di``
discrete input; ADDRESS is the 0-based protocol address (0..65535), as sent on the wire. How many
registers a tag takes is in :mod:`plcstack.north.modbus.registers`. Two tags whose registers
overlap are refused when the file is loaded, naming both with their lines.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Mapping
from dataclasses import dataclass

from plcstack.checks import Listen, Table
from plcstack.errors import ConfigError
from plcstack.north.modbus.registers import TABLES, Layout, layout_for
from plcstack.poll.config import TagConfig
from plcstack.transports.guard import LIMIT_KEYS, Limits, parse_limits
from plcstack.values import WordOrder

__all__ = [
    "DEFAULT_ENDPOINT",
    "DEFAULT_IDLE_TIMEOUT",
    "DEFAULT_LIMITS",
    "DEFAULT_LISTEN",
    "DEFAULT_MAX_CLIENTS",
    "MapEntry",
    "ModbusSettings",
    "build_map",
    "parse_address",
    "parse_modbus",
]

DEFAULT_LISTEN = Listen("127.0.0.1", 5020)
DEFAULT_ENDPOINT = str(DEFAULT_LISTEN)
#: clients at once: enough for the panels and SCADA of a line; a flood of connections (a scan, a
#: client that leaks sockets) is turned away at the limit instead of taking the process's files
DEFAULT_MAX_CLIENTS = 32
#: seconds a client may send nothing: a dead panel (cable pulled, power cut) never says goodbye,
#: and its connection would count against ``max_clients`` for ever. Longer than any sane poll.
DEFAULT_IDLE_TIMEOUT = 600.0
#: what the server allows its clients (``[modbus]`` sets each; see plcstack.transports.guard)
DEFAULT_LIMITS = Limits(max_clients=DEFAULT_MAX_CLIENTS, idle_timeout=DEFAULT_IDLE_TIMEOUT)
_ADDRESS = re.compile(r"^\s*(hr|ir|co|di)\s*:\s*(\d{1,5})\s*$", re.IGNORECASE)


@dataclass(frozen=True)
class ModbusSettings:
    """Everything ``[modbus]`` sets."""

    host: str = DEFAULT_LISTEN.host
    port: int = DEFAULT_LISTEN.port
    unit_id: int = 1
    word_order: WordOrder = WordOrder.BIG
    #: clients at once and per host, the first-request and idle deadlines
    limits: Limits = DEFAULT_LIMITS

    @property
    def listen(self) -> Listen:
        return Listen(self.host, self.port)

    @property
    def endpoint(self) -> str:
        return str(self.listen)


def parse_address(text: object) -> tuple[str, int]:
    """``"hr:100"`` -> ``("hr", 100)``; ValueError with the grammar otherwise."""
    m = _ADDRESS.match(text) if isinstance(text, str) else None
    if m is None or int(m.group(2)) > 0xFFFF:
        raise ValueError(
            f'modbus must be "hr:N", "ir:N", "co:N" or "di:N" with N 0..65535, not {text!r}'
        )
    return m.group(1).lower(), int(m.group(2))


def parse_modbus(table: object) -> ModbusSettings:
    """``[modbus]``: listen, unit_id, word_order and the client limits (max_clients,
    max_clients_per_host, first_request_timeout, idle_timeout); ConfigError
    naming the key otherwise. The old ``endpoint = "HOST:PORT"`` still loads, with a notice."""
    t = Table.of(table, "modbus")
    t.keys(("listen", "endpoint", "unit_id", "word_order", *LIMIT_KEYS))
    if "endpoint" in t:
        if "listen" in t:
            raise t.error(
                "endpoint", "and listen both say where to listen: keep listen, drop endpoint"
            )
        try:
            listen = Listen.parse(t.raw("endpoint"))
        except ValueError as exc:
            raise t.error("endpoint", str(exc)) from None
        t.notice("endpoint", t.deprecated("endpoint", f'listen = "{listen}"'))
    else:
        listen = t.listen(DEFAULT_LISTEN)
    unit_id = t.integer("unit_id", 1, 0, 255)
    word_order = WordOrder(t.choice("word_order", "big", ("big", "little")))
    limits = parse_limits(t, DEFAULT_LIMITS)
    return ModbusSettings(listen.host, listen.port, unit_id, word_order, limits)


@dataclass(frozen=True, slots=True)
class MapEntry:
    """One mapped tag: the PLC, the tag and its registers."""

    plc: str
    tag: TagConfig
    layout: Layout

    def describe(self) -> str:
        last = self.layout.end - 1
        start = self.layout.start
        span = str(start) if last == start else f"{start}..{last}"
        return f"tag {self.tag.name!r} of PLC {self.plc!r} ({self.layout.table}:{span})"


def build_map(
    plcs: Mapping[str, Mapping[str, tuple[TagConfig, int]]],
    *,
    source: str | None = None,
) -> list[MapEntry]:
    """Every tag with a ``modbus`` key, in address order; ConfigError for a bad key or overlap.

    ``plcs`` is PLC name -> tag name -> (tag, point bits), in the file's order (what
    ``Poller.tags`` gives); ``source`` the file the tags were read from: errors name it with
    each tag's line (which the poll loader noted, :attr:`TagConfig.line`), the file is not read
    again.
    """

    def where(tag: TagConfig) -> str:
        name = source or "<config>"
        return f"{name}:{tag.line}" if tag.line else name

    entries: list[tuple[MapEntry, str]] = []
    for plc, tags in plcs.items():
        for name, (tag, bits) in tags.items():
            if tag.modbus is None:
                continue
            try:
                table, start = parse_address(tag.modbus)
                layout = layout_for(tag, bits, table, start)
            except ValueError as exc:
                raise ConfigError(f"tag {name!r}: {exc} ({where(tag)})", plc=plc) from None
            entries.append((MapEntry(plc, tag, layout), where(tag)))
    entries.sort(key=lambda e: (TABLES.index(e[0].layout.table), e[0].layout.start))
    for (a, a_at), (b, b_at) in itertools.pairwise(entries):
        if a.layout.table == b.layout.table and b.layout.start < a.layout.end:
            raise ConfigError(
                f"modbus map: {b.describe()} ({b_at}) overlaps {a.describe()} ({a_at})"
            )
    return [entry for entry, _ in entries]
