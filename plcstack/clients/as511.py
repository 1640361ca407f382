"""AS511 client (PG side) for S5-90U...115U CPUs over a serial line or a serial device server.

``as511:///dev/ttyS0?baud=9600`` (8E1 by default; ``parity=``, ``stopbits=``) or
``as511+tcp://HOST:PORT`` (a serial device server; ``baud=`` is the line rate behind it and only
stretches deadlines for long frames). Further options: ``char_timeout`` (0.5 s, B5.7),
``response_timeout`` (defaults to ``char_timeout``; D.B6), ``cache`` (block address cache, on),
``strict`` (check the 5 leading zero bytes of read answers, off; D.B2), ``timeout`` (upper bound of
one transaction on top of its line time) and ``connect_timeout``.

The client is built in three layers, one module each: the link
(:mod:`plcstack.clients.as511_link`: one transaction of the byte-by-byte dialogue, the silence
rule after an abort, the failure policy), the PG services on it
(:mod:`plcstack.clients.as511_blocks`: system parameters, B_INFO and the block address cache,
absolute, block and area reads and writes) and, here, the API every client offers: ``read`` and
``write`` in S5 notation, the URL options and the poller's address hooks.
"""

from __future__ import annotations

import struct
from collections.abc import Hashable, Sequence
from typing import Any, Self

from plcstack.clients.as511_blocks import AREA_BYTES, BLOCK_TYPES, As511Blocks, pack_words
from plcstack.clients.as511_link import BITS_PER_BYTE
from plcstack.clients.base import (
    Points,
    as_points,
)
from plcstack.clients.options import COMMON, Option, choice, flag, integer, seconds
from plcstack.clients.s5access import S5Access
from plcstack.codecs.as511 import (
    DEFAULT_CHAR_TIMEOUT,
    MAX_READ_BYTES,
)
from plcstack.errors import AddressError, PlcError, ValueEncodeError
from plcstack.s5address import S5Address, S5Area, S5Unit, parse_s5_address
from plcstack.transports.base import Transport
from plcstack.transports.serial import SerialTransport
from plcstack.transports.tcp import TcpTransport
from plcstack.url import PlcUrl

__all__ = ["AREA_BYTES", "BLOCK_TYPES", "AS511Client"]


def _stopbits(value: object) -> object:
    if isinstance(value, bool) or not isinstance(value, int | float) or value not in (1, 1.5, 2):
        raise ValueError("not 1, 1.5 or 2")
    return float(value)


def _as_user_request(exc: PlcError, what: str) -> PlcError:
    """Name the request as the caller wrote it (``read MW100 x1``), keeping the AS511 step that
    failed in brackets: logs are searched for the address the user configured, which the
    transaction-level wording (``read M bytes 100..101``) did not contain."""
    if exc.request is None or exc.request.startswith(what):
        exc.request = what
    else:
        exc.request = f"{what} ({exc.request})"
    return exc


