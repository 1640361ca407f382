"""The memory of a simulated S5-90U...115U CPU, shared by the S5-LAN, AS511 and FETCH/WRITE sims.

Modelled the way the CPU has it (spec part B.6): one 64 KiB byte-addressed space. Inputs, outputs,
flags, timers, counters and system data sit at base addresses given by the system parameters
(B.7.1); data blocks are real blocks with the 10-byte header, allocated in RAM, and move when the
memory is compressed. Keeping the real layout (instead of a dict of areas) means an AS511 absolute
read sees exactly what a FETCH of the same DB returns, and "the block moved" can be simulated.

All words are big-endian (S5 byte order). Access errors carry the S5 error numbers that the
S5-LAN module and FETCH/WRITE share: 2 = area/block does not exist, 3 = area too small.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field

__all__ = [
    "AREA_SIZES",
    "BLOCK_HEADER_BYTES",
    "Area",
    "BlockType",
    "S5AccessError",
    "S5Memory",
    "SystemParameters",
]

BLOCK_HEADER_BYTES = 10
_SYNC = b"\x70\x70"


class BlockType(enum.IntEnum):
    """AS511 block type codes (B.6)."""

    DB = 0x01
    SB = 0x02
    PB = 0x04
    FX = 0x05
    FB = 0x08
    DX = 0x0C
    OB = 0x10


class Area(enum.Enum):
    """Byte areas outside blocks, named by their S5 operand letters (German / English)."""

    INPUTS = "E"  # PAE, process image of inputs (I)
    OUTPUTS = "A"  # PAA, process image of outputs (Q)
    FLAGS = "M"
    TIMERS = "T"  # one word per timer
    COUNTERS = "Z"  # one word per counter (C)
    SYSTEM = "BS"  # system data, one word per BS word


#: bytes per area (S5-115U-like: 128 input and output bytes, 256 flag bytes, 128 timers/counters)
AREA_SIZES: dict[Area, int] = {
    Area.INPUTS: 128,
    Area.OUTPUTS: 128,
    Area.FLAGS: 256,
    Area.TIMERS: 256,
    Area.COUNTERS: 256,
    Area.SYSTEM: 512,
}


class S5AccessError(Exception):
    """An access the CPU would refuse. ``code`` is the shared S5 error number (2 or 3)."""

    def __init__(self, code: int, message: str) -> None:
        self.code = code
        super().__init__(message)


@dataclass
class SystemParameters:
    """The system parameter block of function 18h (B.7.1); defaults are the spec's [R] values."""

    esf: int = 0x0000
    asf: int = 0x0000
    pae: int = 0xEF00
    paa: int = 0xEF80
    flags: int = 0xEE00
    timers: int = 0xED00
    counters: int = 0xEC00
    system_data: int = 0xEA00
    software_version: int = 0x00
    status: int = 0x00
    end_of_ram: int = 0x7FFF
    system_program_ram: int = 0x0000
    block_list_lengths: tuple[int, ...] = (0x0200,) * 7
    db0_list_length: int = 0x0000
    cpu_id2: int = 0x00
    slot_id: int = 0x00
    block_header_length: int = 0x0005
    cpu_id: int = 0x00
    trailer: bytes = field(default=bytes(7))

    def to_bytes(self) -> bytes:
        """The 50 parameter bytes (without the leading 00 of the AS511 answer)."""
        out = struct.pack(
            ">8HBBHH",
            self.esf,
            self.asf,
            self.pae,
            self.paa,
            self.flags,
            self.timers,
            self.counters,
            self.system_data,
            self.software_version,
            self.status,
            self.end_of_ram,
            self.system_program_ram,
        )
        out += struct.pack(">7H", *self.block_list_lengths)
        out += struct.pack(
            ">HBBH", self.db0_list_length, self.cpu_id2, self.slot_id, self.block_header_length
        )
        out += bytes([0x00, self.cpu_id]) + bytes(6)
        assert len(out) == 50
        return out

    def base(self, area: Area) -> int:
        return {
            Area.INPUTS: self.pae,
            Area.OUTPUTS: self.paa,
            Area.FLAGS: self.flags,
            Area.TIMERS: self.timers,
            Area.COUNTERS: self.counters,
            Area.SYSTEM: self.system_data,
        }[area]


@dataclass
class _Block:
    type: BlockType
    number: int
    header_address: int
    length_words: int  # including the 5-word header

    @property
    def dw0_address(self) -> int:
        return self.header_address + BLOCK_HEADER_BYTES

    @property
    def data_bytes(self) -> int:
        return (self.length_words - 5) * 2


