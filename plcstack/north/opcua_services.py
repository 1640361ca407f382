"""What the OPC UA server answers beyond asyncua's defaults, per session and per request.

asyncua answers the Read service from the address space as stored, for every session alike, and
takes monitored items as asked. Three things a client relies on need the session or the request:

- **UserAccessLevel** (Part 3, 5.6.2): what *this session's* user may do. A tag variable stores
  CurrentRead, plus CurrentWrite for ``writable = true``; the Read answer is narrowed per session:
  an anonymous read-only session and a user without ``write = true`` read CurrentRead only, so a
  client (UaExpert) does not offer a write the server will refuse with BadUserAccessDenied.
- **IndexRange on Read** (Part 4, 7.22): honoured for the Value of tag variables: ``"3"`` is one
  element, ``"2:5"`` elements 2..5 (an upper bound beyond the array returns the part there is);
  a string value is ranged by characters. A range that does not parse or whose first index is not
  below its last is BadIndexRangeInvalid; a first index beyond the value, a range on a scalar or a
  range with more dimensions than the value (``"1:2,0:1"``) is BadIndexRangeNoData.
- **PercentDeadband** (Part 8, 6.2): a DataChangeFilter with a percent deadband needs the item's
  EURange (``deadband / 100 * (high - low)``). On a tag with ``scale`` (it has an EURange) the
  filter is taken as the absolute deadband it amounts to; on any other variable CreateMonitored
  Items answers the item BadDeadbandFilterInvalid instead of accepting it and ignoring it.

How: the Read answers are changed in asyncua's PostRead server callback, which receives the
request, the result list (changed in place) and the session's user; CreateMonitoredItems goes
through a wrapper around the subscription service's method, which answers the refused items
itself and passes the others on.

Also here: the BuildInfo this server states (ProductName plcstack, SoftwareVersion the package
version, ManufacturerName and ProductUri plcstack's), instead of asyncua's own.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any, Final, cast

from asyncua import ua
from asyncua.common.callback import CallbackType, ServerItemCallback
from asyncua.server.server import Server
from asyncua.ua.attribute_ids import AttributeIds
from asyncua.ua.status_codes import StatusCodes as _S

from plcstack.north.opcua_users import PlcUser

__all__ = [
    "MANUFACTURER",
    "PRODUCT_NAME",
    "PRODUCT_URI",
    "apply_index_range",
    "by_node",
    "install",
    "set_build_info",
    "software_version",
    "user_access_level",
]

PRODUCT_NAME: Final = "plcstack"
PRODUCT_URI: Final = "urn:plcstack"
MANUFACTURER: Final = "the plcstack authors"

_RANGE: Final = re.compile(r"^(\d+)(?::(\d+))?$")
#: the time this module's file was installed: the BuildDate
_BUILT: Final = Path(__file__).stat().st_mtime
_READ: Final = ua.AccessLevel.CurrentRead.mask
_WRITE: Final = ua.AccessLevel.CurrentWrite.mask


def software_version() -> str:
    """The installed package's version (the one ``pip`` shows)."""
    try:
        return metadata.version("plcstack")
    except metadata.PackageNotFoundError:  # run from a source tree without installing
        return "unknown"


async def set_build_info(server: Server) -> None:
    """State plcstack's BuildInfo (Server_ServerStatus_BuildInfo) and ProductUri."""
    version = software_version()
    server.product_uri = PRODUCT_URI
    server.manufacturer_name = MANUFACTURER
    built = datetime.fromtimestamp(_BUILT, UTC)
    await server.set_build_info(PRODUCT_URI, MANUFACTURER, PRODUCT_NAME, version, version, built)


def user_access_level(writable: bool, may_write: bool) -> int:
    """UserAccessLevel of a tag variable for a session: CurrentRead, plus CurrentWrite when
    the tag is ``writable = true`` and the session's login may write."""
    return _READ | (_WRITE if writable and may_write else 0)


