"""The north side's tables of the configuration file: ``[mqtt]``, ``[metrics]``, ``[report]``,
``[influx]``, ``[opcua]``, ``[web]``, ``[modbus]``, ``[audit]``, ``[history]``, ``[trace]``.

They sit next to ``[poll]`` and ``[[plc]]`` in the same file, which
:func:`plcstack.config.load_config` reads once; each table is a field of :class:`NorthConfig`
whose metadata names the table and the function reading it
(:func:`plcstack.checks.toml_table`), so a table added here is one field. Each table is
optional: without ``[mqtt]`` there is no MQTT sink, without ``[metrics]`` no HTTP server,
without ``[report]`` every sample is reported.

```toml
[influx]
measurement = "plc"        # measurement name of --format influx (default "plc")
layout = "fields"          # a field per tag (default); "typed": a field per value type
```
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from plcstack.checks import Notice, read_tables, table_names, toml_table
from plcstack.north.audit import AuditSettings, parse_audit
from plcstack.north.history.settings import HistorySettings, parse_history
from plcstack.north.influx_config import InfluxSettings, parse_influx
from plcstack.north.metrics import MetricsSettings, parse_metrics
from plcstack.north.modbus.config import ModbusSettings, parse_modbus
from plcstack.north.mqtt import MqttSettings, parse_mqtt
from plcstack.north.opcua_config import OpcUaConfig, parse_opcua_config
from plcstack.north.rbe import PASS_ALL, Report, parse_report
from plcstack.north.trace import TraceSettings, parse_trace
from plcstack.north.web.settings import WebSettings, parse_web

__all__ = ["NORTH_TABLES", "NorthConfig", "parse_north"]


@dataclass(frozen=True)
class NorthConfig:
    """The north side's tables, typed; a table not in the file is its default (None: the
    face or sink is not run)."""

    mqtt: MqttSettings | None = field(default=None, metadata=toml_table("mqtt", parse_mqtt))
    metrics: MetricsSettings | None = field(
        default=None, metadata=toml_table("metrics", parse_metrics)
    )
    #: ``[report]``: report-by-exception (every sample without the table)
    report: Report = field(default=PASS_ALL, metadata=toml_table("report", parse_report))
    #: ``[influx]``: the line protocol of ``--format influx``
    influx: InfluxSettings = field(
        default=InfluxSettings(), metadata=toml_table("influx", parse_influx)
    )
    #: ``[opcua]``: the OPC UA server (relative certificate paths taken relative to the file)
    opcua: OpcUaConfig | None = field(
        default=None, metadata=toml_table("opcua", parse_opcua_config)
    )
    #: ``[web]``: the web console and REST API (plcstack.north.web)
    web: WebSettings | None = field(default=None, metadata=toml_table("web", parse_web))
    #: ``[modbus]``: the Modbus TCP server
    modbus: ModbusSettings | None = field(default=None, metadata=toml_table("modbus", parse_modbus))
    #: ``[audit]``: one JSON line per write attempt from any north side (north/audit.py)
    audit: AuditSettings | None = field(default=None, metadata=toml_table("audit", parse_audit))
    #: ``[history]``: the embedded history (plcstack.north.history)
    history: HistorySettings | None = field(
        default=None, metadata=toml_table("history", parse_history)
    )
    #: ``[trace]``: the flight recorder (plcstack.north.trace)
    trace: TraceSettings | None = field(default=None, metadata=toml_table("trace", parse_trace))

    @property
    def reports_by_exception(self) -> bool:
        return self.report is not PASS_ALL

    @property
    def influx_measurement(self) -> str:
        return self.influx.measurement

    @property
    def influx_layout(self) -> str:
        return self.influx.layout


#: top-level TOML tables that belong to the north side
NORTH_TABLES = table_names(NorthConfig)


def parse_north(
    tables: Mapping[str, object],
    *,
    base: Path | None = None,
    notices: list[Notice] | None = None,
) -> NorthConfig:
    """The north-side tables of a parsed file (``tables``: the whole file or just those
    tables); ``base`` = the TOML file's directory, for relative file paths (``[mqtt]``
    ca_file, cert_file, key_file, buffer_path, state_path; ``[opcua]`` certificates;
    ``[audit]`` and ``[history]`` path, ``[trace]`` dir). A
    :class:`~plcstack.errors.ConfigError` carries the key it is about."""
    return NorthConfig(**read_tables(NorthConfig, tables, base=base, notices=notices))
