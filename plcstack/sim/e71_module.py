"""Simulated E71 module and CPU state beyond device memory (spec §7.4-§7.8, §9, App. A).

``module_of(memory)`` gives the :class:`E71Module` that belongs to a
:class:`~plcstack.sim.melsec_memory.MelsecMemory` (created on first use), so every connection of a
simulator shares it, as they share the CPU. It holds the key switch and remote RUN/STOP state,
the CPU model code, the random access buffer, special function modules, extended file register
blocks and the byte/word areas of parameters, programs and comments. :func:`execute_extension`
answers the requests of :mod:`plcstack.codecs.e71_commands` as an E71 would.

Mode gating (§7.1 table, §13 A12): reads and 13H-16H work in every state; writes need STOP or
RUN with write-during-RUN enabled (else 55H); parameter writes (11H, 12H) and microcomputer SUB
writes (21H) need STOP; sequence/microcomputer MAIN program writes in RUN only on an A3-class CPU
with M9050 OFF and M9051 ON (set values 0CH/0DH at FE00H+ follow the write-during-RUN switch).
"""

from __future__ import annotations

import enum
import weakref
from array import array
from collections.abc import Callable
from typing import Final

from plcstack.codecs.e71 import (
    Ack,
    Code,
    CpuGroup,
    Device,
    ErrorResponse,
    ExtensionRequest,
    ExtensionResponse,
    Response,
    WordsResponse,
)
from plcstack.codecs.e71_commands import (
    EXT_FILE_BLOCK_SIZE,
    FIXED_BUFFER_MAX_WORDS,
    RANDOM_BUFFER_MAX_WORDS,
    RANDOM_BUFFER_WORDS,
    BytesResponse,
    CpuModelResponse,
    FixedBufferData,
    Loopback,
    LoopbackResponse,
    MonitorExt,
    OpaqueCommand,
    RandomBufferResponse,
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
from plcstack.codecs.e71_programs import (
    PROGRAM_COMMANDS,
    WORD_COMMANDS,
    encode_answer,
    parse_request,
)
from plcstack.codecs.e71_wire import Malformed
from plcstack.sim.melsec_memory import CpuState, MelsecMemory

__all__ = ["E71Module", "KeySwitch", "execute_extension", "module_of"]

#: CPU model code by CPU group (§5.2 groups, §7.6 codes): the first CPU of each group
GROUP_MODEL: Final = {
    CpuGroup.I: 0xA1,
    CpuGroup.II: 0xA2,
    CpuGroup.III: 0xA2,
    CpuGroup.IV: 0xA3,
    CpuGroup.V: 0x92,
    CpuGroup.VI: 0x93,
    CpuGroup.VII: 0x94,
}
#: CPUs that may write programs in RUN under conditions (*) of §7.1: A3, A3N, A3A, A3U, A4U
_A3_CLASS: Final = frozenset({0xA3, 0x94})
#: AnA/AnU CPUs (model codes 92H, 93H, 94H)
_AnA_AnU: Final = frozenset({0x92, 0x93, 0x94})
#: microcomputer program area size by model code (§7.8, seed Tab. 10-47)
_MICRO_SIZE: Final = {0xA1: 0x2800, 0x98: 0x3800, 0x9A: 0x3800, 0xA3: 0xE800, 0x94: 0xE800}


class KeySwitch(enum.Enum):
    """The CPU's key switch; with remote RUN/STOP it decides the state (seed Tab. 10-33)."""

    RUN = "RUN"
    STOP = "STOP"
    PAUSE = "PAUSE"
    STEP_RUN = "STEP-RUN"


class E71Module:
    """State of the E71 and its CPU that is not device memory (shared by all connections)."""

    def __init__(self, memory: MelsecMemory) -> None:
        self._memory = weakref.ref(memory)
        self.model_code: int = GROUP_MODEL[memory.group]
        self.key_switch = KeySwitch(memory.state.value)
        #: who stopped the CPU remotely ("E71" for a 14H, another name for another module)
        self.remote_stop_by: str | None = None
        #: §13 A2: 2 = ASCII random access buffer answers "E1"+end; 4 = "E100"+end
        self.rab_ascii_sub_chars = 2
        self.random_buffer: array[int] = array("H", bytes(2 * RANDOM_BUFFER_WORDS))
        #: module number -> buffer memory bytes (§7.5); an AD61-like module at 01H by default
        self.special_modules: dict[int, bytearray] = {0x01: bytearray(0x1000)}
        #: blocks the memory cassette can hold (beyond -> 57H); existing blocks (absent -> 58H)
        self.ext_cassette_blocks = 32
        self.ext_blocks: dict[int, array[int]] = {
            b: array("H", bytes(2 * EXT_FILE_BLOCK_SIZE)) for b in range(1, 9)
        }
        self.ext_monitor: tuple[tuple[int, int], ...] = ()
        # §7.8 areas [R]: parameters 3 kB, programs (steps) and T/C set values, comments, micro
        self.parameters = bytearray(0xC00)
        self.programs: dict[int, array[int]] = {
            0x0A: array("H", bytes(2 * 0x7800)),
            0x0B: array("H", bytes(2 * 0x7800)),
        }
        self.set_values: dict[int, array[int]] = {
            0x0A: array("H", bytes(2 * 512)),
            0x0B: array("H", bytes(2 * 512)),
        }
        micro = _MICRO_SIZE.get(self.model_code, 0x6800)
        self.micro: dict[int, bytearray] = {0x1E: bytearray(micro), 0x1F: bytearray(micro)}
        self.comments = bytearray(0x10000)
        self.ext_comments = bytearray(63 * 1024)
        self.parameter_analyses = 0
        #: buffer memory word 496 (§1.3): keep the connections when the CPU stops. [R] The
        #: simulator default is "enabled" (a real module's default 0 closes them on a STOP).
        self.comm_in_stop = True
        #: called after a remote STOP when ``comm_in_stop`` is off (the TCP simulator closes
        #: its connections)
        self.stop_listeners: list[Callable[[], None]] = []
        #: called with the 60H telegram words from a partner; returns the end code to answer
        self.fixed_buffer_handler: Callable[[tuple[int, ...]], int] | None = None
        self.fixed_buffer_received: list[tuple[int, ...]] = []
        self.refresh_status()

    # -- CPU state ------------------------------------------------------------------------
    @property
    def memory(self) -> MelsecMemory:
        mem = self._memory()
        if mem is None:  # pragma: no cover - the memory owns us through module_of
            raise RuntimeError("the MelsecMemory of this module is gone")
        return mem

    def set_key_switch(self, switch: KeySwitch) -> None:
        """Turn the key switch; a remote STOP stays in force (seed Tab. 10-33)."""
        self.key_switch = switch
        self._apply(stopped=self.remote_stop_by is not None)

    def _apply(self, *, stopped: bool) -> None:
        mem = self.memory
        if stopped or self.key_switch is KeySwitch.STOP:
            mem.state = CpuState.STOP
        elif self.key_switch is KeySwitch.PAUSE:
            mem.state = CpuState.PAUSE
        else:
            # [R] STEP-RUN is modelled as RUN (the core CPU model has RUN/STOP/PAUSE only)
            mem.state = CpuState.RUN
        self.refresh_status()

    def refresh_status(self) -> None:
        """Write D9015 from the CPU state (also after ``memory.state`` was set directly).

        [R] D9015 is the A-series special register "CPU operating status": bits 0-3 the state
        (0 RUN, 1 STOP, 2 PAUSE, 3 STEP-RUN), bits 4-7 the cause (0 key switch, 2 remote).
        """
        mem = self.memory
        status = {CpuState.RUN: 0, CpuState.STOP: 1, CpuState.PAUSE: 2}[mem.state]
        if status == 0 and self.key_switch is KeySwitch.STEP_RUN:
            status = 3
        cause = 2 if self.remote_stop_by is not None and status == 1 else 0
        mem.write_words(Device.D, 9015, [status | cause << 4])

    def remote_run(self, by: str = "E71") -> int:
        """Remote RUN; returns the abnormal code 18H when another module stopped the CPU."""
        if self.remote_stop_by is not None and self.remote_stop_by != by:
            return 0x18
        self.remote_stop_by = None
        self._apply(stopped=False)
        return 0

    def remote_stop(self, by: str = "E71") -> int:
        if self.remote_stop_by is not None and self.remote_stop_by != by:
            return 0x18
        self.remote_stop_by = by
        self._apply(stopped=True)
        if not self.comm_in_stop:
            for listener in list(self.stop_listeners):
                listener()
        return 0

    def add_special_module(self, number: int, size: int = 0x1000) -> bytearray:
        """Mount a special function module with ``size`` bytes of buffer memory at ``number``."""
        buf = bytearray(size)
        self.special_modules[number] = buf
        return buf

    # -- PLC-program side of the random access buffer (buffer memory 4608-7679, §9) ----------
    def rab_read(self, address: int, count: int) -> list[int]:
        return self.random_buffer[address : address + count].tolist()

    def rab_write(self, address: int, values: list[int] | tuple[int, ...]) -> None:
        self.random_buffer[address : address + len(values)] = array("H", values)

    # -- extended file registers ---------------------------------------------------------
    def ext_check(self, block: int, number: int, count: int) -> None:
        if not 1 <= block <= self.ext_cassette_blocks:
            raise Malformed(0x57, f"block {block} beyond the memory cassette")
        if block not in self.ext_blocks:
            raise Malformed(0x58, f"block {block} does not exist")
        if number >= EXT_FILE_BLOCK_SIZE:
            raise Malformed(0x58, f"R{number} beyond 8191")
        if number + count > EXT_FILE_BLOCK_SIZE:
            raise Malformed(0x57, f"R{number} + {count} beyond 8191")

    def _direct_cells(self, number: int, count: int) -> list[tuple[array[int], int]]:
        """(block array, index) of each register of a 3BH/3CH span (number = (b-1)*8192 + r)."""
        cells = []
        for k in range(count):
            block, reg = divmod(number + k, EXT_FILE_BLOCK_SIZE)
            arr = self.ext_blocks.get(block + 1)
            if arr is None:
                raise Malformed(0x58 if k == 0 else 0x57, f"block {block + 1} does not exist")
            cells.append((arr, reg))
        return cells


_MODULES: weakref.WeakKeyDictionary[MelsecMemory, E71Module] = weakref.WeakKeyDictionary()


def module_of(memory: MelsecMemory) -> E71Module:
    """The :class:`E71Module` of ``memory`` (one per simulated PLC, created on first use)."""
    module = _MODULES.get(memory)
    if module is None:
        module = _MODULES[memory] = E71Module(memory)
    return module


# ---------------------------------------------------------------------------------------------
# Execution

_WRITES: Final = frozenset({0x0F, 0x18, 0x19, 0x3C, 0x0C, 0x0D, 0x11, 0x12, 0x1D, 0x20, 0x21})
_WRITES_ALL = _WRITES | {0x3A}
_STOP_ONLY: Final = frozenset({0x11, 0x12, 0x21})
_EXT_FILE: Final = frozenset({0x17, 0x18, 0x19, 0x1A, 0x1B, 0x3B, 0x3C})


def execute_extension(
    memory: MelsecMemory, req: ExtensionRequest, code: Code
) -> Response | ExtensionResponse:
    """What the E71 answers to one request of :mod:`plcstack.codecs.e71_commands`."""
    module = module_of(memory)
    module.refresh_status()
    if isinstance(req, (ReadRandomBuffer, WriteRandomBuffer)):
        return _random_buffer(module, req, code)
    if isinstance(req, FixedBufferData):
        return _fixed_buffer(module, req, code)
    cmd = req.COMMAND
    if getattr(req, "pc", 0xFF) != 0xFF:
        # PC 00H-40H address MELSECNET stations; the simulated E71 has no network (5BH/10H).
        return ErrorResponse(cmd, 0x5B, 0x10)
    try:
        return _execute(memory, module, req, code)
    except Malformed as exc:
        return ErrorResponse(cmd, exc.end_code)


def _mode_error(memory: MelsecMemory, module: E71Module, cmd: int, address: int = 0) -> bool:
    """Whether the CPU state refuses ``cmd`` (55H), per §7.1 and §13 A12."""
    if cmd not in _WRITES_ALL or memory.state is CpuState.STOP:
        return False
    if cmd in _STOP_ONLY:
        return True
    if cmd in (0x0C, 0x0D, 0x20) and not (cmd != 0x20 and address >= 0xFE00):
        # program write in RUN: only A3-class CPUs with M9050 OFF and M9051 ON (*)
        m9050, m9051 = memory.read_bits(Device.M, 9050, 2)
        return not (memory.write_in_run and module.model_code in _A3_CLASS and not m9050 and m9051)
    return not memory.writes_allowed


def _execute(
    memory: MelsecMemory, module: E71Module, req: ExtensionRequest, code: Code
) -> Response | ExtensionResponse:
    cmd = req.COMMAND
    if isinstance(req, RemoteRun):
        abnormal = module.remote_run()
        return ErrorResponse(cmd, 0x5B, abnormal) if abnormal else Ack(cmd)
    if isinstance(req, RemoteStop):
        abnormal = module.remote_stop()
        return ErrorResponse(cmd, 0x5B, abnormal) if abnormal else Ack(cmd)
    if isinstance(req, ReadCpuModel):
        return CpuModelResponse(module.model_code)
    if isinstance(req, Loopback):
        return LoopbackResponse(req.data)
    if isinstance(req, (ReadSpecial, WriteSpecial)):
        buf = module.special_modules.get(req.module)
        if buf is None:
            return ErrorResponse(cmd, 0x5B, 0x12)
        count = req.count if isinstance(req, ReadSpecial) else len(req.data)
        if req.address >= len(buf):
            return ErrorResponse(cmd, 0x58)  # [R] head address beyond the buffer memory
        if req.address + count > len(buf):
            return ErrorResponse(cmd, 0x57)
        if isinstance(req, ReadSpecial):
            return BytesResponse(cmd, bytes(buf[req.address : req.address + count]))
        if _mode_error(memory, module, cmd):
            return ErrorResponse(cmd, 0x55)
        buf[req.address : req.address + count] = req.data
        return Ack(cmd)
    if cmd in _EXT_FILE:
        return _ext_file(memory, module, req)
    if isinstance(req, OpaqueCommand):
        return _program(memory, module, req, code)
    return ErrorResponse(cmd, 0x50)  # pragma: no cover - every decoder has a branch


def _ext_file(
    memory: MelsecMemory, module: E71Module, req: ExtensionRequest
) -> Response | ExtensionResponse:
    cmd = req.COMMAND
    if memory.group is CpuGroup.I:
        return ErrorResponse(cmd, 0x59)  # extended file registers on an A1(N)
    if isinstance(req, MonitorExt):
        if memory.monitor is None or memory.monitor[0] != "ext":
            return ErrorResponse(cmd, 0x57)  # §13 A10: 1BH only after 1AH
        return WordsResponse(cmd, tuple(module.ext_blocks[b][n] for b, n in module.ext_monitor))
    if isinstance(req, (ReadExtFile, WriteExtFile)):
        count = req.count if isinstance(req, ReadExtFile) else len(req.values)
        module.ext_check(req.block, req.number, 1)
        if not 1 <= count <= 256:
            return ErrorResponse(cmd, 0x57)
        module.ext_check(req.block, req.number, count)
        arr = module.ext_blocks[req.block]
        if isinstance(req, ReadExtFile):
            return WordsResponse(cmd, tuple(arr[req.number : req.number + count]))
        if _mode_error(memory, module, cmd):
            return ErrorResponse(cmd, 0x55)
        arr[req.number : req.number + count] = array("H", req.values)
        return Ack(cmd)
    if isinstance(req, (TestExtFile, RegisterMonitorExt)):
        limit = 40 if isinstance(req, TestExtFile) else 20
        for point in req.points:
            module.ext_check(point[0], point[1], 1)
        if not 1 <= len(req.points) <= limit:
            return ErrorResponse(cmd, 0x57)
        if isinstance(req, RegisterMonitorExt):
            # one registration per CPU, shared with 06H/07H and by all connections (§7.3)
            memory.monitor = ("ext", ())
            module.ext_monitor = req.points
            return Ack(cmd)
        if _mode_error(memory, module, cmd):
            return ErrorResponse(cmd, 0x55)
        for block, number, value in req.points:
            module.ext_blocks[block][number] = value
        return Ack(cmd)
    if isinstance(req, (ReadExtDirect, WriteExtDirect)):
        count = req.count if isinstance(req, ReadExtDirect) else len(req.values)
        module._direct_cells(req.number, 1)
        if not 1 <= count <= 256:
            return ErrorResponse(cmd, 0x57)
        cells = module._direct_cells(req.number, count)
        if isinstance(req, ReadExtDirect):
            return WordsResponse(cmd, tuple(arr[i] for arr, i in cells))
        if _mode_error(memory, module, cmd):
            return ErrorResponse(cmd, 0x55)
        for (arr, i), value in zip(cells, req.values, strict=True):
            arr[i] = value
        return Ack(cmd)
    return ErrorResponse(cmd, 0x50)  # pragma: no cover


def _program(
    memory: MelsecMemory, module: E71Module, req: OpaqueCommand, code: Code
) -> Response | ExtensionResponse:
    """0AH-0DH, 10H-12H, 1CH-21H, 39H/3AH on byte/word arrays by the [R] layout of §7.8."""
    cmd = req.command
    if cmd == 0x12:
        if req.body:
            return ErrorResponse(cmd, 0x57)
        if _mode_error(memory, module, cmd):
            return ErrorResponse(cmd, 0x55)
        module.parameter_analyses += 1
        return Ack(cmd)
    access = parse_request(req, code)
    is_write = PROGRAM_COMMANDS[cmd][1]
    # §7.1 CPU-type restrictions; [R] the refusal code is not documented, 58H is used
    if cmd in (0x39, 0x3A) and module.model_code not in _AnA_AnU:
        return ErrorResponse(cmd, 0x58)  # extended comments: AnA/AnU only (§13 A12)
    if cmd in (0x1F, 0x21) and module.model_code not in _A3_CLASS:
        return ErrorResponse(cmd, 0x58)  # microcomputer SUB: A3/A3N/A3A only
    area: bytearray | array[int]
    if cmd in WORD_COMMANDS:
        key = 0x0A if cmd in (0x0A, 0x0C) else 0x0B
        if cmd in (0x0B, 0x0D) and module.model_code not in _A3_CLASS:
            return ErrorResponse(cmd, 0x58)  # [R] sub programs only on A3-class CPUs
        if access.address >= 0xFE00:
            # T set values FE00H + n, C set values FF00H + n (n <= 255)
            area, start = module.set_values[key], access.address - 0xFE00
        else:
            area, start = module.programs[key], access.address
            if start >= len(area):
                return ErrorResponse(cmd, 0x5B, 0x13)  # program step number error
    else:
        start = access.address
        if cmd in (0x10, 0x11):
            area = module.parameters
        elif cmd in (0x1C, 0x1D):
            area = module.comments
        elif cmd in (0x39, 0x3A):
            area = module.ext_comments
        else:
            area = module.micro[0x1E if cmd in (0x1E, 0x20) else 0x1F]
        if start >= len(area):
            return ErrorResponse(cmd, 0x58 if cmd in (0x10, 0x11) else 0x57)
    if start + access.count > len(area):
        return ErrorResponse(cmd, 0x57)
    if is_write:
        if _mode_error(memory, module, cmd, access.address):
            return ErrorResponse(cmd, 0x55)
        assert access.data is not None
        if isinstance(area, bytearray):
            area[start : start + access.count] = bytes(access.data)
        else:
            area[start : start + access.count] = array("H", access.data)
        return Ack(cmd)
    return encode_answer(cmd, list(area[start : start + access.count]), code)


def _random_buffer(
    module: E71Module, req: ReadRandomBuffer | WriteRandomBuffer, code: Code
) -> ExtensionResponse:
    """§9: 51H start outside 0-6143, 52H start + length outside or too long; no mode gating
    (the buffer is the E71's own memory)."""
    cmd = req.COMMAND
    count = req.count if isinstance(req, ReadRandomBuffer) else len(req.values)
    sub = module.rab_ascii_sub_chars if code is Code.ASCII else 2
    if req.address >= RANDOM_BUFFER_WORDS:
        return RandomBufferResponse(cmd, 0x51, ascii_sub_chars=sub)
    if not 1 <= count <= RANDOM_BUFFER_MAX_WORDS[code] or req.address + count > RANDOM_BUFFER_WORDS:
        return RandomBufferResponse(cmd, 0x52, ascii_sub_chars=sub)
    if isinstance(req, ReadRandomBuffer):
        return RandomBufferResponse(
            cmd, 0, tuple(module.rab_read(req.address, count)), ascii_sub_chars=sub
        )
    module.rab_write(req.address, req.values)
    return RandomBufferResponse(cmd, 0, ascii_sub_chars=sub)


def _fixed_buffer(module: E71Module, req: FixedBufferData, code: Code) -> Response:
    """60H from a partner: stored for the PLC program; the handler decides the end code.
    52H when the length is outside 1-1017 (ASCII 1-508) words (§8.1, seed Tab. 7-2)."""
    if not 1 <= len(req.values) <= FIXED_BUFFER_MAX_WORDS[code]:
        return ErrorResponse(0x60, 0x52)
    if module.fixed_buffer_handler is not None:
        end = module.fixed_buffer_handler(req.values)
    else:
        module.fixed_buffer_received.append(req.values)
        end = 0
    return Ack(0x60) if end == 0 else ErrorResponse(0x60, end)
