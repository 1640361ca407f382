"""AS511 jobs (spec part B.7): the functions this library uses, their parameter frames and
the parsing of their answers. Pure data; :class:`plcstack.codecs.as511.ClientConnection` runs a
:class:`Job` as one transaction.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from plcstack.codecs._common import slot_init
from plcstack.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "FN_BLOCK_LIST",
    "FN_B_INFO",
    "FN_OPERATING_MODE",
    "FN_READ",
    "FN_SYSTEM_PARAMETERS",
    "FN_WRITE",
    "FUNCTION_NAMES",
    "MAX_READ_BYTES",
    "MAX_WRITE_BYTES",
    "OPERATING_MODES",
    "READ_PREFIX",
    "SYSTEM_ADDRESS_NAMES",
    "BlockInfo",
    "Job",
    "SystemAddresses",
    "b_info_job",
    "block_list_job",
    "header_matches",
    "operating_mode_job",
    "parse_b_info",
    "parse_read",
    "parse_system_parameters",
    "read_job",
    "run_job",
    "stop_job",
    "system_parameters_job",
    "write_job",
]

FN_WRITE = 0x03
FN_READ = 0x04
FN_SYSTEM_PARAMETERS = 0x18
FN_B_INFO = 0x1A
FN_BLOCK_LIST = 0x1B
FN_OPERATING_MODE = 0x1E

#: the function codes of B.7 ([O-PS] as511.h, names translated): what the Wireshark dissector
#: shows; this library uses 03h, 04h, 18h, 1Ah, 1Bh and 1Eh
FUNCTION_NAMES: dict[int, str] = {
    0x03: "write memory (DB_WRITE)",
    0x04: "read memory (DB_READ)",
    0x05: "write block",
    0x06: "read block",
    0x07: "compress memory",
    0x08: "write DB (block transfer)",
    0x09: "delete block",
    0x0E: "debug start",
    0x10: "debug continue",
    0x11: "delete all blocks",
    0x13: "control outputs",
    0x14: "status variable",
    0x15: "status block",
    0x16: "debug init",
    0x17: "control outputs init",
    0x18: "read system parameters",
    0x19: "read RAM info",
    0x1A: "read block info (B_INFO)",
    0x1B: "read block address list",
    0x1C: "read B-stack",
    0x1D: "read U-stack",
    0x1E: "change operating mode",
    0x80: "online start",
    0x81: "online stop",
}
#: the mode byte of 1Eh (B.7.5)
OPERATING_MODES: dict[int, str] = {0x00: "stop", 0x01: "restart (Neustart)", 0x02: "warm restart"}
#: the addresses at the start of the 18h answer (B.7.1), in wire order (:class:`SystemAddresses`)
SYSTEM_ADDRESS_NAMES: tuple[str, ...] = (
    "ESF (input signal formers)",
    "ASF (output signal formers)",
    "PAE (process image of inputs)",
    "PAA (process image of outputs)",
    "flags",
    "timers",
    "counters",
    "system data",
)

#: [R] B.7.3/B.7.4: the client splits reads and writes into transactions of <= 512 bytes
MAX_READ_BYTES = 512
MAX_WRITE_BYTES = 512
#: leading bytes of a 04h answer (B.7.3, D.B2)
READ_PREFIX = 5


# -- jobs and their answers (B.7) --------------------------------------------------------------
@slot_init
@dataclass(frozen=True, slots=True)
class Job:
    """One AS511 transaction: function code, unstuffed parameters, whether a data frame follows.

    ``response_length`` is the exact unstuffed length of the data frame when known (04h, 1Ah);
    the PG aborts an answer that grows beyond it (plus a little slack) and the client checks it.
    """

    fn: int
    params: bytes = b""
    has_response: bool = True
    response_length: int | None = None


def system_parameters_job() -> Job:
    return Job(FN_SYSTEM_PARAMETERS, b"", True, None)


def b_info_job(block_type: int, number: int) -> Job:
    if not (0 <= block_type <= 0xFF and 0 <= number <= 0xFF):
        raise LocalProtocolError(f"block type {block_type} / number {number} out of range")
    return Job(FN_B_INFO, bytes([block_type, number]), True, 13)


def read_job(start: int, length: int) -> Job:
    """04h: ``length`` bytes from absolute ``start`` (inclusive end address on the wire)."""
    if length < 1 or start < 0 or start + length > 0x10000:
        raise LocalProtocolError(f"read of {length} bytes at {start:#06x} is outside 64 KiB")
    return Job(FN_READ, struct.pack(">HH", start, start + length - 1), True, READ_PREFIX + length)


def write_job(start: int, data: bytes) -> Job:
    """03h: write ``data`` at absolute ``start``; no data frame in the answer."""
    if not data or start < 0 or start + len(data) > 0x10000:
        raise LocalProtocolError(f"write of {len(data)} bytes at {start:#06x} is outside 64 KiB")
    return Job(FN_WRITE, struct.pack(">H", start) + bytes(data), False, None)


def block_list_job(block_type: int) -> Job:
    return Job(FN_BLOCK_LIST, bytes([block_type]), True, None)


def operating_mode_job(mode: int) -> Job:
    """1Eh (135U/155U): 00 stop, 01 restart, 02 warm restart; 01/02 answer one byte (B.7.5)."""
    if mode not in (0, 1, 2):
        raise LocalProtocolError(f"operating mode {mode} is not 0 (stop), 1 or 2 (restart)")
    return Job(FN_OPERATING_MODE, bytes([mode]), mode != 0, 1 if mode else None)


def stop_job(system_data: int) -> Job:
    """Stop a small CPU: libnodave's ``88 04`` at system data + 0Ch (B.7.5, B.11.4)."""
    return write_job(system_data + 0x0C, b"\x88\x04")


