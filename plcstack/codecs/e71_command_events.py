"""E71 command constants and the response events of the commands beyond 00H-09H (§7.4-§7.8, §9).

The numbers a caller of those commands needs (file register device code, block and buffer sizes,
the CPU model table of 15H, the opaque command set) and the events their answers decode to,
apart from the request classes of :mod:`plcstack.codecs.e71_commands`, which imports them and
re-exports every name: import from there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from plcstack.codecs.e71_events import ExtensionResponse
from plcstack.codecs.e71_wire import Code, Writer

__all__ = [
    "CPU_MODELS",
    "EXT_FILE_BLOCK_SIZE",
    "FIXED_BUFFER_MAX_WORDS",
    "OPAQUE_COMMANDS",
    "RANDOM_BUFFER_MAX_WORDS",
    "RANDOM_BUFFER_WORDS",
    "R_CODE",
    "BytesResponse",
    "CpuModelResponse",
    "LoopbackResponse",
    "OpaqueResponse",
    "RandomBufferResponse",
    "cpu_model_name",
]

#: device code of the file register R, the only device of 17H-1BH, 3BH, 3CH (§7.4)
R_CODE: Final = 0x5220
#: registers per extended file register block; 3BH/3CH number = (block - 1) * 8192 + register
EXT_FILE_BLOCK_SIZE: Final = 8192
#: random access buffer size in words (internal addresses 0-6143, §9)
RANDOM_BUFFER_WORDS: Final = 6144
#: words per random access buffer message: binary 1017, ASCII 508 (§1.5, §9)
RANDOM_BUFFER_MAX_WORDS: Final = {Code.BINARY: 1017, Code.ASCII: 508}
#: words per fixed buffer telegram with procedure: binary 1017, ASCII 508 (§1.5, §8.1)
FIXED_BUFFER_MAX_WORDS: Final = {Code.BINARY: 1017, Code.ASCII: 508}

#: CPU model codes of 15H (§7.6, seed Tab. 10-35; F3H from [FX])
CPU_MODELS: Final[dict[int, str]] = {
    0xA1: "A1, A1N",
    0xA2: "A2, A2-S1, A2N, A2N-S1, A2S",
    0xA3: "A3, A3N",
    0x92: "A2A, A2U, A2AS, Q2A, Q2AS, Q2ASH",
    0x93: "A2A-S1, A2U-S1, A2AS-S1, Q2A-S1, Q2AS-S1, Q2ASH-S1",
    0x94: "A3A, A3U, A4U, Q3A, Q4A, AJ72LP25/BR15, AJ72QLP25/QBR15",
    0x98: "A0J2H, A1S, A1SJ",
    0x9A: "A2C",
    0xAB: "AJ72P25/R25",
    0xF3: "FX3U, FX3UC",
}


def cpu_model_name(model_code: int) -> str:
    """The CPU names of a 15H model code, or ``unknown model code XXH``."""
    return CPU_MODELS.get(model_code, f"unknown model code {model_code:02X}H")


#: commands kept opaque (command + raw body): their layout is not documented (§7.8, §13 A11)
OPAQUE_COMMANDS: Final = frozenset(
    {0x0A, 0x0B, 0x0C, 0x0D, 0x10, 0x11, 0x12, 0x1C, 0x1D, 0x1E, 0x1F, 0x20, 0x21, 0x39, 0x3A}
)


# ---------------------------------------------------------------------------------------------
# Response events (client side) that the core does not have


@dataclass(frozen=True, slots=True)
class BytesResponse(ExtensionResponse):
    """Normal completion with byte data (8EH special module buffer memory)."""

    command: int
    data: bytes

    def encode(self, code: Code) -> bytes:
        w = Writer(code is Code.ASCII)
        w.num((self.command | 0x80) & 0xFF, 1)
        w.num(0, 1)
        w.raw(self.data)
        return w.getvalue()


@dataclass(frozen=True, slots=True)
class CpuModelResponse(ExtensionResponse):
    """95H: the CPU model code (§7.6); :attr:`name` from the table of seed Tab. 10-35."""

    model_code: int
    command: int = 0x15

    @property
    def name(self) -> str:
        return cpu_model_name(self.model_code)

    def encode(self, code: Code) -> bytes:
        w = Writer(code is Code.ASCII)
        w.num(0x95, 1)
        w.num(0, 1)
        w.num(self.model_code, 1)
        w.num(0, 1)
        return w.getvalue()


@dataclass(frozen=True, slots=True)
class LoopbackResponse(ExtensionResponse):
    """96H: the loopback data echoed (§7.7); ``len(data)`` 1-256 (256 = length byte 00H)."""

    data: bytes
    command: int = 0x16

    def encode(self, code: Code) -> bytes:
        w = Writer(code is Code.ASCII)
        w.num(0x96, 1)
        w.num(0, 1)
        w.num(len(self.data) & 0xFF, 1)
        w.raw(self.data)
        return w.getvalue()


@dataclass(frozen=True, slots=True)
class OpaqueResponse(ExtensionResponse):
    """Normal completion of an opaque command: ``data`` = the raw wire bytes after the end code
    (binary bytes, or the ASCII text as received)."""

    command: int
    data: bytes = b""

    def encode(self, code: Code) -> bytes:
        w = Writer(code is Code.ASCII)
        w.num((self.command | 0x80) & 0xFF, 1)
        w.num(0, 1)
        return w.getvalue() + self.data


@dataclass(frozen=True, slots=True)
class RandomBufferResponse(ExtensionResponse):
    """E71 side of E1H/E2H: end code and (read, end code 00H) words. ``ascii_sub_chars`` = 4
    renders the subheader as ``E100``/``E200`` (the 6-char form of §13 A2); default 2."""

    command: int
    end_code: int = 0
    values: tuple[int, ...] = ()
    ascii_sub_chars: int = 2

    def encode(self, code: Code) -> bytes:
        w = Writer(code is Code.ASCII)
        w.num((self.command | 0x80) & 0xFF, 1)
        if code is Code.ASCII and self.ascii_sub_chars == 4:
            w.num(0, 1)
        w.num(self.end_code, 1)
        if self.end_code == 0:
            w.words(self.values)
        return w.getvalue()
