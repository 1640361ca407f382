"""An OPC UA server in front of the poller: SCADA, MES and historians see the old PLCs as OPC UA.

A face of the runtime (:mod:`plcstack.north.pipeline`): ``[opcua]`` in the file of ``plcstack
poll`` (or ``plcstack serve opcua plant.toml``, the same runtime) serves it, fed with the
poller's scans after report-by-exception like every other face. Needs the optional extra
``plcstack[opcua]`` (asyncua, LGPL); nothing else in plcstack imports this module.

Address space (namespace ``urn:plcstack`` unless configured)::

    Objects/
      press1/                 Folder, NodeId ns=N;s=press1, description = the PLC's URL
        strokes               Variable, NodeId ns=N;s=press1.strokes, DataType UInt16
        alarms                Variable, Boolean[16] (a tag with count = 16)

Each sample becomes the variable's DataValue: the value, SourceTimestamp = the sample's source
time (when the request was sent), ServerTimestamp = when the server took it, and a StatusCode
from the sample's quality (:data:`STATUS_MAP`). A sample equal to the current value and status is
skipped, so SourceTimestamp is the time of the last change (OPC UA Part 4, 7.7.3) and a
subscription only hears of changes.

Writes. A client's Write of a tag's Value goes to :meth:`Poller.write_tag` (the same single-flight
connection the poller reads through) and its Write response is sent only when the PLC confirmed
the write or it failed; a failure returns the Bad status of :func:`write_status` and logs the full
:class:`PlcError` text (OPC UA status codes carry no text). The variable is not set from the
written value: the next poll shows what the PLC holds. Only tags with ``writable = true`` accept
writes, and only from sessions whose login may write (``anonymous = "write"`` or a user with
``write = true``).

How writes are intercepted, and why this way: asyncua calls ``InternalServer.attribute_service.
write(params, user)`` for every Write service call of a session and sends its per-item results as
the response. Replacing that one object with a subclass (:class:`_WriteService`) lets the server
await the PLC for each item and answer each with its own status. The other hooks do not fit:
``set_attribute_value_setter`` is synchronous (it cannot wait for a PLC) and an exception there
fails the whole request, and the PreWrite callback cannot change the results. The server's own
value updates go straight into the address space (``Server.write_attribute_value`` ->
``AddressSpace.write_attribute_value``), which never passes through the attribute service, so they
cannot reach a PLC; and a write that does reach it without a login of ours (the server's internal
session) is refused for tag variables.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from types import TracebackType
from typing import Any, Self, cast
from urllib.parse import urlsplit, urlunsplit

from asyncua import ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.address_space import AttributeService
from asyncua.server.internal_server import InternalServer
from asyncua.server.server import Server
from asyncua.ua.attribute_ids import AttributeIds
from asyncua.ua.object_ids import ObjectIds
from asyncua.ua.status_codes import StatusCodes as _S

from plcstack.errors import (
    PlcError,
)
from plcstack.north.face import FaceBase, PlcUpdate, PollerView
from plcstack.north.health import Health
from plcstack.north.opcua_config import (
    OpcUaConfig,
    load_opcua_config,
    parse_opcua_config,
)
from plcstack.north.opcua_services import by_node, install, set_build_info
from plcstack.north.opcua_types import (
    INITIAL_STATUS,
    STATUS_MAP,
    UNECE_NAMESPACE,
    read_status,
    unit_id,
    variant_type,
    write_status,
)
from plcstack.north.opcua_types import status as _status
from plcstack.north.opcua_users import (
    PlcUser,
    UserManagerOfConfig,
    limit_clients,
    session_peer,
    trust_list,
)
from plcstack.north.supervise import Supervised, Supervisor
from plcstack.north.write_values import parse_write_value
from plcstack.north.writes import WritePath, WriteResult
from plcstack.poll.config import ConfigError, TagConfig
from plcstack.poll.samples import Quality, Sample, Scan
from plcstack.transports.guard import FaceGuard, Limits

__all__ = [
    "STATUS_MAP",
    "OpcUaConfig",
    "OpcUaServer",
    "load_opcua_config",
    "parse_opcua_config",
    "read_status",
    "variant_type",
    "write_status",
]

log = logging.getLogger(__name__)


def _node(identifier: str | int, namespace: int = 0) -> ua.NodeId:
    return ua.NodeId(cast(ua.String, identifier), cast(ua.Int16, namespace))


def _utc(t: float) -> ua.DateTime:
    return cast(ua.DateTime, datetime.fromtimestamp(t, UTC))


# -- the address space --------------------------------------------------------------------------


class _SampleValue(ua.DataValue):
    """A DataValue this server builds once per sample and never changes afterwards.

    asyncua deep-copies the value for every monitored item it is written to (``MonitoredItem
    Values.set_current_datavalue``: "to prevent referencing the inner value"), which was about
    70 % of the cost of an update. Nothing mutates these objects (asyncua's data path replaces
    DataValues, it does not modify them), so the copy may be the object itself.
    """

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any]) -> _SampleValue:
        return self


@dataclass(slots=True)
class _Binding:
    """One tag variable: where its samples go and how a written value comes back."""

    plc: str
    tag: TagConfig
    nodeid: ua.NodeId
    vtype: ua.VariantType
    #: (status, value) last put into the variable: equal samples are skipped
    last: tuple[int, Any] = field(default=(INITIAL_STATUS, None))

    def variant(self, value: Any) -> ua.Variant:
        if self.vtype is ua.VariantType.Double:
            value = [float(v) for v in value] if isinstance(value, list) else float(value)
        elif self.vtype is ua.VariantType.String:  # KY pairs of bytes as "12,255"
            value = [_text(v) for v in value] if isinstance(value, list) else _text(value)
        return ua.Variant(value, self.vtype)

    def value_of(self, variant: ua.Variant | None) -> Any:
        """The Python value to hand to ``write_tag``; raises ValueError on a type mismatch."""
        if variant is None or variant.VariantType != self.vtype:
            raise ValueError("type mismatch")
        value = variant.Value
        if self.tag.count == 1 and isinstance(value, list | tuple):
            raise ValueError("array for a scalar")
        # the one value grammar of every north side (KY "12,255", lists of count values)
        return parse_write_value(self.tag, value, plc=self.plc)


def _same(a: _Binding | None, b: _Binding | None) -> bool:
    """Whether two bindings make the same variable (a reload keeps it as it is)."""
    return a is not None and b is not None and a.tag == b.tag and a.vtype == b.vtype


def same_value(a: Any, b: Any) -> bool:
    """Equality for "unchanged?", with NaN equal to NaN: a register stuck at a NaN pattern is
    one value, not a change every scan (plain ``==`` says NaN != NaN)."""
    if a == b:
        return True
    if isinstance(a, float) and isinstance(b, float):
        return a != a and b != b
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return all(same_value(x, y) for x, y in zip(a, b, strict=True))
    return False


def _text(value: Any) -> str:
    if isinstance(value, tuple):
        return ",".join(str(b) for b in value)
    return str(value)


def variable_description(tag: TagConfig) -> str:
    """A variable's Description: the engineer's text from the config first (what UaExpert shows
    as the tag's meaning), then where it lives (``M0 bool x4``), so a client without the config
    still sees the address and type."""
    count = f" x{tag.count}" if tag.count > 1 else ""
    where = f"{tag.address} {tag.type.name}{count}"
    return f"{tag.description} ({where})" if tag.description else where


def _tag_item(binding: _Binding, parent: ua.NodeId, idx: int, interval: float) -> ua.AddNodesItem:
    tag = binding.tag
    item = ua.AddNodesItem()
    item.RequestedNewNodeId = binding.nodeid
    item.BrowseName = ua.QualifiedName(tag.name, idx)
    item.NodeClass = ua.NodeClass.Variable
    item.ParentNodeId = parent
    item.ReferenceTypeId = _node(ObjectIds.Organizes)
    item.TypeDefinition = _node(_type_definition(tag))
    attrs = ua.VariableAttributes()
    attrs.DisplayName = ua.LocalizedText(tag.name)
    attrs.Description = ua.LocalizedText(variable_description(tag))
    attrs.DataType = _node(binding.vtype.value)
    if tag.count == 1:
        attrs.ValueRank = ua.ValueRank.Scalar
        attrs.Value = ua.Variant(None, ua.VariantType.Null)
    else:
        attrs.ValueRank = ua.ValueRank.OneDimension
        attrs.ArrayDimensions = [tag.count]
        attrs.Value = ua.Variant(None, ua.VariantType.Null)
    access = ua.AccessLevel.CurrentRead.mask
    if tag.writable:
        access |= ua.AccessLevel.CurrentWrite.mask
    attrs.AccessLevel = access
    attrs.UserAccessLevel = access
    attrs.MinimumSamplingInterval = interval * 1000.0  # ms: the tag's scan interval
    attrs.Historizing = False
    attrs.WriteMask = 0
    attrs.UserWriteMask = 0
    item.NodeAttributes = attrs
    return item


def _property_item(
    owner: ua.NodeId, owner_id: str, name: str, value: Any, datatype: int, idx: int
) -> ua.AddNodesItem:
    item = ua.AddNodesItem()
    item.RequestedNewNodeId = _node(f"{owner_id}#{name}", idx)
    item.BrowseName = ua.QualifiedName(name, 0)  # standard property names live in namespace 0
    item.NodeClass = ua.NodeClass.Variable
    item.ParentNodeId = owner
    item.ReferenceTypeId = _node(ObjectIds.HasProperty)
    item.TypeDefinition = _node(ObjectIds.PropertyType)
    attrs = ua.VariableAttributes()
    attrs.DisplayName = ua.LocalizedText(name)
    attrs.DataType = _node(datatype)
    attrs.Value = ua.Variant(value)
    attrs.ValueRank = ua.ValueRank.Scalar
    attrs.AccessLevel = ua.AccessLevel.CurrentRead.mask
    attrs.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
    item.NodeAttributes = attrs
    return item


def _eu_span(tag: TagConfig) -> tuple[float, float] | None:
    """The EURange (low, high) of a tag: its engineering span, if it has ``scale``."""
    if tag.scale is None:
        return None
    lo, hi = sorted((float(tag.scale.eng_lo), float(tag.scale.eng_hi)))
    return lo, hi


def _eu_items(binding: _Binding, idx: int) -> list[ua.AddNodesItem]:
    """EURange (from ``scale``) and EngineeringUnits (from ``unit``) of an analog tag."""
    tag = binding.tag
    text = f"{binding.plc}.{tag.name}"
    items = []
    span = _eu_span(tag)
    if span is not None:
        lo, hi = span
        items.append(
            _property_item(binding.nodeid, text, "EURange", ua.Range(lo, hi), ObjectIds.Range, idx)
        )
    if tag.unit is not None:
        info = ua.EUInformation(
            NamespaceUri=UNECE_NAMESPACE,
            UnitId=cast(ua.Int32, unit_id(tag.unit)),
            DisplayName=ua.LocalizedText(tag.unit),
            Description=ua.LocalizedText(tag.unit),
        )
        items.append(
            _property_item(
                binding.nodeid, text, "EngineeringUnits", info, ObjectIds.EUInformation, idx
            )
        )
    return items


def _type_definition(tag: TagConfig) -> int:
    """AnalogItemType when the tag is scaled (its EURange is mandatory there), BaseAnalogType
    with a unit only, else BaseDataVariableType."""
    if tag.scale is not None:
        return ObjectIds.AnalogItemType
    if tag.unit is not None:
        return ObjectIds.BaseAnalogType
    return ObjectIds.BaseDataVariableType


def _folder_item(name: str, description: str, idx: int) -> ua.AddNodesItem:
    item = ua.AddNodesItem()
    item.RequestedNewNodeId = _node(name, idx)
    item.BrowseName = ua.QualifiedName(name, idx)
    item.NodeClass = ua.NodeClass.Object
    item.ParentNodeId = _node(ObjectIds.ObjectsFolder)
    item.ReferenceTypeId = _node(ObjectIds.Organizes)
    item.TypeDefinition = _node(ObjectIds.FolderType)
    attrs = ua.ObjectAttributes()
    attrs.DisplayName = ua.LocalizedText(name)
    attrs.Description = ua.LocalizedText(description)
    attrs.EventNotifier = 0
    item.NodeAttributes = attrs
    return item


# -- writes ---------------------------------------------------------------------------------------


#: one tag write of a client's request: (value, the session's login, its client's address)
_Job = tuple[Any, str | None, str | None]

#: asyncua's default for callers that name no user (the server itself): an admin
_INTERNAL_USER = User(role=UserRole.Admin)


class _WriteService(AttributeService):
    """asyncua's attribute service with client writes of tag variables sent to the PLC.

    Items for other nodes (asyncua's own) go to the base class unchanged.
    """

    def __init__(self, iserver: InternalServer, owner: OpcUaServer) -> None:
        super().__init__(iserver.aspace)
        self._iserver = iserver
        self._owner = owner

    async def write(
        self, params: ua.WriteParameters, user: User = _INTERNAL_USER
    ) -> list[ua.StatusCode]:
        items = params.NodesToWrite
        results: list[ua.StatusCode | None] = [None] * len(items)
        others: list[int] = []
        jobs: dict[str, list[tuple[int, _Binding, _Job]]] = {}
        owner = self._owner
        bindings = owner.bindings
        # the session's login and client address for the audit (None: anonymous or the server
        # itself; no address for the server's own calls)
        login = user.name if isinstance(user, PlcUser) else None
        peer = session_peer(self._iserver, user)
        for i, item in enumerate(items):
            binding = bindings.get(item.NodeId)
            if binding is None:
                others.append(i)
                continue
            allowed = owner.writes.allowed(binding.plc, binding.tag.name)
            checked = _check_write(binding, item, user, allowed)
            if isinstance(checked, _Refusal):
                results[i] = _status(checked.status)
                # refused before the write path: logged and audited as every other attempt
                raw = item.Value.Value.Value if item.Value and item.Value.Value else None
                where = f"{binding.plc}: write {binding.tag.name}"
                owner.writes.refuse(
                    "opcua",
                    login,
                    binding.plc,
                    binding.tag.name,
                    raw,
                    checked.code,
                    f"{where}: {checked.reason}; not attempted",
                    peer=peer,
                )
            else:
                jobs.setdefault(binding.plc, []).append((i, binding, (checked, login, peer)))
        if others:
            rest = ua.WriteParameters()
            rest.NodesToWrite = [items[i] for i in others]
            for i, status in zip(others, await super().write(rest, user), strict=True):
                results[i] = status
        if jobs:
            for i, status in await owner.write_to_plcs(jobs):
                results[i] = status
        return [r if r is not None else _status(_S.BadInternalError) for r in results]


@dataclass(frozen=True, slots=True)
class _Refusal:
    """A write refused before anything is sent: the OPC UA status, the north side's result
    code (the words every write path answers and audits) and the reason in words."""

    status: int
    code: str
    reason: str


def _check_write(
    binding: _Binding, item: ua.WriteValue, user: User, allowed: WriteResult | None
) -> _Refusal | Any:
    """The value to write, or why the write is refused before anything is sent (``allowed``:
    the run's allow-list said None, or its refusal)."""
    if item.AttributeId != AttributeIds.Value:
        return _Refusal(_S.BadNotWritable, "not_writable", "only the Value attribute is written")
    if not isinstance(user, PlcUser):
        return _Refusal(_S.BadUserAccessDenied, "unauthorized", "not from a client session")
    if allowed is not None:
        return _Refusal(_S.BadNotWritable, allowed.code, "the tag is not writable = true")
    if not user.may_write:
        who = f"user {user.name}" if user.name else "an anonymous session"
        return _Refusal(_S.BadUserAccessDenied, "unauthorized", f"{who} may not write")
    if item.IndexRange:
        return _Refusal(_S.BadWriteNotSupported, "bad_request", "IndexRange is not written")
    data = item.Value
    if data is None:
        return _Refusal(_S.BadTypeMismatch, "wrong_type", "no value")
    if data.StatusCode is not None and not data.StatusCode.is_good():
        # a PLC holds values, not statuses
        return _Refusal(_S.BadWriteNotSupported, "bad_request", "a value with a bad status")
    try:
        return binding.value_of(data.Value)
    except ValueError as exc:
        return _Refusal(_S.BadTypeMismatch, "wrong_type", str(exc))


# -- the server -----------------------------------------------------------------------------------


class OpcUaServer(FaceBase):
    """An asyncua server whose address space mirrors the poller's PLCs and tags; a face of the
    runtime (:class:`~plcstack.north.face.Face`).

    ``start()`` builds the address space and listens; :meth:`submit` takes the scans (never
    blocks; a supervised task of the run applies them), or ``await`` :meth:`send` puts samples
    in at once. Every tag variable reads Bad_WaitingForInitialData until its first sample.
    ``writes``: the run's one write path (default: one on ``poller`` without an audit);
    ``supervisor``: the run's (default: its own).
    """

    name = "opcua"

    def __init__(
        self,
        poller: PollerView,
        config: OpcUaConfig | None = None,
        *,
        writes: WritePath | None = None,
        supervisor: Supervisor | None = None,
    ) -> None:
        self.poller = poller
        self.config = config if config is not None else OpcUaConfig()
        self._server: Server | None = None
        #: undoes the client limit's log filter (at stop)
        self._unlimit: Callable[[], None] = lambda: None
        config = self.config
        #: its limits (asyncua keeps them: clients at once, from any host alike, and a session
        #: activated in time) and what they refused and closed, by reason
        self.guard = FaceGuard(
            "opcua",
            "OPC UA server",
            Limits(
                max_clients=config.max_clients,
                max_clients_per_host=config.max_clients,
                first_request_timeout=config.first_request_timeout,
                idle_timeout=None,
            ),
            log,
        )
        #: every tag variable's binding by its NodeId (after :meth:`start`)
        self.bindings: dict[ua.NodeId, _Binding] = {}
        self._by_tag: dict[tuple[str, str], _Binding] = {}
        self._writes: set[asyncio.Future[Any]] = set()
        self.writes = writes if writes is not None else WritePath(poller)
        self.supervisor = supervisor if supervisor is not None else Supervisor()
        self.namespace_index = 0
        self.url = self.config.endpoint
        #: samples put into the address space / skipped as unchanged (for statistics)
        self.updates = 0
        self.unchanged = 0
        #: submitted samples replaced by a newer one of the same tag before they were applied
        self.coalesced = 0
        self._pending: dict[tuple[str, str], Sample] = {}
        self._wakeup = asyncio.Event()
        self._applier: Supervised | None = None
        self._plan_bindings()

    def _plan_bindings(self) -> None:
        """Every tag's node and type, before anything listens (a clash is a ConfigError)."""
        for plc in self.poller.plcs:
            if "." in plc:
                # the NodeId of a tag is "plc.tag": a dot in a PLC name could make two equal
                raise ConfigError(f"PLC name {plc!r}: the OPC UA server needs names without '.'")
            for name, (tag, bits) in self.poller.tags(plc).items():
                nodeid = _node(f"{plc}.{name}", 0)  # index fixed in start()
                self._by_tag[(plc, name)] = _Binding(plc, tag, nodeid, variant_type(tag, bits))
        # property NodeIds are "plc.tag#EURange": a tag named "x#EURange" would clash
        ids: set[str] = set(self.poller.plcs)
        for plc, name in self._by_tag:
            mine = [f"{plc}.{name}"]
            mine += [f"{plc}.{name}#{p}" for p in ("EURange", "EngineeringUnits")]
            for text in mine:
                if text in ids:
                    raise ConfigError(f"tag {name!r}: its OPC UA NodeId {text!r} is taken", plc=plc)
                ids.add(text)

    def nodeid(self, plc: str, tag: str) -> ua.NodeId:
        """The NodeId of a tag's variable (after :meth:`start`)."""
        return self._by_tag[(plc, tag)].nodeid

    @property
    def server(self) -> Server:
        """The asyncua server (after :meth:`start`), for what this class does not cover."""
        if self._server is None:
            raise RuntimeError("the OPC UA server is not started")
        return self._server

    # -- life cycle -------------------------------------------------------------------------
    async def start(self) -> None:
        if self._server is not None:
            return
        config = self.config
        server = Server(user_manager=UserManagerOfConfig(config))
        await server.init()
        server.set_endpoint(config.endpoint)
        server.set_server_name(config.server_name)
        await server.set_application_uri(f"{config.namespace}:server")
        server.set_security_policy([ua.SecurityPolicyType[p] for p in config.policies])
        tokens: list[type] = []
        if config.anonymous != "none":
            tokens.append(ua.AnonymousIdentityToken)
        if config.users:
            tokens.append(ua.UserNameIdentityToken)
        server.set_identity_tokens(tokens)
        if config.certificate is not None and config.private_key is not None:
            try:
                await server.load_certificate(str(config.certificate))
                await server.load_private_key(str(config.private_key))
            except (OSError, ValueError) as exc:
                raise ConfigError(f"opcua: cannot load certificate or private key: {exc}") from None
        if config.trusted_client_certificates is not None:
            server.set_certificate_validator(await trust_list(config.trusted_client_certificates))
        self.namespace_index = idx = await server.register_namespace(config.namespace)
        await self._build(server, idx)
        iserver = server.iserver
        iserver.attribute_service = _WriteService(iserver, self)
        # per-session UserAccessLevel, IndexRange on Read, PercentDeadband, BuildInfo
        await set_build_info(server)
        allowed = self.writes.allowed
        install(
            server,
            by_node(self.bindings, lambda b: allowed(b.plc, b.tag.name) is None),
            by_node(self.bindings, lambda b: _eu_span(b.tag)),
        )
        unlimit = limit_clients(server, self.guard)
        try:
            await server.start()
        except OSError as exc:
            unlimit()
            raise PlcError(f"OPC UA server cannot listen on {config.endpoint}: {exc}") from None
        self._server, self._unlimit = server, unlimit
        self._applier = self.supervisor.start(self.name, self._apply_submitted)
        bound = server.bserver
        if bound is not None:
            parts = urlsplit(config.endpoint)
            self.url = urlunsplit(parts._replace(netloc=f"{parts.hostname}:{bound.port}"))
        self.guard.announce(self.url)

    async def _build(self, server: Server, idx: int) -> None:
        for binding in self._by_tag.values():
            binding.nodeid = _node(f"{binding.plc}.{binding.tag.name}", idx)
        await self._add(server, self.poller.plcs, list(self._by_tag.values()))

    async def _add(self, server: Server, folders: Iterable[str], bindings: list[_Binding]) -> None:
        """Add the folders of PLCs ``folders`` and the variables of ``bindings`` (in folders
        there already or added here), each reading Bad_WaitingForInitialData."""
        session = server.iserver.isession
        idx = self.namespace_index
        config = self.poller.config
        urls = {p.name: p.url for p in config.plcs}
        for plc in folders:
            for result in await session.add_nodes([_folder_item(plc, urls.get(plc, ""), idx)]):
                result.StatusCode.check()
        items = []
        for binding in bindings:
            interval = config.groups[binding.tag.group]
            items.append(_tag_item(binding, _node(binding.plc, idx), idx, interval))
            items.extend(_eu_items(binding, idx))
        for result in await session.add_nodes(items) if items else ():
            result.StatusCode.check()
        waiting = ua.DataValue(StatusCode=_status(INITIAL_STATUS))
        for binding in bindings:
            self.bindings[binding.nodeid] = binding
            await server.write_attribute_value(binding.nodeid, waiting)

    async def update_plcs(self, update: PlcUpdate) -> None:
        """The address space of a reloaded configuration: a removed PLC's folder and
        variables are deleted (a client's monitored items on them report BadNodeIdUnknown); an
        added PLC's appear, reading Bad_WaitingForInitialData until its first scan; of a
        changed PLC only the variables whose tag changed are replaced. Every other variable
        stays with its value and its subscriptions."""
        view, idx = update.view, self.namespace_index
        wanted: dict[tuple[str, str], _Binding] = {}
        for plc in (*update.added, *update.changed):
            for name, (tag, bits) in view.tags(plc).items():
                nodeid = _node(f"{plc}.{name}", idx)
                wanted[(plc, name)] = _Binding(plc, tag, nodeid, variant_type(tag, bits))
        touched = {*update.added, *update.changed, *update.removed}
        gone = [
            key
            for key, b in self._by_tag.items()
            if key[0] in touched and not _same(b, wanted.get(key))
        ]
        new = [b for key, b in wanted.items() if not _same(self._by_tag.get(key), b)]
        server = self._server
        if server is not None:
            nodes = [server.get_node(self._by_tag[key].nodeid) for key in gone]
            nodes += [server.get_node(_node(plc, idx)) for plc in update.removed]
            if nodes:
                await server.delete_nodes(nodes, recursive=True)
        for key in gone:
            binding = self._by_tag.pop(key)
            self.bindings.pop(binding.nodeid, None)
            self._pending.pop(key, None)
        self._by_tag.update({(b.plc, b.tag.name): b for b in new})
        if server is not None:
            await self._add(server, update.added, new)

    async def aclose(self) -> None:
        """Stop listening; PLC writes still in flight finish (their outcome is logged)."""
        applier, self._applier = self._applier, None
        if applier is not None:
            await applier.stop()
        server, self._server = self._server, None
        if server is not None:
            await server.stop()
            self._unlimit()
        self.guard.close()
        if self._writes:
            await asyncio.gather(*self._writes, return_exceptions=True)

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    # -- samples in -------------------------------------------------------------------------
    async def send(self, samples: Iterable[Sample]) -> None:
        """Put samples into the address space (the sink side: any sample feed may call this)."""
        server = self.server
        by_tag = self._by_tag
        good = _S.Good
        now = _utc(time.time())
        for sample in samples:
            binding = by_tag.get((sample.plc, sample.tag))
            if binding is None:
                continue
            if sample.quality is Quality.GOOD:
                status, value = good, sample.value
            else:
                status, value = read_status(sample.error_type), None
            last_status, last_value = binding.last
            if last_status == status and same_value(last_value, value):
                self.unchanged += 1
                continue
            binding.last = (status, value)
            try:
                variant = binding.variant(value) if value is not None else None
            except (TypeError, ValueError):
                status, variant = _S.BadTypeMismatch, None
            data = _SampleValue(
                Value=variant,
                StatusCode=_status(status),
                SourceTimestamp=_utc(sample.source_time),
                ServerTimestamp=now,
            )
            await server.write_attribute_value(binding.nodeid, data)
            self.updates += 1

    def submit(self, scans: Iterable[Scan]) -> None:
        """The sinks' common interface: never blocks, holds at most one sample per tag.

        Samples are applied by a task of the server; when it falls behind, a tag's newer sample
        replaces its older one (an OPC UA variable holds the current value; ``coalesced`` counts
        the replaced ones). Samples of tags this server does not know are ignored.
        """
        pending = self._pending
        known = self._by_tag
        for sample in (s for scan in scans for s in scan.samples):
            key = (sample.plc, sample.tag)
            if key not in known:
                continue
            if key in pending:
                self.coalesced += 1
            pending[key] = sample
        if pending:
            self._wakeup.set()

    def health(self) -> Health:
        if self._server is None:
            return Health(self.name, f"not listening on {self.config.endpoint}")
        return Health(self.name, figures=(("variables", len(self.bindings)),))

    def summary(self) -> str:
        return (
            f"opcua {self.url}: {self.updates} values set, {self.unchanged} unchanged,"
            f" {self.coalesced} replaced by a newer one before they were set"
        )

    def announce(self) -> str:
        return f"OPC UA server listening on {self.url}"

    async def _apply_submitted(self) -> None:
        while True:
            await self._wakeup.wait()
            self._wakeup.clear()
            batch = list(self._pending.values())
            self._pending.clear()
            try:
                await self.send(batch)
            except Exception:  # one bad batch must not end the feed of every later one
                log.exception("OPC UA server: applying %d samples failed", len(batch))

    # -- writes out -------------------------------------------------------------------------
    async def write_to_plcs(
        self, jobs: dict[str, list[tuple[int, _Binding, _Job]]]
    ) -> list[tuple[int, ua.StatusCode]]:
        """Each PLC's writes in request order, PLCs in parallel; shielded from the client.

        A client that disconnects (cancelling its request) does not cut a PLC exchange short:
        the write finishes, and its outcome is logged.
        """
        task = asyncio.ensure_future(
            asyncio.gather(*(self._write_plc(items) for items in jobs.values()))
        )
        self._writes.add(task)
        task.add_done_callback(self._writes.discard)
        per_plc = await asyncio.shield(task)
        return [pair for results in per_plc for pair in results]

    async def _write_plc(
        self, items: Sequence[tuple[int, _Binding, _Job]]
    ) -> list[tuple[int, ua.StatusCode]]:
        out: list[tuple[int, ua.StatusCode]] = []
        for i, binding, (value, login, peer) in items:
            out.append((i, _status(await self._write_tag(binding, value, login, peer))))
        return out

    async def _write_tag(
        self, binding: _Binding, value: Any, login: str | None, peer: str | None
    ) -> int:
        # the one write path of every north side: allow-list, value grammar, write_tag, the
        # audit line (with the session's login and client address) and one log line
        result = await self.writes.write(
            "opcua",
            login,
            binding.plc,
            binding.tag.name,
            value,
            peer=peer,
            previous=binding.last[1],
        )
        if result.ok:
            return _S.Good
        if result.error is None:  # refused before the PLC (not writable, unknown tag)
            return _S.BadNotWritable
        return write_status(result.error)
