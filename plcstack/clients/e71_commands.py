"""E71 client methods beyond device read/write (spec §7.4-§7.8, §9); mixed into ``E71Client``.

* :meth:`~E71CommandsMixin.cpu_model`, :meth:`~E71CommandsMixin.cpu_status`,
  :meth:`~E71CommandsMixin.remote_run`, :meth:`~E71CommandsMixin.remote_stop`,
  :meth:`~E71CommandsMixin.loopback` (13H-16H)
* special function module buffer memory in bytes and words (0EH/0FH)
* extended file registers by block (17H-1BH) and direct (3BH/3CH)
* the random access buffer (61H/62H), spans longer than one message split into several
* program/parameter/comment areas streamed in chunks by the EXPERIMENTAL [R] layout (§7.8)
"""

from __future__ import annotations

import struct
from abc import abstractmethod
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

from plcstack.clients.exchange import RequestClient
from plcstack.codecs.e71 import (
    Ack,
    Code,
    E71ClientConnection,
    ExtensionRequest,
    ExtensionResponse,
    Response,
    WordsResponse,
)
from plcstack.codecs.e71_commands import (
    EXT_FILE_BLOCK_SIZE,
    RANDOM_BUFFER_MAX_WORDS,
    RANDOM_BUFFER_WORDS,
    BytesResponse,
    CpuModelResponse,
    FixedBufferData,
    Loopback,
    LoopbackResponse,
    MonitorExt,
    OpaqueCommand,
    OpaqueResponse,
    ReadCpuModel,
    ReadExtDirect,
    ReadExtFile,
    ReadRandomBuffer,
    ReadSpecial,
    RegisterMonitorExt,
    RemoteRun,
    RemoteStop,
    TestExtFile,
    WriteExtDirect,
    WriteExtFile,
    WriteRandomBuffer,
    WriteSpecial,
)
from plcstack.codecs.e71_programs import PROGRAM_COMMANDS, build, parse_response
from plcstack.errors import AddressError, LocalProtocolError, RemoteProtocolError

__all__ = ["CPU_STATES", "CpuStatus", "E71CommandsMixin", "ProgressCallback"]

#: progress callback of streamed reads/writes: (units done, units total)
ProgressCallback = Callable[[int, int], None]

R = TypeVar("R")

#: [R] D9015 bits 0-3 (A-series special register "CPU operating status")
CPU_STATES = {0: "RUN", 1: "STOP", 2: "PAUSE", 3: "STEP-RUN"}


@dataclass(frozen=True, slots=True)
class CpuStatus:
    """What ``plcstack info`` shows: 15H model code and name, D9015 operating state."""

    model_code: int
    model: str
    state: str
    status_word: int