class AS511Client(As511Blocks, S5Access):
    """Read and write an S5 CPU through its programming port (spec part B).

    The PG services come first in the bases: their block and area reads and writes replace
    :class:`S5Access`'s generic ones; from :class:`S5Access` the client takes the STEP 5 bit
    notation, which :class:`Client`'s default (no bit notation) would otherwise shadow.
    """

    split_bit = S5Access.split_bit

    OPTIONS = (
        *COMMON,
        integer("baud", 9600, 50, 4_000_000, "line rate (behind a device server: for deadlines)"),
        seconds("char_timeout", DEFAULT_CHAR_TIMEOUT, "silence that ends a frame (B5.7)"),
        seconds("response_timeout", None, "wait for an answer; default char_timeout (D.B6)"),
        seconds("nak_backoff", 0.5, "pause after a DLE NAK before the next STX (B5.1)"),
        flag("cache", True, "cache block addresses from B_INFO"),
        flag("strict", False, "check the 5 leading zero bytes of read answers (D.B2)"),
    )
    #: a serial line adds its character format
    SERIAL_OPTIONS = (
        *OPTIONS,
        choice("parity", "E", ("N", "E", "O"), "parity (8E1 by default)"),
        Option("stopbits", 1.0, float, _stopbits, "stop bits: 1, 1.5 or 2"),
    )

    # -- construction -----------------------------------------------------------------------
    @classmethod
    def options_for(cls, url: PlcUrl) -> tuple[Option, ...]:
        return cls.SERIAL_OPTIONS if url.transport == "serial" else cls.OPTIONS

    @classmethod
    def create(cls, url: PlcUrl, options: dict[str, Any]) -> Self:
        opts = dict(options)
        baud = opts.pop("baud")
        transport: Transport
        if url.transport == "serial":
            assert url.path is not None
            transport = SerialTransport(
                url.path, baudrate=baud, parity=opts.pop("parity"), stopbits=opts.pop("stopbits")
            )
        else:
            assert url.host is not None and url.port is not None
            transport = TcpTransport(url.host, url.port)
            opts["line_byte_time"] = BITS_PER_BYTE / baud
        return cls(url.raw, transport, **opts)

    # -- the generic API --------------------------------------------------------------------
    def _parse(self, address: str, count: int) -> S5Address:
        try:
            addr = parse_s5_address(address)
        except AddressError as exc:
            raise exc.bind(plc=self.name) from None
        if not isinstance(count, int) or isinstance(count, bool) or count < 1:
            raise AddressError(f"count {count!r} must be a positive integer", plc=self.name)
        return addr

    async def read(self, address: str, count: int = 1) -> list[int]:
        """Read in S5 notation: words (DBn.DWk, MW, IW, QW, T, C) or bytes (MB, IB, DL/DR)."""
        try:
            # exact int: 2.0 or True would find the plan of 2 or 1 (equal keys) and skip _parse
            if type(count) is int:
                # the polling hot path: a DB/DX word read checked before, its block address
                # cached (see As511Blocks.read_prepared); anything else continues below from
                # exactly the point where the general path would
                words = await self.read_prepared(address, count)
                if words is not None:
                    return words
            return await self._read(address, count)
        except PlcError as exc:
            raise _as_user_request(exc, f"read {address} x{count}") from None

    async def _read(self, address: str, count: int) -> list[int]:
        addr = self._parse(address, count)
        nbytes = addr.byte_length(count)
        self.prepare_word_read(address, count, addr, nbytes)
        if addr.area.is_block:
            raw = await self.read_block_bytes(
                addr.area.value, addr.db or 0, addr.byte_offset, nbytes
            )
        else:
            raw = await self.read_bytes(addr.area, addr.byte_offset, nbytes)
        if addr.unit is S5Unit.WORD:
            return list(struct.unpack(f">{count}H", raw))
        return list(raw)

    async def write(self, address: str, values: Points) -> None:
        """Write in S5 notation; returns once the PLC acknowledged every byte."""
        values = as_points(values, plc=self.name, request=f"write {address}")
        try:
            await self._write(address, values)
        except PlcError as exc:
            raise _as_user_request(exc, f"write {address} x{len(values)}") from None

    async def _write(self, address: str, values: Sequence[int] | Sequence[bool]) -> None:
        addr = self._parse(address, max(1, len(values)))
        if not values:
            raise AddressError("no values to write", plc=self.name, request=f"write {address}")
        try:
            raw = (
                pack_words(values)
                if addr.unit is S5Unit.WORD
                else bytes(_check_byte(v) for v in values)
            )
        except AddressError as exc:
            raise exc.bind(plc=self.name, request=f"write {address}") from None
        if addr.area.is_block:
            await self.write_block_bytes(addr.area.value, addr.db or 0, addr.byte_offset, raw)
        else:
            await self.write_bytes(addr.area, addr.byte_offset, raw)

    # -- poller hooks -----------------------------------------------------------------------
    def locate(self, address: str, count: int = 1) -> tuple[Hashable, int]:
        addr = self._parse(address, count)
        # M/E/A words step by 2 bytes (MW10, MW12, ...): odd and even starts are different grids.
        parity = addr.offset % addr.step
        area = (addr.area.value, addr.db, addr.unit.name, parity)
        index = addr.offset // addr.step
        if addr.byte_offset + addr.byte_length(count) > self._area_limit(addr):
            raise AddressError(f"{address} x{count} is outside its area", plc=self.name)
        return area, index

    def address_at(self, area: Hashable, index: int) -> str:
        letter, db, unit_name, parity = _split_area(area)
        unit = S5Unit[unit_name]
        s5area = S5Area(letter)
        words_by_byte = (S5Area.FLAGS, S5Area.INPUTS, S5Area.OUTPUTS)
        step = 2 if unit is S5Unit.WORD and s5area in words_by_byte else 1
        return S5Address(s5area, unit, index * step + parity, db).to_str()

    def max_points(self, area: Hashable) -> int:
        letter, _, unit_name, _ = _split_area(area)
        per_point = S5Unit[unit_name].size
        # a cached block read carries the 10-byte header in its first transaction
        limit = MAX_READ_BYTES - 10 if letter in ("DB", "DX") else MAX_READ_BYTES
        return limit // per_point

    def point_bits(self, area: Hashable) -> int:
        """Width of one point of ``area`` for the poller: 16 for words, 8 for bytes."""
        return 8 * S5Unit[_split_area(area)[2]].size

    @staticmethod
    def _area_limit(addr: S5Address) -> int:
        return 0x10000 if addr.area.is_block else AREA_BYTES[addr.area]


def _split_area(area: Hashable) -> tuple[str, int | None, str, int]:
    """Undo the area key built by :meth:`AS511Client.locate`."""
    if not (isinstance(area, tuple) and len(area) == 4):
        raise AddressError(f"{area!r} is not an area key of AS511Client.locate")
    letter, db, unit_name, parity = area
    return str(letter), db if isinstance(db, int) else None, str(unit_name), int(parity)


def _check_byte(value: int | bool) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise ValueEncodeError(
            f"byte value {value!r} ({type(value).__name__}) is not an integer in 0..255"
        )
    return value
