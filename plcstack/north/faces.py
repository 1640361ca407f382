"""Which faces a configuration asks for, and how each is built: the one table of them.

Every face the runtime can run is one :class:`FaceKind` in :data:`FACES`: the TOML table that
configures it, the optional libraries it needs (checked before anything starts, so a missing
extra is one line naming the ``pip install``) and the function that builds it from a
:class:`FaceContext` (None: the file does not configure it). Adding a face is adding its row
here; the runtime (:mod:`plcstack.north.pipeline`) starts, feeds, supervises, health-checks and
stops every face the same way.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import TypeVar

from plcstack.north.config import NorthConfig
from plcstack.north.control import ConfigControl
from plcstack.north.face import Face, PollerView
from plcstack.north.health import Health
from plcstack.north.history import History
from plcstack.north.influx_sink import InfluxSink
from plcstack.north.layout import JsonLayout, scan_groups
from plcstack.north.metrics import MetricsServer, PlcstackCollector
from plcstack.north.mqtt import MqttSink
from plcstack.north.supervise import Supervisor
from plcstack.north.trace import TraceSink
from plcstack.north.writes import WritePath
from plcstack.output import float32_tags

__all__ = [
    "FACES",
    "FaceContext",
    "FaceKind",
    "Need",
    "build_face",
    "build_faces",
    "missing",
    "needs_of",
    "restarts",
]

_F = TypeVar("_F")

#: (what needs it, the module to import, the extra that installs it)
Need = tuple[str, str, str]


@dataclass(frozen=True)
class FaceContext:
    """What a face is built with: the run's poller view, its north-side configuration, its one
    write path, its supervisor, its metrics collector, the health of the whole run, the
    running configuration's control (what the web console's ``/api/config`` asks; None: the
    run cannot be reconfigured) and the faces built before it (the web console reads the
    history's)."""

    poller: PollerView
    config: NorthConfig
    writes: WritePath
    supervisor: Supervisor
    collector: PlcstackCollector
    health: Callable[[], list[Health]]
    #: whether a PLC is reachable (None before its first scan), by the rule of the MQTT status
    reachable: Callable[[str], bool | None]
    earlier: tuple[Face, ...] = ()
    control: ConfigControl | None = None

    def built(self, kind: type[_F]) -> _F | None:
        """The face of one class built before this one, if any."""
        return next((face for face in self.earlier if isinstance(face, kind)), None)


@dataclass(frozen=True)
class FaceKind:
    """One kind of face: ``build`` returns it, or None when the configuration has no table for
    it; ``needs`` lists the optional libraries the configured table needs; ``uses``: the
    tables of the faces it is built with (:meth:`FaceContext.built`), restarted with it when
    one of those restarts."""

    table: str
    build: Callable[[FaceContext], Face | None]
    needs: Callable[[NorthConfig], list[Need]]
    uses: tuple[str, ...] = ()


def _mqtt(ctx: FaceContext) -> Face | None:
    settings = ctx.config.mqtt
    if settings is None:
        return None
    poll = ctx.poller.config
    if settings.mode == "sparkplug":
        from plcstack.north.sparkplug import SparkplugLayout

        layout: JsonLayout | SparkplugLayout = SparkplugLayout.for_config(
            settings, poll, ctx.poller
        )
    else:
        layout = JsonLayout(
            settings.prefix,
            settings.client_id,
            settings.qos,
            float32_tags(poll.plcs),
            scan_groups(poll.plcs),
            plcs=[p.name for p in poll.plcs],
        )
    return MqttSink(settings, layout=layout, writes=ctx.writes, supervisor=ctx.supervisor)


def _mqtt_needs(config: NorthConfig) -> list[Need]:
    if config.mqtt is None:
        return []
    if config.mqtt.mode == "sparkplug":
        return [
            ("[mqtt] mode = sparkplug", "aiomqtt", "sparkplug"),
            ("[mqtt] mode = sparkplug", "google.protobuf", "sparkplug"),
        ]
    return [("[mqtt]", "aiomqtt", "mqtt")]


def _history(ctx: FaceContext) -> Face | None:
    if ctx.config.history is None:
        return None
    return History(ctx.config.history, supervisor=ctx.supervisor)


def _trace(ctx: FaceContext) -> Face | None:
    if ctx.config.trace is None:
        return None
    sink = TraceSink(ctx.config.trace)
    sink.attach(ctx.poller)  # rings on every PLC's connection from its next connect on
    return sink


def _influx(ctx: FaceContext) -> Face | None:
    if ctx.config.influx.url is None:
        return None
    return InfluxSink(ctx.config.influx, ctx.poller.config.plcs, supervisor=ctx.supervisor)


def _opcua(ctx: FaceContext) -> Face | None:
    if ctx.config.opcua is None:
        return None
    from plcstack.north.opcua import OpcUaServer  # asyncua: only when serving

    return OpcUaServer(ctx.poller, ctx.config.opcua, writes=ctx.writes, supervisor=ctx.supervisor)


def _modbus(ctx: FaceContext) -> Face | None:
    settings = ctx.config.modbus
    if settings is None:
        return None
    from plcstack.north.modbus.config import build_map
    from plcstack.north.modbus.server import ModbusServer

    poller = ctx.poller
    tags = {plc.name: poller.tags(plc.name) for plc in poller.config.plcs}
    entries = build_map(tags, source=poller.config.source)
    return ModbusServer(poller, settings, entries, writes=ctx.writes)


def _web(ctx: FaceContext) -> Face | None:
    if ctx.config.web is None:
        return None
    from plcstack.north.web.server import WebConsole  # aiohttp: only when serving

    return WebConsole(
        ctx.poller,
        ctx.config.web,
        writes=ctx.writes,
        supervisor=ctx.supervisor,
        health=ctx.health,
        history=ctx.built(History),
        reachable=ctx.reachable,
        trace=ctx.built(TraceSink),
        control=ctx.control,
    )


def _metrics(ctx: FaceContext) -> Face | None:
    if ctx.config.metrics is None:
        return None
    return MetricsServer(ctx.collector, ctx.config.metrics, ctx.health, supervisor=ctx.supervisor)


def _none(config: NorthConfig) -> list[Need]:
    return []


#: every face the runtime can run, in the order they start (and are fed)
FACES: tuple[FaceKind, ...] = (
    FaceKind("mqtt", _mqtt, _mqtt_needs),
    FaceKind("history", _history, _none),
    FaceKind("trace", _trace, _none),
    FaceKind(
        "influx",
        _influx,
        lambda c: [("[influx] url", "aiohttp", "influx")] if c.influx.url is not None else [],
    ),
    FaceKind(
        "opcua",
        _opcua,
        lambda c: [("[opcua]", "asyncua", "opcua")] if c.opcua is not None else [],
    ),
    FaceKind("modbus", _modbus, _none),
    FaceKind(
        "web",
        _web,
        lambda c: [("[web] or --web-port", "aiohttp", "web")] if c.web else [],
        uses=("history", "trace"),
    ),
    FaceKind(
        "metrics",
        _metrics,
        lambda c: [("[metrics]", "prometheus_client", "metrics")] if c.metrics else [],
    ),
)


def build_faces(ctx: FaceContext) -> dict[str, Face]:
    """The faces ``ctx.config`` configures, built, by the table of their kind, in the order of
    :data:`FACES` (a face that cannot be built raises a :class:`~plcstack.errors.ConfigError`
    naming what is wrong; nothing is started yet)."""
    faces: dict[str, Face] = {}
    for kind in FACES:
        face = build_face(kind, ctx, faces)
        if face is not None:
            faces[kind.table] = face
    return faces


def build_face(kind: FaceKind, ctx: FaceContext, built: Mapping[str, Face]) -> Face | None:
    """One face of ``kind`` (None: ``ctx.config`` has no table for it), built with the faces
    of the kinds it uses from ``built``."""
    earlier = tuple(built[table] for table in kind.uses if table in built)
    return kind.build(dataclasses.replace(ctx, earlier=earlier))


def restarts(tables: Collection[str]) -> list[FaceKind]:
    """The kinds of face a change of ``tables`` restarts, in the order of :data:`FACES`: each
    kind whose table changed, and each that uses one of them."""
    out: list[FaceKind] = []
    names: set[str] = set()
    for kind in FACES:
        if kind.table in tables or names.intersection(kind.uses):
            out.append(kind)
            names.add(kind.table)
    return out


def needs_of(config: NorthConfig) -> list[Need]:
    """``(what, module, extra)`` for each optional library the configured faces use."""
    return [need for kind in FACES for need in kind.needs(config)]


def missing(needs: Sequence[Need]) -> str | None:
    """The first of ``(what, module, extra)`` whose module cannot be imported, as one line
    naming the pip install that fixes it; None if all are there. Checked at start: a face
    whose library is missing would otherwise fail only inside its task, after the run began."""
    for what, module, extra in needs:
        try:
            importlib.import_module(module)
        except ImportError:
            return (
                f"{what} needs the Python package {module.split('.')[0]}, which is not installed:"
                f" pip install 'plcstack[{extra}]'"
            )
    return None