class E71CommandsMixin(RequestClient[Response]):
    """The commands of :mod:`plcstack.codecs.e71_commands` as async methods of ``E71Client``.

    A base of ``E71Client`` rather than a free-floating mixin: it inherits ``exchange`` from
    :class:`RequestClient`, and the few E71 pieces it needs from the client are the abstract
    methods below, which ``E71Client`` must implement (checked when it is instantiated).
    """

    #: §13 A2: ASCII random access buffer answers with a 2-char (default) or 4-char subheader
    rab_ascii_sub_chars: int = 2
    #: binary or ASCII (set by ``E71Client``)
    code: Code
    #: the partner-side codec of the current connection (set by ``E71Client``)
    codec: E71ClientConnection
    #: the 06H/07H monitor registration; a 1AH registration replaces it (§7.3)
    _monitor: tuple[int | None, int | None] = (None, None)

    # -- what E71Client provides -----------------------------------------------------------------
    @abstractmethod
    def _hdr(self) -> dict[str, int]:
        """``pc`` and ``timer`` for a request header, as configured now."""

    @abstractmethod
    def _bad(self, message: str, what: str) -> AddressError:
        """Our caller's misuse, as the error to raise (naming PLC and request)."""

    @abstractmethod
    def _reply_or_raise(self, event: R, what: str, *, is_write: bool = False) -> R:
        """The reply, or the PLC's end code as a PlcErrorResponse (an undocumented end code
        as a RemoteProtocolError, may-or-may-not for a write)."""

    @abstractmethod
    async def read_words(self, address: str, count: int = 1) -> list[int]:
        """Words from a word device (used for the CPU status register D9015)."""

    _ext_monitor_count: int | None = None

    # -- plumbing -------------------------------------------------------------------------------
    async def _xcall(
        self, request: ExtensionRequest, what: str, *, is_write: bool
    ) -> Response | ExtensionResponse:
        try:
            request.encode(self.code)  # our own checks first: nothing is sent on bad input
        except LocalProtocolError as exc:
            raise self._bad(exc.message, what) from None
        event: Response | ExtensionResponse = await self.exchange(request, what, is_write=is_write)
        return self._reply_or_raise(event, what, is_write=is_write)

    async def _xwords(self, request: ExtensionRequest, what: str) -> list[int]:
        event = await self._xcall(request, what, is_write=False)
        if not isinstance(event, WordsResponse):  # pragma: no cover - the codec guarantees it
            raise RemoteProtocolError("unexpected response", plc=self.name, request=what)
        return list(event.values)

    def _xint(self, value: object, low: int, high: int, name: str, what: str) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise self._bad(f"{name} must be an integer {low}..{high}, got {value!r}", what)
        return value

    def _xword_values(self, values: Sequence[int], what: str) -> tuple[int, ...]:
        out = []
        for v in values:
            self._xint(v, -0x8000, 0xFFFF, "word value", what)
            out.append(v & 0xFFFF)
        return tuple(out)

    # -- 13H-16H --------------------------------------------------------------------------------
    async def cpu_model(self) -> tuple[int, str]:
        """15H: ``(model code, CPU names)``, e.g. ``(0xA3, "A3, A3N")``."""
        event = await self._xcall(ReadCpuModel(**self._hdr()), "read CPU model", is_write=False)
        assert isinstance(event, CpuModelResponse)
        return event.model_code, event.name

    async def cpu_status(self) -> CpuStatus:
        """15H model plus the operating state from D9015 [R] (RUN/STOP/PAUSE/STEP-RUN)."""
        code, name = await self.cpu_model()
        (word,) = await self.read_words("D9015", 1)
        return CpuStatus(code, name, CPU_STATES.get(word & 0x0F, f"unknown ({word:04X}H)"), word)

    async def remote_run(self) -> None:
        """13H remote RUN (the key switch must be RUN; 5BH/18H if another station stopped it)."""
        await self._xcall(RemoteRun(**self._hdr()), "remote RUN", is_write=True)

    async def remote_stop(self) -> None:
        """14H remote STOP. Without "communication in STOP" enabled the E71 then closes its
        connections (§1.3); the client reconnects on the next request."""
        await self._xcall(RemoteStop(**self._hdr()), "remote STOP", is_write=True)

    async def loopback(self, data: bytes) -> bytes:
        """16H: send 1-254 bytes (§13 A6) and check they come back unchanged."""
        what = f"loopback {len(data)} bytes"
        if not isinstance(data, bytes) or not 1 <= len(data) <= 254:
            raise self._bad("loopback takes 1-254 bytes", what)
        event = await self._xcall(Loopback(data, **self._hdr()), what, is_write=False)
        assert isinstance(event, LoopbackResponse)
        if event.data != data:
            raise RemoteProtocolError(
                f"loopback answered {event.data.hex()} for {data.hex()}",
                plc=self.name,
                request=what,
            )
        return event.data

    # -- 0EH/0FH --------------------------------------------------------------------------------
    async def read_special(self, module: int, address: int, count: int) -> bytes:
        """0EH: ``count`` (1-256) bytes at byte ``address`` of special module ``module``."""
        what = f"read special module {module:02X}H @{address:X}H x{count}"
        self._xint(count, 1, 256, "byte count", what)
        event = await self._xcall(
            ReadSpecial(module, address, count, **self._hdr()), what, is_write=False
        )
        assert isinstance(event, BytesResponse)
        return event.data

    async def write_special(self, module: int, address: int, data: bytes) -> None:
        """0FH: write 1-256 bytes at byte ``address`` of special module ``module``."""
        what = f"write special module {module:02X}H @{address:X}H x{len(data)}"
        await self._xcall(
            WriteSpecial(module, address, bytes(data), **self._hdr()), what, is_write=True
        )

    async def read_special_words(
        self, module: int, word_address: int, count: int, *, offset: int = 0
    ) -> list[int]:
        """Words of a module's buffer memory by its FROM/TO word address: byte address =
        ``word_address * 2 + offset`` (``offset`` = the module's buffer start, e.g. 80H for an
        AD61, §7.5); 1-128 words."""
        what = f"read special module {module:02X}H words @{word_address} x{count}"
        self._xint(count, 1, 128, "word count", what)
        data = await self.read_special(module, word_address * 2 + offset, 2 * count)
        return list(struct.unpack(f"<{count}H", data))

    async def write_special_words(
        self, module: int, word_address: int, values: Sequence[int], *, offset: int = 0
    ) -> None:
        what = f"write special module {module:02X}H words @{word_address} x{len(values)}"
        words = self._xword_values(values, what)
        if not 1 <= len(words) <= 128:
            raise self._bad("1-128 words per request", what)
        data = struct.pack(f"<{len(words)}H", *words)
        await self.write_special(module, word_address * 2 + offset, data)

    # -- extended file registers (17H-1BH, 3BH/3CH) ---------------------------------------------
    async def read_ext_file(self, block: int, number: int, count: int = 1) -> list[int]:
        """17H: ``count`` (1-256) registers R``number``.. of extended file register ``block``."""
        what = f"read ext file register block {block} R{number} x{count}"
        return await self._xwords(ReadExtFile(block, number, count, **self._hdr()), what)

    async def write_ext_file(self, block: int, number: int, values: Sequence[int]) -> None:
        what = f"write ext file register block {block} R{number} x{len(values)}"
        req = WriteExtFile(block, number, self._xword_values(values, what), **self._hdr())
        await self._xcall(req, what, is_write=True)

    async def test_ext_file(self, points: Sequence[tuple[int, int, int]]) -> None:
        """19H: write scattered ``(block, number, value)`` registers (at most 40)."""
        what = f"test ext file registers x{len(points)}"
        triples = tuple(
            (b, n, v)
            for (b, n, _), v in zip(
                points, self._xword_values([p[2] for p in points], what), strict=True
            )
        )
        await self._xcall(TestExtFile(triples, **self._hdr()), what, is_write=True)

    async def register_monitor_ext(self, points: Sequence[tuple[int, int]]) -> None:
        """1AH: register up to 20 ``(block, number)`` registers for :meth:`monitor_ext`. This
        replaces any 06H/07H registration: there is one per CPU (§7.3)."""
        what = f"register monitor ext file registers x{len(points)}"
        req = RegisterMonitorExt(tuple((b, n) for b, n in points), **self._hdr())
        await self._xcall(req, what, is_write=False)
        self._monitor = (None, None)
        self.codec.monitor_bits = self.codec.monitor_words = None
        self._ext_monitor_count = len(points)

    async def monitor_ext(self) -> list[int]:
        what = "monitor ext file registers"
        if self._ext_monitor_count is None:
            raise self._bad("register registers first (register_monitor_ext)", what)
        return await self._xwords(MonitorExt(self._ext_monitor_count, **self._hdr()), what)

    async def read_ext_direct(self, number: int, count: int = 1) -> list[int]:
        """3BH: registers by the direct number (block - 1) * 8192 + register (AnA/AnU)."""
        what = f"read ext file register direct {number} x{count}"
        return await self._xwords(ReadExtDirect(number, count, **self._hdr()), what)

    async def write_ext_direct(self, number: int, values: Sequence[int]) -> None:
        what = f"write ext file register direct {number} x{len(values)}"
        req = WriteExtDirect(number, self._xword_values(values, what), **self._hdr())
        await self._xcall(req, what, is_write=True)

    @staticmethod
    def ext_direct_number(block: int, register: int) -> int:
        """The 3BH/3CH number of ``register`` (0-8191) in ``block`` (1-256), §7.4."""
        if not (1 <= block <= 256 and 0 <= register < EXT_FILE_BLOCK_SIZE):
            raise AddressError(f"block {block} / register {register} outside 1-256 / 0-8191")
        return (block - 1) * EXT_FILE_BLOCK_SIZE + register

    # -- random access buffer (61H/62H) ---------------------------------------------------------
    async def read_random_buffer(self, address: int, count: int = 1) -> list[int]:
        """``count`` words from internal address ``address`` (0-6143). Longer than one message
        (1017 words binary / 508 ASCII) is split into several reads (not atomic)."""
        what = f"read random access buffer @{address} x{count}"
        self._rab_span(address, count, what)
        out: list[int] = []
        step = RANDOM_BUFFER_MAX_WORDS[self.code]
        for start in range(address, address + count, step):
            n = min(step, address + count - start)
            req = ReadRandomBuffer(start, n, ascii_sub_chars=self.rab_ascii_sub_chars)
            out.extend(await self._xwords(req, what))
        return out

    async def write_random_buffer(self, address: int, values: Sequence[int]) -> None:
        """Write words at internal address ``address``; split like :meth:`read_random_buffer`."""
        what = f"write random access buffer @{address} x{len(values)}"
        words = self._xword_values(values, what)
        self._rab_span(address, len(words), what)
        step = RANDOM_BUFFER_MAX_WORDS[self.code]
        for k in range(0, len(words), step):
            req = WriteRandomBuffer(
                address + k, words[k : k + step], ascii_sub_chars=self.rab_ascii_sub_chars
            )
            await self._xcall(req, what, is_write=True)

    def _rab_span(self, address: int, count: int, what: str) -> None:
        self._xint(address, 0, RANDOM_BUFFER_WORDS - 1, "address", what)
        self._xint(count, 1, RANDOM_BUFFER_WORDS - address, "word count", what)

    # -- fixed buffer telegram on this (with procedure) connection ---------------------------------
    async def send_fixed_buffer(self, values: Sequence[int]) -> None:
        """60H on this connection (a "with procedure" connection carries fixed buffer telegrams
        too, §8.1); returns on ``E0 00``. PLC-initiated telegrams need their own connection:
        :class:`plcstack.clients.e71_fixed.E71FixedBufferClient`."""
        what = f"fixed buffer send x{len(values)}"
        await self._xcall(FixedBufferData(self._xword_values(values, what)), what, is_write=True)

    # -- programs, parameters, comments (EXPERIMENTAL [R] layout, §7.8) ------------------------
    async def opaque(self, command: int, body: bytes, response_length: int) -> bytes:
        """Send an opaque command with a raw wire ``body``; returns the raw answer data
        (``response_length`` binary bytes expected; ASCII: twice as many characters)."""
        what = f"command {command:02X}H"
        req = OpaqueCommand(command, body, response_length, **self._hdr())
        is_write = (command in PROGRAM_COMMANDS and PROGRAM_COMMANDS[command][1]) or command == 0x12
        event = await self._xcall(req, what, is_write=is_write)
        assert isinstance(event, (OpaqueResponse, Ack))
        return event.data if isinstance(event, OpaqueResponse) else b""

    async def iter_area(
        self, command: int, start: int, length: int, *, chunk: int = 256
    ) -> AsyncIterator[tuple[int, ...]]:
        """EXPERIMENTAL [R]: stream ``length`` units (steps/set values for 0AH/0BH, else bytes)
        of the area read by ``command`` from ``start``, one request of ``chunk`` (<= 256) at a
        time; yields each chunk's values."""
        what = f"read {PROGRAM_COMMANDS.get(command, ('?', False))[0]} @{start:X}H x{length}"
        if command not in PROGRAM_COMMANDS or PROGRAM_COMMANDS[command][1]:
            raise self._bad(f"{command!r} is not a program/parameter/comment read", what)
        self._xint(chunk, 1, 256, "chunk", what)
        self._xint(length, 1, 1 << 24, "length", what)
        done = 0
        while done < length:
            n = min(chunk, length - done)
            try:
                req = build(command, start + done, n, self.code, **self._hdr())
            except LocalProtocolError as exc:
                raise self._bad(exc.message, what) from None
            event = await self._xcall(req, what, is_write=False)
            assert isinstance(event, OpaqueResponse)
            yield parse_response(req, event, self.code)
            done += n

    async def read_area(
        self,
        command: int,
        start: int,
        length: int,
        *,
        chunk: int = 256,
        progress: ProgressCallback | None = None,
    ) -> list[int]:
        """EXPERIMENTAL [R]: the whole area as one list (words for 0AH/0BH, else bytes)."""
        out: list[int] = []
        async for part in self.iter_area(command, start, length, chunk=chunk):
            out.extend(part)
            if progress is not None:
                progress(len(out), length)
        return out

    async def write_area(
        self,
        command: int,
        start: int,
        values: Sequence[int],
        *,
        chunk: int = 256,
        progress: ProgressCallback | None = None,
    ) -> None:
        """EXPERIMENTAL [R]: write an area in chunks (write commands 0CH/0DH/11H/1DH/20H/21H/3AH).
        Writing programs or parameters partially may make a real CPU malfunction (§7.8)."""
        what = f"write {PROGRAM_COMMANDS.get(command, ('?', False))[0]} @{start:X}H x{len(values)}"
        if command not in PROGRAM_COMMANDS or not PROGRAM_COMMANDS[command][1]:
            raise self._bad(f"{command!r} is not a program/parameter/comment write", what)
        self._xint(chunk, 1, 256, "chunk", what)
        for k in range(0, len(values), chunk):
            part = list(values[k : k + chunk])
            try:
                req = build(command, start + k, part, self.code, **self._hdr())
            except LocalProtocolError as exc:
                raise self._bad(exc.message, what) from None
            await self._xcall(req, what, is_write=True)
            if progress is not None:
                progress(k + len(part), len(values))

    async def analyse_parameters(self) -> None:
        """12H parameter analysis request (after writing parameters, §7.8)."""
        await self.opaque(0x12, b"", 0)