def run_job(system_data: int) -> Job:
    """Start (restart) a small CPU: ``68 00`` at system data + 0Ch (B.7.5, B.11.4)."""
    return write_job(system_data + 0x0C, b"\x68\x00")


@dataclass(frozen=True, slots=True)
class SystemAddresses:
    """The part of the 18h answer the client uses (offsets 0-21 of B.7.1) and the raw block."""

    esf: int
    asf: int
    inputs: int  # PAE
    outputs: int  # PAA
    flags: int
    timers: int
    counters: int
    system_data: int
    software_version: int
    status: int
    end_of_ram: int
    raw: bytes


def parse_system_parameters(payload: bytes) -> SystemAddresses:
    """Decode an 18h data frame (``00`` + parameters); at least 00 + 44 bytes as libnodave."""
    if len(payload) < 45:
        raise RemoteProtocolError(
            f"system parameter answer has {len(payload)} bytes, expected at least 45"
        )
    if payload[0] != 0:
        raise RemoteProtocolError(f"system parameter answer starts with {payload[0]:02X}h, not 00")
    esf, asf, pae, paa, flags, timers, counters, system, version, status, end_of_ram = (
        struct.unpack_from(">8HBBH", payload, 1)
    )
    return SystemAddresses(
        esf,
        asf,
        pae,
        paa,
        flags,
        timers,
        counters,
        system,
        version,
        status,
        end_of_ram,
        raw=bytes(payload[1:]),
    )


@dataclass(frozen=True, slots=True)
class BlockInfo:
    """B_INFO (1Ah) of one block: where DW0 is and how long the block is (B.7.2)."""

    block_type: int
    number: int
    dw0: int
    length_words: int  # including the 5-word header
    header: bytes

    @property
    def data_bytes(self) -> int:
        return max(0, (self.length_words - 5) * 2)

    @property
    def header_address(self) -> int:
        return self.dw0 - 10


def header_matches(header: bytes, block_type: int, number: int) -> bool:
    """The signature check of B.7.2: ``70 70``, ``40h + type``, number."""
    return (
        len(header) >= 10
        and header[0] == 0x70
        and header[1] == 0x70
        and header[2] == 0x40 + block_type
        and header[3] == number
    )


def parse_b_info(payload: bytes, block_type: int, number: int) -> BlockInfo | None:
    """Decode a 1Ah answer; ``None`` when the signature check fails (block unusable, D.B3)."""
    if len(payload) < 13 or payload[0] != 0:
        return None
    header = bytes(payload[3:13])
    if not header_matches(header, block_type, number):
        return None
    dw0 = (payload[1] << 8) | payload[2]
    length = (header[8] << 8) | header[9]
    if length < 5:
        return None
    return BlockInfo(block_type, number, dw0, length, header)


def parse_read(payload: bytes, length: int, *, strict: bool = False) -> bytes:
    """The data of a 04h answer: skip the 5 leading bytes (zero in strict mode; D.B2)."""
    if len(payload) != READ_PREFIX + length:
        raise RemoteProtocolError(
            f"read answer has {len(payload)} bytes, expected {READ_PREFIX + length} "
            f"(5 leading bytes + {length} data bytes)"
        )
    # [R] D.B2: skip the 5 leading bytes; only strict mode insists that they are zero
    if strict and any(payload[:READ_PREFIX]):
        raise RemoteProtocolError(f"read answer starts with {payload[:5].hex(' ')}, not 5 x 00")
    return bytes(payload[READ_PREFIX:])