class S5Memory:
    """A 64 KiB S5 address space with blocks, areas and the system parameters.

    Blocks are allocated from ``ram_start`` upwards; :meth:`delete_block` leaves a gap that
    :meth:`compress` closes by moving later blocks down (as the PG function "compress" does), which
    changes their DW0 addresses: exactly the event an AS511 client's address cache must survive.
    """

    def __init__(
        self,
        params: SystemParameters | None = None,
        *,
        ram_start: int = 0x0100,
        default_dbs: dict[int, int] | None = None,
    ) -> None:
        self.params = params or SystemParameters()
        self.image = bytearray(0x10000)
        self.ram_start = ram_start
        self._blocks: dict[tuple[BlockType, int], _Block] = {}
        self._next_free = ram_start
        for number, words in (default_dbs if default_dbs is not None else {}).items():
            self.create_block(BlockType.DB, number, words)

    # -- blocks ------------------------------------------------------------------------------
    def create_block(
        self, type: BlockType, number: int, data_words: int, data: bytes | None = None
    ) -> int:
        """Create (or replace) a block with ``data_words`` data words; returns its DW0 address."""
        if not 1 <= number <= 255:
            raise ValueError(f"block number {number} outside 1..255")
        if not 0 <= data_words <= 0x7FFF:
            raise ValueError(f"block length {data_words} words out of range")
        if (type, number) in self._blocks:
            self.delete_block(type, number)
        length_words = data_words + 5
        size = length_words * 2
        if self._next_free + size - 1 > self.params.end_of_ram:
            self.compress()
            if self._next_free + size - 1 > self.params.end_of_ram:
                raise ValueError(f"no room for {type.name}{number} ({size} bytes) in RAM")
        addr = self._next_free
        block = _Block(type, number, addr, length_words)
        header = (
            _SYNC + bytes([0x40 | type, number, 0x80, 0, 0, 0]) + struct.pack(">H", length_words)
        )
        self.image[addr : addr + BLOCK_HEADER_BYTES] = header
        body = bytes(data or b"")[: data_words * 2].ljust(data_words * 2, b"\x00")
        self.image[block.dw0_address : block.dw0_address + data_words * 2] = body
        self._blocks[(type, number)] = block
        self._next_free = addr + size
        return block.dw0_address

    def delete_block(self, type: BlockType, number: int) -> None:
        block = self._blocks.pop((type, number), None)
        if block is None:
            raise S5AccessError(2, f"{type.name}{number} does not exist")
        # Invalidate the header in place, as the CPU marks a deleted block (valid bits cleared).
        self.image[block.header_address + 2] &= 0x3F

    def compress(self) -> None:
        """Move all blocks down to close gaps; their addresses change (B.6, "compress")."""
        addr = self.ram_start
        for block in sorted(self._blocks.values(), key=lambda b: b.header_address):
            size = block.length_words * 2
            if block.header_address != addr:
                chunk = bytes(self.image[block.header_address : block.header_address + size])
                self.image[addr : addr + size] = chunk
                block.header_address = addr
            addr += size
        self.image[addr : self._next_free] = bytes(self._next_free - addr)
        self._next_free = addr

    def block_info(self, type: BlockType, number: int) -> tuple[int, bytes]:
        """``(DW0 address, 10-byte header)`` as function 1Ah answers it; error 2 if missing."""
        block = self._blocks.get((type, number))
        if block is None:
            raise S5AccessError(2, f"{type.name}{number} does not exist")
        header = bytes(self.image[block.header_address : block.dw0_address])
        return block.dw0_address, header

    def blocks(self) -> list[tuple[BlockType, int]]:
        return sorted(self._blocks, key=lambda k: (k[0], k[1]))

    # -- typed access (S5-LAN, FETCH/WRITE) ----------------------------------------------------
    def _block_span(self, type: BlockType, number: int, byte_offset: int, length: int) -> int:
        block = self._blocks.get((type, number))
        if block is None:
            raise S5AccessError(2, f"{type.name}{number} does not exist")
        if byte_offset < 0 or length < 0 or byte_offset + length > block.data_bytes:
            raise S5AccessError(
                3,
                f"{type.name}{number} has {block.data_bytes // 2} data words; "
                f"bytes {byte_offset}..{byte_offset + length - 1} are outside it",
            )
        return block.dw0_address + byte_offset

    def _area_span(self, area: Area, byte_offset: int, length: int) -> int:
        size = AREA_SIZES[area]
        if byte_offset < 0 or length < 0 or byte_offset + length > size:
            raise S5AccessError(
                3, f"area {area.value} has {size} bytes; {byte_offset}+{length} is outside it"
            )
        return self.params.base(area) + byte_offset

    def read_block(self, type: BlockType, number: int, byte_offset: int, length: int) -> bytes:
        addr = self._block_span(type, number, byte_offset, length)
        return bytes(self.image[addr : addr + length])

    def write_block(self, type: BlockType, number: int, byte_offset: int, data: bytes) -> None:
        addr = self._block_span(type, number, byte_offset, len(data))
        self.image[addr : addr + len(data)] = data

    def read_area(self, area: Area, byte_offset: int, length: int) -> bytes:
        addr = self._area_span(area, byte_offset, length)
        return bytes(self.image[addr : addr + length])

    def write_area(self, area: Area, byte_offset: int, data: bytes) -> None:
        addr = self._area_span(area, byte_offset, len(data))
        self.image[addr : addr + len(data)] = data

    # -- word conveniences (tests, PLC programs of the demo) ------------------------------------
    def read_db_words(
        self, number: int, dw: int, count: int, type: BlockType = BlockType.DB
    ) -> list[int]:
        raw = self.read_block(type, number, 2 * dw, 2 * count)
        return list(struct.unpack(f">{count}H", raw))

    def write_db_words(
        self, number: int, dw: int, values: list[int], type: BlockType = BlockType.DB
    ) -> None:
        self.write_block(type, number, 2 * dw, struct.pack(f">{len(values)}H", *values))

    # -- absolute access (AS511) ------------------------------------------------------------
    def read_absolute(self, address: int, length: int) -> bytes:
        """Bytes ``address .. address+length-1`` of the 64 KiB space (the AS511 view)."""
        if address < 0 or length < 0 or address + length > 0x10000:
            raise S5AccessError(3, f"absolute range {address:#06x}+{length} beyond 64 KiB")
        return bytes(self.image[address : address + length])

    def write_absolute(self, address: int, data: bytes) -> None:
        if address < 0 or address + len(data) > 0x10000:
            raise S5AccessError(3, f"absolute range {address:#06x}+{len(data)} beyond 64 KiB")
        self.image[address : address + len(data)] = data
