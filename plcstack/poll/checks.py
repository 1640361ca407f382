"""What a file's PLCs ask of the PLCs themselves, checked when the file is read.

* Every tag is planned on a client of its PLC's URL (built, never connected), so an address the
  family cannot hold is refused at load with its ``FILE:LINE`` and the words ``plcstack read``
  and the Python API use (``DB10.DW0`` on an E71: "that is Siemens S5 notation").
* A value type of the S5 family (``kg``, ``kt``, ``kf``, ...) is refused on a MELSEC PLC: the
  bits of a KG real in a D register are not a number the PLC ever meant.
* PLCs of one file that share a connection the device cannot share are said, one WARNING each:
  an E71 has 8 connections, an S5-LAN module takes one, an AS511 line has one master. Such
  PLCs are one ``[[plc]]`` (the tags of one PLC share its connection), and other programs reach
  the PLC through a gateway face, which shares that connection.

The poller builds the same plans again when it starts; these checks only make sure a file that
loads is one the poller and every face accept.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterator
from typing import Final

from plcstack.clients import connect
from plcstack.clients.base import Client
from plcstack.errors import AddressError, ConfigError
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.plan import build_plan
from plcstack.url import PlcUrl, parse_url
from plcstack.values import KC, KF, KG, KH, KM, KT, KY, KZ

__all__ = ["MELSEC_FOR_S5", "PlanCheck", "TagBits", "check_plans", "shared_connections"]

#: the S5 formats and the MELSEC type that holds what each means (a MELSEC word is no S5
#: format: KG in two D registers is not the PLC's float)
MELSEC_FOR_S5: Final[dict[str, str]] = {
    KF.name: "int16",
    KH.name: "uint16",
    KM.name: "uint16",
    KY.name: "uint16",
    KC.name: "string:2",
    KT.name: "bcd16",
    KZ.name: "bcd16",
    KG.name: "float32",
}
#: connections a device takes at once, by what it is (E71: specs, 8 connections)
_LIMITS: Final = {"E71": 8, "S5-LAN module": 1, "AS511 line": 1}

#: each PLC's tags with the width of their points in bits (what the Modbus map needs)
TagBits = dict[str, dict[str, tuple[TagConfig, int]]]
#: builds the (unconnected) client a PLC's tags are planned on
ClientOf = Callable[[PlcConfig], Client]


def _where(config: PollConfig, line: int | None) -> str:
    source = config.source or "<config>"
    return f"{source}:{line}" if line else source


def _unconnected(plc: PlcConfig) -> Client:
    return connect(plc.url)


class PlanCheck:
    """Plans every PLC's tags on a client of its URL; :meth:`run` raises the first refusal as a
    :class:`ConfigError` naming the PLC, the tag and ``FILE:LINE``."""

    def __init__(self, config: PollConfig, client_of: ClientOf = _unconnected) -> None:
        self.config = config
        self.client_of = client_of

    def run(self) -> TagBits:
        return {plc.name: self._plc(plc) for plc in self.config.plcs}

    def _error(self, plc: PlcConfig, line: int | None, message: str) -> ConfigError:
        return ConfigError(f"{message} ({_where(self.config, line)})", plc=plc.name)

    def _plc(self, plc: PlcConfig) -> dict[str, tuple[TagConfig, int]]:
        if parse_url(plc.url).scheme.startswith("e71"):
            for tag in plc.tags:
                melsec = MELSEC_FOR_S5.get(tag.type.name)
                if melsec is not None:
                    raise self._error(
                        plc,
                        tag.line,
                        f"tag {tag.name!r}: type {tag.type.name} is an S5 format"
                        f" ({tag.type.summary}) and this is a MELSEC PLC, whose words hold no"
                        f" S5 formats; use type = {melsec!r}",
                    )
        try:
            client = self.client_of(plc)
        except AddressError as exc:  # an option of the URL (?timeout=x)
            raise self._error(plc, plc.line, f"bad url: {exc.message}") from None
        try:
            return dict(self._planned(plc, client))
        finally:
            client.transport.abort()  # never connected: nothing to say goodbye to

    def _planned(
        self, plc: PlcConfig, client: Client
    ) -> Iterator[tuple[str, tuple[TagConfig, int]]]:
        for group in self.config.groups:
            members = [t for t in plc.tags if t.group == group]
            if not members:
                continue
            try:
                plan = build_plan(client, members, max_gap=plc.max_gap)
            except AddressError:
                raise self._refusal(plc, client, members) from None
            for tag_plan in plan.tags:
                yield tag_plan.tag.name, (tag_plan.tag, tag_plan.point_bits)

    def _refusal(self, plc: PlcConfig, client: Client, members: list[TagConfig]) -> ConfigError:
        """The first tag the client refuses on its own, with its line (the group's plan says
        which tag only in its words)."""
        for tag in members:
            try:
                build_plan(client, [tag], max_gap=0)
            except AddressError as exc:
                return self._error(plc, tag.line, exc.message)
        return self._error(plc, plc.line, "its tags cannot be planned together")


def check_plans(config: PollConfig, client_of: ClientOf = _unconnected) -> TagBits:
    """:class:`PlanCheck` of ``config``: each PLC's tags with their point widths."""
    return PlanCheck(config, client_of).run()


def _device(url: PlcUrl) -> tuple[str, str] | None:
    """(what it is, where) of the device a URL's connection takes a place of, for the ones
    with few places; None for the others."""
    if url.scheme.startswith("e71"):
        return "E71", f"{url.host}:{url.port}"
    if url.scheme == "s5lan":
        return "S5-LAN module", f"{url.host}:{url.port}"
    if url.scheme == "as511":
        return "AS511 line", url.path or ""
    if url.scheme.startswith("as511"):
        return "AS511 line", f"{url.host}:{url.port}"
    return None


def shared_connections(config: PollConfig) -> list[tuple[int | None, str]]:
    """(line, message) for each device that more PLCs of the file connect to than it takes
    connections; the line is that of the first PLC beyond the limit."""
    sharing: dict[tuple[str, str], list[PlcConfig]] = defaultdict(list)
    for plc in config.plcs:
        device = _device(parse_url(plc.url))
        if device is not None:
            sharing[device].append(plc)
    said = []
    for (kind, where), plcs in sharing.items():
        limit = _LIMITS[kind]
        if len(plcs) <= limit:
            continue
        names = ", ".join(repr(p.name) for p in plcs)
        takes = "one connection at a time" if limit == 1 else f"{limit} connections"
        said.append(
            (
                plcs[limit].line,
                f"PLCs {names} ({len(plcs)}) share the {kind} at {where}, which takes {takes}:"
                f" {'the second' if limit == 1 else f'the {limit + 1}th'} and later cannot"
                " connect. Make them one [[plc]] (the tags of one PLC share its connection),"
                " and let other programs reach that PLC through a gateway face, which shares"
                " it too (plcstack docs gateway)",
            )
        )
    return said
