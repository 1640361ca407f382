"""The AS511 PG services: system parameters, B_INFO, absolute and block reads and writes.

Decisions (spec part B):

* Block addresses (DW0 from B_INFO) are cached per block. A read with a cached address also reads
  the block's 10-byte header in the same transaction and checks its signature (``70 70``, type,
  number, length); a mismatch, a NAK or an answer of the wrong length drops the entry and the read
  is repeated once after a fresh B_INFO. A *write* always asks B_INFO first, as libnodave does:
  writing to a stale address would corrupt whatever block moved there.
* Reads are split into transactions of at most 512 bytes, writes likewise (B.7.3/B.7.4). A split
  write that fails part-way says how many bytes were written.
* I/Q/M/T/C use the base addresses of function 18h (read once per connection). Their sizes are
  those of the S5-115U layout (I/Q 128 bytes, M 256 bytes, T/C 128 words) [R]; the system
  parameters give the bases but no sizes.
* A DB/DX word read checked once is prepared (:meth:`As511Blocks.prepare_word_read`): later
  reads of it with the block address cached run as one transaction
  (:meth:`As511Blocks.read_prepared`), the wire work and checks of the general path.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from plcstack.clients.as511_link import As511Link
from plcstack.clients.base import DEFAULT_CONNECT_TIMEOUT, DEFAULT_TIMEOUT
from plcstack.codecs.as511 import (
    DEFAULT_CHAR_TIMEOUT,
    MAX_READ_BYTES,
    MAX_WRITE_BYTES,
    BlockInfo,
    Job,
    SystemAddresses,
    b_info_job,
    block_list_job,
    header_matches,
    operating_mode_job,
    parse_b_info,
    parse_read,
    parse_system_parameters,
    read_job,
    run_job,
    stop_job,
    system_parameters_job,
    write_job,
)
from plcstack.errors import (
    AddressError,
    PlcError,
    PlcErrorResponse,
    RemoteProtocolError,
    ValueEncodeError,
)
from plcstack.s5address import S5Address, S5Area, S5Unit
from plcstack.transports.backoff import Backoff
from plcstack.transports.base import Transport
from plcstack.values import pack_ints

__all__ = ["AREA_BYTES", "BLOCK_TYPES", "As511Blocks", "block_type_code", "pack_words"]

#: AS511 block type codes (B.6) by name
BLOCK_TYPES: dict[str, int] = {
    "DB": 0x01,
    "SB": 0x02,
    "PB": 0x04,
    "FX": 0x05,
    "FB": 0x08,
    "DX": 0x0C,
    "OB": 0x10,
}

#: bytes per area outside blocks (S5-115U layout) [R]
AREA_BYTES: dict[S5Area, int] = {
    S5Area.INPUTS: 128,
    S5Area.OUTPUTS: 128,
    S5Area.FLAGS: 256,
    S5Area.TIMERS: 256,
    S5Area.COUNTERS: 256,
}

_SYSPAR_FIELD = {
    S5Area.INPUTS: "inputs",
    S5Area.OUTPUTS: "outputs",
    S5Area.FLAGS: "flags",
    S5Area.TIMERS: "timers",
    S5Area.COUNTERS: "counters",
}

#: header bytes prepended to a cached block read for the signature check, if the gap is small
_MAX_SIGNATURE_GAP = 64
#: most (address, count) word reads whose checks :meth:`AS511Client.read` keeps
_MAX_PLANS = 4096


def _after_signature(head: bytes, info: BlockInfo, offset: int) -> bytes:
    """What follows the block header (and ``offset`` bytes) in a read that began at the header;
    :class:`_BlockMoved` when the header is not the cached block's any more."""
    header = head[:10]
    if not header_matches(header, info.block_type, info.number) or header != info.header:
        raise _BlockMoved
    return head[10 + offset :]


class _BlockMoved(Exception):
    """The header read with a cached address does not match: the block moved."""


