"""pcapng blocks written and read, and classic pcap files read (Sans-IO: bytes only).

Written as the IETF draft "PCAP Next Generation (pcapng) Capture File Format"
(draft-ietf-opsawg-pcapng) lays the blocks out: a Section Header Block (type 0A0D0D0AH, the
byte-order magic 1A2B3C4DH, version 1.0, section length -1 = unknown), Interface Description
Blocks (type 1: link type, snap length, options), Enhanced Packet Blocks (type 6: interface,
a 64-bit timestamp in the interface's resolution, captured and original length, the data padded
to 32 bits, options). Every block ends with its total length again; options are code, length,
value padded to 32 bits, and a list ends with ``opt_endofopt``. We write our own byte order
(little-endian) and microsecond timestamps (no ``if_tsresol``: 10^-6 is the default).

The reader takes what Wireshark, tcpdump and dumpcap write: pcapng of either byte order with
any ``if_tsresol``, several sections, and the classic libpcap format (micro- or nanosecond
magic). A damaged file is a :class:`CaptureError` naming the offset, never a crash.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Final

__all__ = [
    "DIRECTION_INBOUND",
    "DIRECTION_OUTBOUND",
    "LINKTYPE_ETHERNET",
    "LINKTYPE_IPV4",
    "LINKTYPE_IPV6",
    "LINKTYPE_LINUX_SLL",
    "LINKTYPE_LINUX_SLL2",
    "LINKTYPE_LOOP",
    "LINKTYPE_NULL",
    "LINKTYPE_RAW",
    "LINKTYPE_WIRESHARK_UPPER_PDU",
    "CaptureError",
    "Packet",
    "enhanced_packet",
    "interface_description",
    "read_capture",
    "section_header",
]

# link types of the tcpdump.org registry that we write or read
LINKTYPE_NULL: Final = 0
LINKTYPE_ETHERNET: Final = 1
LINKTYPE_RAW: Final = 101  # an IPv4 or IPv6 packet, told apart by its version nibble
LINKTYPE_LOOP: Final = 108
LINKTYPE_LINUX_SLL: Final = 113
LINKTYPE_IPV4: Final = 228
LINKTYPE_IPV6: Final = 229
LINKTYPE_WIRESHARK_UPPER_PDU: Final = 252
LINKTYPE_LINUX_SLL2: Final = 276

#: ``epb_flags`` bits 0-1 (the draft's flags word): 01 = inbound, 10 = outbound
DIRECTION_INBOUND: Final = 1
DIRECTION_OUTBOUND: Final = 2

_SHB: Final = 0x0A0D0D0A
_IDB: Final = 0x00000001
_SPB: Final = 0x00000003
_EPB: Final = 0x00000006
_BYTE_ORDER_MAGIC: Final = 0x1A2B3C4D

_OPT_END: Final = 0
_OPT_COMMENT: Final = 1
_SHB_USERAPPL: Final = 4
_IF_NAME: Final = 2
_IF_DESCRIPTION: Final = 3
_IF_TSRESOL: Final = 9
_EPB_FLAGS: Final = 2

_EPB_HEAD: Final = struct.Struct("<IIIIIII")
_PADDING: Final = (b"", b"\x00", b"\x00\x00", b"\x00\x00\x00")


def _option(code: int, value: bytes) -> bytes:
    return struct.pack("<HH", code, len(value)) + value + b"\x00" * (-len(value) % 4)


def _options(items: list[tuple[int, bytes]]) -> bytes:
    if not items:
        return b""
    return b"".join(_option(code, value) for code, value in items) + _option(_OPT_END, b"")


#: the options of a packet block without a comment: its direction flags (none when unknown)
_DIRECTION_OPTIONS: Final = {
    direction: _options([(_EPB_FLAGS, struct.pack("<I", direction))]) if direction else b""
    for direction in (0, DIRECTION_INBOUND, DIRECTION_OUTBOUND, 3)
}


def _block(block_type: int, body: bytes) -> bytes:
    total = 12 + len(body)
    return struct.pack("<II", block_type, total) + body + struct.pack("<I", total)


def section_header(application: str) -> bytes:
    """The Section Header Block that starts a file; ``shb_userappl`` names the writer."""
    body = struct.pack("<IHHq", _BYTE_ORDER_MAGIC, 1, 0, -1) + _options(
        [(_SHB_USERAPPL, application.encode())]
    )
    return _block(_SHB, body)


def interface_description(linktype: int, name: str, description: str = "") -> bytes:
    """An Interface Description Block: link type, no snap length limit (0), its name."""
    options = [(_IF_NAME, name.encode())]
    if description:
        options.append((_IF_DESCRIPTION, description.encode()))
    return _block(_IDB, struct.pack("<HHI", linktype, 0, 0) + _options(options))


def enhanced_packet(
    interface: int, micros: int, data: bytes, direction: int = 0, comment: str = ""
) -> bytes:
    """An Enhanced Packet Block of ``data`` at ``micros`` (microseconds since the epoch), with
    its direction (``DIRECTION_INBOUND``/``OUTBOUND``, 0 = unknown) and an optional comment."""
    if comment:
        options = [(_OPT_COMMENT, comment.encode())]
        if direction:
            options.insert(0, (_EPB_FLAGS, struct.pack("<I", direction)))
        tail = _PADDING[-len(data) % 4] + _options(options)
    else:
        tail = _PADDING[-len(data) % 4] + _DIRECTION_OPTIONS[direction]
    total = 32 + len(data) + len(tail)
    return (
        _EPB_HEAD.pack(
            _EPB, total, interface, micros >> 32, micros & 0xFFFFFFFF, len(data), len(data)
        )
        + data
        + tail
        + struct.pack("<I", total)
    )


# -- reading -----------------------------------------------------------------------------------


class CaptureError(ValueError):
    """The bytes are not a capture file we can read, or are damaged at ``offset``."""


@dataclass(frozen=True, slots=True)
class Packet:
    """One captured packet: its interface's link type and name, the time in nanoseconds since
    the epoch, the data as captured, and the direction bits (0 when the file does not say)."""

    linktype: int
    interface: str
    nanos: int
    data: bytes
    direction: int = 0
    #: which interface of its section (pcapng) it was captured on; 0 for classic pcap
    interface_id: int = 0


_PCAP_MAGICS: Final = {
    b"\xd4\xc3\xb2\xa1": ("<", 1000),
    b"\xa1\xb2\xc3\xd4": (">", 1000),
    b"\x4d\x3c\xb2\xa1": ("<", 1),
    b"\xa1\xb2\x3c\x4d": (">", 1),
}


def read_capture(data: bytes) -> Iterator[Packet]:
    """Every packet of a pcapng or classic pcap file, in file order."""
    if data[:4] in _PCAP_MAGICS:
        yield from _read_pcap(data)
    elif data[:4] == struct.pack("<I", _SHB):
        yield from _read_pcapng(data)
    else:
        raise CaptureError("not a pcap or pcapng file (unknown magic number)")


def _read_pcap(data: bytes) -> Iterator[Packet]:
    order, scale = _PCAP_MAGICS[data[:4]]
    if len(data) < 24:
        raise CaptureError("pcap file header truncated")
    linktype = struct.unpack_from(order + "I", data, 20)[0] & 0x0FFFFFFF
    record = struct.Struct(order + "IIII")
    offset = 24
    while offset < len(data):
        if offset + 16 > len(data):
            raise CaptureError(f"packet record header truncated at offset {offset}")
        seconds, fraction, captured, _ = record.unpack_from(data, offset)
        offset += 16
        if offset + captured > len(data):
            raise CaptureError(f"packet data truncated at offset {offset}")
        nanos = seconds * 1_000_000_000 + fraction * scale
        yield Packet(linktype, "", nanos, data[offset : offset + captured])
        offset += captured


@dataclass(slots=True)
class _Interface:
    linktype: int
    name: str
    #: nanoseconds per timestamp unit, as a fraction (numerator, denominator)
    unit: tuple[int, int]


def _tsresol(value: int) -> tuple[int, int]:
    exponent = value & 0x7F
    base = 2 if value & 0x80 else 10
    return (1_000_000_000, base**exponent)


def _parse_options(data: bytes, order: str) -> Iterator[tuple[int, bytes]]:
    offset = 0
    head = struct.Struct(order + "HH")
    while offset + 4 <= len(data):
        code, length = head.unpack_from(data, offset)
        offset += 4
        if code == _OPT_END:
            return
        yield code, data[offset : offset + length]
        offset += length + (-length % 4)


def _read_pcapng(data: bytes) -> Iterator[Packet]:
    offset = 0
    order = "<"
    interfaces: list[_Interface] = []
    while offset < len(data):
        if offset + 12 > len(data):
            raise CaptureError(f"block header truncated at offset {offset}")
        raw_type = data[offset : offset + 4]
        if raw_type == struct.pack("<I", _SHB):
            magic = data[offset + 8 : offset + 12]
            if magic == struct.pack("<I", _BYTE_ORDER_MAGIC):
                order = "<"
            elif magic == struct.pack(">I", _BYTE_ORDER_MAGIC):
                order = ">"
            else:
                raise CaptureError(f"section header without byte-order magic at offset {offset}")
            interfaces = []
        block_type, total = struct.unpack_from(order + "II", data, offset)
        if total < 12 or total % 4 or offset + total > len(data):
            raise CaptureError(f"block of bad length {total} at offset {offset}")
        body = data[offset + 8 : offset + total - 4]
        if block_type == _IDB:
            if len(body) < 8:
                raise CaptureError(f"interface description truncated at offset {offset}")
            linktype = struct.unpack_from(order + "H", body, 0)[0]
            name = ""
            unit = (1000, 1)
            for code, value in _parse_options(body[8:], order):
                if code == _IF_NAME:
                    name = value.rstrip(b"\x00").decode(errors="replace")
                elif code == _IF_TSRESOL and value:
                    unit = _tsresol(value[0])
            interfaces.append(_Interface(linktype, name, unit))
        elif block_type == _EPB:
            if len(body) < 20:
                raise CaptureError(f"packet block truncated at offset {offset}")
            iface, high, low, captured, _ = struct.unpack_from(order + "IIIII", body, 0)
            if iface >= len(interfaces) or 20 + captured > len(body):
                raise CaptureError(f"packet block with a bad interface or length at {offset}")
            interface = interfaces[iface]
            direction = 0
            rest = body[20 + captured + (-captured % 4) :]
            for code, value in _parse_options(rest, order):
                if code == _EPB_FLAGS and len(value) >= 4:
                    direction = struct.unpack_from(order + "I", value)[0] & 3
            numerator, denominator = interface.unit
            nanos = ((high << 32) | low) * numerator // denominator
            yield Packet(
                interface.linktype,
                interface.name,
                nanos,
                bytes(body[20 : 20 + captured]),
                direction,
                iface,
            )
        elif block_type == _SPB:
            if not interfaces or len(body) < 4:
                raise CaptureError(f"simple packet block without an interface at {offset}")
            length = struct.unpack_from(order + "I", body, 0)[0]
            yield Packet(interfaces[0].linktype, interfaces[0].name, 0, bytes(body[4 : 4 + length]))
        offset += total