def apply_index_range(data: ua.DataValue, index_range: str) -> ua.DataValue:
    """The part of ``data`` that ``index_range`` selects (Part 4, 7.22), or a DataValue with
    BadIndexRangeInvalid / BadIndexRangeNoData (see the module docstring)."""

    def bad(code: int) -> ua.DataValue:
        return ua.DataValue(StatusCode=ua.StatusCode(cast(ua.UInt32, code)))

    text = index_range.strip()
    if "," in text:
        dims = text.split(",")
        if not all(_RANGE.match(d.strip()) for d in dims):
            return bad(_S.BadIndexRangeInvalid)
        return bad(_S.BadIndexRangeNoData)  # our values have one dimension
    m = _RANGE.match(text)
    if m is None:
        return bad(_S.BadIndexRangeInvalid)
    first = int(m.group(1))
    last = int(m.group(2)) if m.group(2) is not None else first
    if m.group(2) is not None and first >= last:
        return bad(_S.BadIndexRangeInvalid)
    if data.StatusCode is not None and not data.StatusCode.is_good():
        return data  # no value to take a part of: the status says why
    variant = data.Value
    value = variant.Value if variant is not None else None
    if variant is None or not isinstance(value, list | str) or first >= len(value):
        return bad(_S.BadIndexRangeNoData)
    part = ua.Variant(value[first : last + 1], variant.VariantType)
    return ua.DataValue(
        Value=part,
        StatusCode=data.StatusCode,
        SourceTimestamp=data.SourceTimestamp,
        ServerTimestamp=data.ServerTimestamp,
    )


def install(
    server: Server,
    writable: Callable[[ua.NodeId], bool | None],
    eu_range: Callable[[ua.NodeId], tuple[float, float] | None],
) -> None:
    """Hook the per-session Read answers and the CreateMonitoredItems check into ``server``.

    ``writable(nodeid)``: whether a tag variable is ``writable = true``, None for a node that is
    not a tag variable (left as asyncua answers it); ``eu_range(nodeid)``: a tag's EURange
    (low, high), None if it has none.
    """

    async def post_read(event: ServerItemCallback, _: Any) -> None:
        params, results = event.request_params, event.response_params
        if results is None:
            return
        user = event.user
        may_write = isinstance(user, PlcUser) and user.may_write
        for i, item in enumerate(params.NodesToRead):
            tag_writable = writable(item.NodeId)
            if tag_writable is None:
                continue
            if item.AttributeId == AttributeIds.UserAccessLevel:
                level = user_access_level(tag_writable, may_write)
                results[i] = ua.DataValue(Value=ua.Variant(level, ua.VariantType.Byte))
            elif item.AttributeId == AttributeIds.Value and item.IndexRange:
                results[i] = apply_index_range(results[i], item.IndexRange)

    server.subscribe_server_callback(CallbackType.PostRead, post_read)
    service = server.iserver.subscription_service
    create = service.create_monitored_items

    async def create_monitored_items(
        params: ua.CreateMonitoredItemsParameters,
    ) -> list[ua.MonitoredItemCreateResult]:
        refused: dict[int, ua.MonitoredItemCreateResult] = {}
        passed: list[ua.MonitoredItemCreateRequest] = []
        for i, item in enumerate(params.ItemsToCreate):
            flt = item.RequestedParameters.Filter
            # a DataChangeFilter (asyncua decodes it into a class of its generated module, not
            # the ua.DataChangeFilter it exports: asked by its fields)
            if getattr(flt, "DeadbandType", None) == ua.DeadbandType.Percent:
                span = eu_range(item.ItemToMonitor.NodeId)
                if span is None:
                    result = ua.MonitoredItemCreateResult()
                    result.StatusCode = ua.StatusCode(cast(ua.UInt32, _S.BadDeadbandFilterInvalid))
                    refused[i] = result
                    continue
                lo, hi = span
                flt.DeadbandType = ua.DeadbandType.Absolute
                flt.DeadbandValue = cast(ua.Double, flt.DeadbandValue / 100.0 * (hi - lo))
            passed.append(item)
        if not refused:
            return await create(params)
        params.ItemsToCreate = passed
        done = iter(await create(params) if passed else [])
        n = len(passed) + len(refused)
        return [refused[i] if i in refused else next(done) for i in range(n)]

    service.create_monitored_items = create_monitored_items  # type: ignore[method-assign]


def by_node(
    table: Mapping[ua.NodeId, Any], get: Callable[[Any], Any]
) -> Callable[[ua.NodeId], Any]:
    """A lookup ``nodeid -> get(table[nodeid])``, None for a node not in ``table``."""

    def lookup(nodeid: ua.NodeId) -> Any:
        entry = table.get(nodeid)
        return None if entry is None else get(entry)

    return lookup