def block_type_code(block_type: int | str) -> tuple[int, str]:
    """The code and name of a block type given by name (``"DB"``) or code."""
    if isinstance(block_type, str):
        name = block_type.upper()
        if name not in BLOCK_TYPES:
            raise AddressError(
                f"unknown block type {block_type!r}; known: {', '.join(BLOCK_TYPES)}"
            )
        return BLOCK_TYPES[name], name
    for name, code in BLOCK_TYPES.items():
        if code == block_type:
            return code, name
    raise AddressError(f"unknown block type code {block_type:#04x}")


class As511Blocks(As511Link):
    """The PG services of spec part B.7 on one :class:`As511Link`, with the block cache."""

    def __init__(
        self,
        name: str,
        transport: Transport,
        *,
        char_timeout: float = DEFAULT_CHAR_TIMEOUT,
        response_timeout: float | None = None,
        nak_backoff: float = 0.5,
        line_byte_time: float | None = None,
        cache: bool = True,
        strict: bool = False,
        timeout: float = DEFAULT_TIMEOUT,
        connect_timeout: float = DEFAULT_CONNECT_TIMEOUT,
        backoff: Backoff | None = None,
    ) -> None:
        """The link's options and the PG services' own: ``cache`` (block addresses from B_INFO)
        and ``strict`` (check the 5 leading zero bytes of read answers). The client takes this
        signature as it is."""
        super().__init__(
            name,
            transport,
            char_timeout=char_timeout,
            response_timeout=response_timeout,
            nak_backoff=nak_backoff,
            line_byte_time=line_byte_time,
            timeout=timeout,
            connect_timeout=connect_timeout,
            backoff=backoff,
        )
        self.cache_enabled = cache
        self.strict = strict
        self.block_cache: dict[tuple[int, int], BlockInfo] = {}
        #: (address, count) -> (block type code, number, byte offset, byte length, "what" text,
        #: word layout) of DB/DX word reads already parsed and checked, whose header and data
        #: fit one transaction: a poller reads the same few addresses every scan
        self._block_word_reads: dict[
            tuple[str, int], tuple[int, int, int, int, str, struct.Struct]
        ] = {}
        #: (start, length) -> the 04h job of that span, for the reads above
        self._read_jobs: dict[tuple[int, int], Job] = {}
        self._sysparams: SystemAddresses | None = None

    def connection_made(self) -> None:
        super().connection_made()
        self._sysparams = None  # a re-plugged cable may lead to another CPU

    # -- functions --------------------------------------------------------------------------
    async def read_system_parameters(self, *, refresh: bool = False) -> SystemAddresses:
        """Function 18h: base addresses of I/Q/M/T/C and system data (cached per connection)."""
        if self._sysparams is None or refresh:
            data = await self.transact(system_parameters_job(), "read system parameters")
            try:
                self._sysparams = parse_system_parameters(data)
            except RemoteProtocolError as exc:
                self.stats.errors += 1
                raise exc.bind(plc=self.name, request="read system parameters") from None
        return self._sysparams

    async def block_info(self, block_type: int | str, number: int) -> BlockInfo:
        """Function 1Ah (B_INFO): DW0 address and length of a block; refreshes the cache."""
        code, name = block_type_code(block_type)
        if not 1 <= number <= 255:
            raise AddressError(f"block number {number} is outside 1..255", plc=self.name)
        what = f"B_INFO {name}{number}"
        missing = f"{name}{number} does not exist in the PLC (B_INFO answered DLE NAK)"
        self.block_cache.pop((code, number), None)
        data = await self.transact(b_info_job(code, number), what, nak_meaning=missing)
        info = parse_b_info(data, code, number)
        if info is None:  # [R] D.B3: a failed signature check means "block not found" too
            self.stats.errors += 1
            raise PlcErrorResponse(
                0x15,
                f"{name}{number} is not usable: the block header failed the signature check "
                f"(answer {data.hex(' ')})",
                plc=self.name,
                request=what,
                code_text="bad block header",
            )
        if self.cache_enabled:
            self.block_cache[(code, number)] = info
        return info

    def invalidate(self, block_type: int | str | None = None, number: int | None = None) -> None:
        """Forget cached block addresses (all, or one block)."""
        if block_type is None:
            self.block_cache.clear()
            return
        code, _ = block_type_code(block_type)
        if number is None:
            for key in [k for k in self.block_cache if k[0] == code]:
                del self.block_cache[key]
        else:
            self.block_cache.pop((code, number), None)

    async def read_absolute(self, address: int, length: int, what: str | None = None) -> bytes:
        """Function 04h over ``address .. address+length-1``, split into 512-byte transactions."""
        if length < 1 or address < 0 or address + length > 0x10000:
            raise AddressError(
                f"absolute range {address:#06x}+{length} is outside 0..FFFFh", plc=self.name
            )
        what = what or f"read {length} bytes at {address:04X}h"
        out = bytearray()
        while len(out) < length:
            start = address + len(out)
            n = min(MAX_READ_BYTES, length - len(out))
            out += await self._read_chunk(start, n, what)
        return bytes(out)

    async def _read_chunk(self, start: int, n: int, what: str) -> bytes:
        return self._read_answer(await self.transact(read_job(start, n), what), n, what)

    def _read_answer(self, data: bytes, n: int, what: str) -> bytes:
        try:
            return parse_read(data, n, strict=self.strict)
        except RemoteProtocolError as exc:
            self.stats.errors += 1
            raise exc.bind(plc=self.name, request=what) from None

    async def write_absolute(self, address: int, data: bytes, what: str | None = None) -> None:
        """Function 03h at ``address``, split into 512-byte transactions."""
        data = bytes(data)
        if not data or address < 0 or address + len(data) > 0x10000:
            raise AddressError(
                f"absolute range {address:#06x}+{len(data)} is outside 0..FFFFh", plc=self.name
            )
        what = what or f"write {len(data)} bytes at {address:04X}h"
        done = 0
        while done < len(data):
            chunk = data[done : done + MAX_WRITE_BYTES]
            try:
                await self.transact(
                    write_job(address + done, chunk),
                    what,
                    is_write=True,
                    nak_meaning="the PLC refused the write (DLE NAK after the data): "
                    "address outside memory or protected",
                )
            except PlcError as exc:
                if done:
                    exc.message += f" (the first {done} of {len(data)} bytes were written)"
                raise
            done += len(chunk)

    # -- blocks (DB, DX) --------------------------------------------------------------------
    async def read_block_bytes(
        self, block_type: int | str, number: int, offset: int, length: int
    ) -> bytes:
        """``length`` bytes from byte ``offset`` of a block's body (DW0 = offset 0)."""
        code, name = block_type_code(block_type)
        what = f"read {name}{number} bytes {offset}..{offset + length - 1}"
        if length < 1 or offset < 0:
            raise AddressError(f"{what}: empty or negative range", plc=self.name)
        for attempt in range(2):
            cached = self.block_cache.get((code, number)) if self.cache_enabled else None
            info = cached or await self.block_info(code, number)
            if cached is not None and offset + length > info.data_bytes:
                self.block_cache.pop((code, number), None)  # maybe re-created longer: ask again
                continue
            self._check_span(info, name, offset, length, what)
            try:
                if cached is not None and offset <= _MAX_SIGNATURE_GAP:
                    return await self._read_verified(info, offset, length, what)
                return await self.read_absolute(info.dw0 + offset, length, what)
            except _BlockMoved:
                self.block_cache.pop((code, number), None)
                if attempt:
                    raise RemoteProtocolError(
                        f"{name}{number} keeps moving while it is read", plc=self.name
                    ) from None
            except (PlcErrorResponse, RemoteProtocolError):
                self.block_cache.pop((code, number), None)  # any sign that the block moved
                if cached is None or attempt:
                    raise
        raise AssertionError("unreachable")  # pragma: no cover

    async def _read_verified(self, info: BlockInfo, offset: int, length: int, what: str) -> bytes:
        """Read with a cached address, the block header in the first transaction (signature)."""
        first = min(length, MAX_READ_BYTES - 10 - offset)
        head = await self._read_chunk(info.header_address, 10 + offset + first, what)
        out = bytearray(_after_signature(head, info, offset))
        if len(out) < length:
            out += await self.read_absolute(info.dw0 + offset + len(out), length - len(out), what)
        return bytes(out)

    @staticmethod
    def _check_span(info: BlockInfo, name: str, offset: int, length: int, what: str) -> None:
        # [R] B.7.3: the wire has no range check; refuse reads/writes beyond the block's data
        if offset + length > info.data_bytes:
            raise AddressError(
                f"{what}: {name}{info.number} has {info.data_bytes // 2} data words "
                f"({info.data_bytes} bytes)"
            )

    async def write_block_bytes(
        self, block_type: int | str, number: int, offset: int, data: bytes
    ) -> None:
        """Write bytes into a block's body; B_INFO first, every time (see module docstring)."""
        code, name = block_type_code(block_type)
        what = f"write {name}{number} bytes {offset}..{offset + len(data) - 1}"
        if not data or offset < 0:
            raise AddressError(f"{what}: empty or negative range", plc=self.name)
        info = await self.block_info(code, number)
        self._check_span(info, name, offset, len(data), what)
        try:
            await self.write_absolute(info.dw0 + offset, data, what)
        except PlcErrorResponse:
            self.block_cache.pop((code, number), None)
            raise

    async def read_db(self, number: int, dw: int, count: int, *, dx: bool = False) -> list[int]:
        """``count`` data words from DW ``dw`` of DB (or DX) ``number``."""
        if count < 1 or dw < 0:
            raise AddressError(f"count {count} / DW{dw} out of range", plc=self.name)
        raw = await self.read_block_bytes("DX" if dx else "DB", number, 2 * dw, 2 * count)
        return list(struct.unpack(f">{count}H", raw))

    async def write_db(
        self, number: int, dw: int, words: Sequence[int], *, dx: bool = False
    ) -> None:
        """Write data words from DW ``dw`` of DB (or DX) ``number``; confirmed by the PLC."""
        await self.write_block_bytes("DX" if dx else "DB", number, 2 * dw, pack_words(words))

    async def read_dx(self, number: int, dw: int, count: int) -> list[int]:
        return await self.read_db(number, dw, count, dx=True)

    async def write_dx(self, number: int, dw: int, words: Sequence[int]) -> None:
        await self.write_db(number, dw, words, dx=True)

    # -- areas ------------------------------------------------------------------------------
    async def _area_address(self, area: S5Area, offset: int, length: int, what: str) -> int:
        size = AREA_BYTES[area]
        if offset < 0 or length < 1 or offset + length > size:
            raise AddressError(
                f"{what}: area {area.value} has {size} bytes; {offset}+{length} is outside it",
                plc=self.name,
            )
        params = await self.read_system_parameters()
        base: int = getattr(params, _SYSPAR_FIELD[area])
        return base + offset

    async def read_bytes(self, area: S5Area | str, offset: int, count: int) -> bytes:
        """Bytes of I/Q/M/T/C (T/C: 2 bytes per timer/counter) from byte ``offset``."""
        area = _area(area)
        what = f"read {area.value} bytes {offset}..{offset + count - 1}"
        address = await self._area_address(area, offset, count, what)
        return await self.read_absolute(address, count, what)

    async def write_bytes(self, area: S5Area | str, offset: int, data: bytes) -> None:
        area = _area(area)
        what = f"write {area.value} bytes {offset}..{offset + len(data) - 1}"
        address = await self._area_address(area, offset, len(data), what)
        await self.write_absolute(address, data, what)

    async def read_block_list(self, block_type: int | str) -> dict[int, int]:
        """Function 1Bh: ``{block number: address}`` of the blocks of one type (B.7.6).

        The meaning of the addresses is not verified on real CPUs (B.7.6); the simulator returns
        the DW0 address that B_INFO would return.
        """
        code, name = block_type_code(block_type)
        what = f"read the {name} block list"
        data = await self.transact(block_list_job(code), what)
        if not data or data[0] != 0 or len(data) % 2 != 1:
            self.stats.errors += 1
            raise RemoteProtocolError(
                f"block list answer of {len(data)} bytes is not 00 + words",
                plc=self.name,
                request=what,
            )
        words = struct.unpack(f">{len(data) // 2}H", data[1:])
        return {number: address for number, address in enumerate(words) if address}

    async def change_operating_mode(self, mode: int) -> int | None:
        """Function 1Eh of 135U/155U CPUs: 0 stop, 1 restart, 2 warm restart (B.7.5).

        Returns the byte the CPU answers for modes 1 and 2 (25h/26h), ``None`` for stop.
        """
        if mode not in (0, 1, 2):
            raise AddressError(f"operating mode {mode} is not 0, 1 or 2", plc=self.name)
        data = await self.transact(
            operating_mode_job(mode), f"change operating mode to {mode}", is_write=True
        )
        return data[0] if data else None

    async def stop(self) -> None:
        """Put a small CPU into STOP (B.7.5: 88 04 at system data + 0Ch)."""
        params = await self.read_system_parameters()
        await self.transact(stop_job(params.system_data), "stop the PLC", is_write=True)

    async def start(self) -> None:
        """Restart a small CPU (B.7.5: 68 00 at system data + 0Ch)."""
        params = await self.read_system_parameters()
        await self.transact(run_job(params.system_data), "start the PLC", is_write=True)

    # -- prepared DB/DX word reads -------------------------------------------------------------
    def prepare_word_read(self, address: str, count: int, addr: S5Address, nbytes: int) -> None:
        """Remember a checked DB/DX word read whose header and data fit one transaction, for
        :meth:`read_prepared`."""
        if (
            addr.area.is_block
            and addr.unit is S5Unit.WORD
            and addr.byte_offset <= _MAX_SIGNATURE_GAP
            and 10 + addr.byte_offset + nbytes <= MAX_READ_BYTES
            and len(self._block_word_reads) < _MAX_PLANS
        ):
            code, name = block_type_code(addr.area.value)
            number, offset = addr.db or 0, addr.byte_offset
            what = f"read {name}{number} bytes {offset}..{offset + nbytes - 1}"
            words = struct.Struct(f">{count}H")
            self._block_word_reads[(address, count)] = (code, number, offset, nbytes, what, words)

    async def read_prepared(self, address: str, count: int) -> list[int] | None:
        """A prepared word read in one transaction, or None: not prepared, the block address not
        cached, or the read failed in a way that drops the cached address (the caller then runs
        the general path, which asks B_INFO again)."""
        plan = self._block_word_reads.get((address, count))
        if plan is None:
            return None
        # One await (the transaction) instead of five nested coroutines that each resume on
        # every answer of the AS511 dialogue; the wire work and every check are those of
        # read_block_bytes -> _read_verified.
        code, number, offset, length, what, words = plan
        key = (code, number)
        info = self.block_cache.get(key) if self.cache_enabled else None
        if info is None or offset + length > info.data_bytes:
            return None
        span = (info.header_address, 10 + offset + length)
        job = self._read_jobs.get(span)
        if job is None:
            job = read_job(*span)  # Job is frozen: one per span serves every read
            if len(self._read_jobs) < _MAX_PLANS:
                self._read_jobs[span] = job
        try:
            data = await self.transact(job, what)
            head = self._read_answer(data, 10 + offset + length, what)
            return list(words.unpack(_after_signature(head, info, offset)))
        except (_BlockMoved, PlcErrorResponse, RemoteProtocolError):
            # the general path's first attempt failed the same way: it drops the address and
            # asks B_INFO again
            self.block_cache.pop(key, None)
            return None


def _area(area: S5Area | str) -> S5Area:
    if isinstance(area, S5Area):
        if area.is_block:
            raise AddressError("use read_db/read_block_bytes for DB and DX")
        return area
    letters = {"I": "E", "Q": "A", "C": "Z"}
    try:
        return _area(S5Area(letters.get(area.upper(), area.upper())))
    except ValueError:
        raise AddressError(f"unknown area {area!r}; use M, I/E, Q/A, T, C/Z") from None


def pack_words(values: Sequence[int] | Sequence[bool]) -> bytes:
    fast = pack_ints(values, ">", "H")  # plain ints in range: no per-value checks needed
    if fast is not None:
        return fast
    out = bytearray()
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueEncodeError(
                f"word value {value!r} ({type(value).__name__}) is not an integer"
            )
        if not -0x8000 <= value <= 0xFFFF:
            raise AddressError(f"word value {value} is outside -32768..65535")
        out += struct.pack(">H", value & 0xFFFF)
    return bytes(out)
