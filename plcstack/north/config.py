"""The north-side tables of the poll TOML: ``[mqtt]``, ``[metrics]``, ``[report]``, ``[influx]``,
``[opcua]``, ``[web]``, ``[modbus]``, ``[audit]``, ``[history]``.

They sit next to ``[poll]`` and ``[[plc]]`` in the same file; the poll loader keeps them as raw
tables (``PollConfig.north``) and checks them here at load time, so a typo is a
:class:`ConfigError` before anything is sent. Each table is optional: without ``[mqtt]`` there is
no MQTT sink, without ``[metrics]`` no HTTP server, without ``[report]`` every sample is reported.

```toml
[influx]
measurement = "plc"        # measurement name of --format influx (default "plc")
layout = "fields"          # a field per tag (default); "typed": a field per value type
```
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from plcstack.errors import ConfigError, check_keys
from plcstack.north.audit import AuditSettings, parse_audit
from plcstack.north.history.settings import HistorySettings, parse_history
from plcstack.north.influx import DEFAULT_LAYOUT, DEFAULT_MEASUREMENT, LAYOUTS
from plcstack.north.metrics import MetricsSettings, parse_metrics
from plcstack.north.modbus.config import ModbusSettings, parse_modbus
from plcstack.north.mqtt import MqttSettings, parse_mqtt
from plcstack.north.opcua_config import OpcUaConfig, parse_opcua_config
from plcstack.north.rbe import PASS_ALL, parse_report
from plcstack.north.trace import TraceSettings, parse_trace
from plcstack.north.web.settings import WebSettings, parse_web
from plcstack.poll.config import PollConfig
from plcstack.poll.config import load_config as load_poll_config

__all__ = ["NORTH_TABLES", "NorthConfig", "load_config", "parse_north"]

_T = TypeVar("_T")

#: top-level TOML tables that belong to the north side
NORTH_TABLES = (
    "mqtt", "metrics", "report", "influx", "opcua", "web", "modbus", "audit", "history", "trace",
)  # fmt: skip


@dataclass(frozen=True)
class NorthConfig:
    mqtt: MqttSettings | None = None
    metrics: MetricsSettings | None = None
    report: Any = PASS_ALL
    influx_measurement: str = DEFAULT_MEASUREMENT
    #: ``[influx] layout``: "fields" (a field per tag) or "typed" (a field per value type)
    influx_layout: str = DEFAULT_LAYOUT
    #: ``[opcua]``: the settings of ``plcstack serve opcua`` (relative certificate paths taken
    #: relative to the TOML file)
    opcua: OpcUaConfig | None = None
    #: the web console and REST API (plcstack.north.web)
    web: WebSettings | None = None
    #: ``[modbus]``: the settings of ``plcstack serve modbus``
    modbus: ModbusSettings | None = None
    #: ``[audit]``: one JSON line per write attempt from any north side (north/audit.py)
    audit: AuditSettings | None = None
    #: ``[history]``: the embedded history (plcstack.north.history)
    history: HistorySettings | None = None
    #: ``[trace]``: the flight recorder (plcstack.north.trace)
    trace: TraceSettings | None = None

    @property
    def reports_by_exception(self) -> bool:
        return self.report is not PASS_ALL


def parse_north(tables: Mapping[str, Any], *, base: Path | None = None) -> NorthConfig:
    """The north-side tables; ``base`` = the TOML file's directory, for relative file paths
    (``[mqtt]`` ca_file, cert_file, key_file, buffer_path, state_path; ``[opcua]``
    certificates; ``[history]`` path). The poll loader checks without it; ``plcstack poll``
    passes it."""
    influx = _parsed(tables, "influx", _influx) or (DEFAULT_MEASUREMENT, DEFAULT_LAYOUT)
    report = _parsed(tables, "report", parse_report)
    return NorthConfig(
        mqtt=_parsed(tables, "mqtt", lambda t: parse_mqtt(t, base=base)),
        metrics=_parsed(tables, "metrics", parse_metrics),
        report=PASS_ALL if report is None else report,
        influx_measurement=influx[0],
        influx_layout=influx[1],
        opcua=_parsed(tables, "opcua", lambda t: parse_opcua_config(t, base=base)),
        web=_parsed(tables, "web", parse_web),
        modbus=_parsed(tables, "modbus", parse_modbus),
        audit=_parsed(tables, "audit", lambda t: parse_audit(t, base=base)),
        history=_parsed(tables, "history", lambda t: parse_history(t, base=base)),
        trace=_parsed(tables, "trace", lambda t: parse_trace(t, base=base)),
    )


def _parsed(tables: Mapping[str, Any], name: str, parse: Callable[[Any], _T]) -> _T | None:
    """``parse(tables[name])``, None without the table. A :class:`ConfigError` that does not
    say where it is gets the table as its ``key``, so the file loader points at least at the
    table's header line."""
    if name not in tables:
        return None
    try:
        return parse(tables[name])
    except ConfigError as exc:
        if exc.key is None:
            exc.key = name
        raise


def _influx(influx: Any) -> tuple[str, str]:
    """``[influx]``: (measurement, layout)."""
    if not isinstance(influx, dict):
        raise ConfigError("[influx] must be a table")
    check_keys(influx, ("measurement", "layout"), "influx")
    measurement = influx.get("measurement", DEFAULT_MEASUREMENT)
    if not isinstance(measurement, str) or not measurement.strip():
        raise ConfigError("[influx] measurement must be a non-empty string")
    influx_layout = influx.get("layout", DEFAULT_LAYOUT)
    if influx_layout not in LAYOUTS:
        raise ConfigError(
            f"[influx] layout must be {' or '.join(repr(x) for x in LAYOUTS)},"
            f" not {influx_layout!r}"
        )
    return measurement, influx_layout


def load_config(path: str | Path) -> tuple[PollConfig, NorthConfig]:
    """Read a poller TOML file once: the poll tables parsed by the poll layer, the north
    tables here (relative file paths taken relative to the file). A mistake in either is a
    :class:`ConfigError` with the file and line."""
    path = Path(path)
    parsed: list[NorthConfig] = []

    def north_tables(tables: Mapping[str, Any]) -> None:
        parsed.append(parse_north(tables, base=path.parent))

    poll = load_poll_config(path, tables=north_tables)
    return poll, parsed[0]
