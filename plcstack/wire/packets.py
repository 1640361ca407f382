"""The packets a capture holds: IPv4/IPv6 with TCP or UDP, and Wireshark's "exported PDU".

Sans-IO: bytes in, bytes out, no clock, no socket. The capture writer builds every packet here;
the replay reads them back with :func:`parse_ip`. Checksums are real (RFC 1071 over the RFC 793
/ RFC 768 / RFC 8200 pseudo headers), so a Wireshark with checksum validation switched on finds
nothing wrong with our packets.
"""

from __future__ import annotations

import ipaddress
import struct
import sys
from array import array
from dataclasses import dataclass
from typing import Final

__all__ = [
    "ACK",
    "FIN",
    "IPPROTO_TCP",
    "IPPROTO_UDP",
    "MAX_SEGMENT",
    "PSH",
    "RST",
    "SYN",
    "IpAddress",
    "IpPacket",
    "checksum",
    "ip_address",
    "parse_ip",
    "tcp_packet",
    "udp_packet",
    "upper_pdu",
]

IpAddress = ipaddress.IPv4Address | ipaddress.IPv6Address

IPPROTO_TCP: Final = 6
IPPROTO_UDP: Final = 17

# TCP flags (RFC 793)
FIN: Final = 0x01
SYN: Final = 0x02
RST: Final = 0x04
PSH: Final = 0x08
ACK: Final = 0x10

#: most payload bytes one synthesised TCP segment carries: an IPv4 packet's total length is a
#: 16-bit field, and 65535 - 20 (IP) - 20 (TCP) leaves this much; longer writes are split
MAX_SEGMENT: Final = 65495

_IPV4: Final = struct.Struct("!BBHHHBBH4s4s")
_IPV6: Final = struct.Struct("!IHBB16s16s")
_TCP: Final = struct.Struct("!HHIIBBHHH")
_UDP: Final = struct.Struct("!HHHH")
_TLV: Final = struct.Struct("!HH")
_PSEUDO4: Final = struct.Struct("!BBH")
_PSEUDO6: Final = struct.Struct("!I3xB")

#: exported-PDU tags (Wireshark's ``exported_pdu_tlvs.h``): the dissector to call by name,
#: the direction (P2P_DIR_SENT 0 / P2P_DIR_RECV 1), the end of the tag list
_TAG_DISSECTOR_NAME: Final = 12
_TAG_P2P_DIRECTION: Final = 35
_TAG_END: Final = 0


def ip_address(host: str) -> IpAddress:
    """``host`` (an IPv4 or IPv6 literal, an IPv6 one possibly with a zone) as an address."""
    return ipaddress.ip_address(host.split("%", 1)[0])


def checksum(data: bytes | bytearray | memoryview) -> int:
    """The Internet checksum of RFC 1071: one's complement of the one's complement sum of the
    16-bit words (an odd byte padded with zero).

    The words are summed in the machine's own order (``array("H")``, in C) and the folded sum
    swapped back: RFC 1071 section 2 (B) shows the sum is independent of byte order that way.
    """
    if len(data) % 2:
        data = bytes(data) + b"\x00"
    words = array("H")
    words.frombytes(bytes(data))
    total = sum(words)
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    if sys.byteorder == "little":
        total = ((total & 0xFF) << 8) | (total >> 8)
    return ~total & 0xFFFF


def _packed(address: IpAddress | bytes) -> bytes:
    return address if isinstance(address, bytes) else address.packed


def _ip(src: bytes, dst: bytes, proto: int, payload: bytes, ident: int) -> bytes:
    if len(src) != len(dst):
        raise ValueError("source and destination are not of one IP version")
    if len(src) == 4:
        header = _IPV4.pack(
            0x45, 0, 20 + len(payload), ident & 0xFFFF, 0x4000, 64, proto, 0, src, dst
        )
        sum_ = checksum(header)
        return header[:10] + sum_.to_bytes(2, "big") + header[12:] + payload
    return _IPV6.pack(6 << 28, len(payload), proto, 64, src, dst) + payload


def _pseudo_header(src: bytes, dst: bytes, proto: int, length: int) -> bytes:
    if len(src) == 4:
        return src + dst + _PSEUDO4.pack(0, proto, length)
    return src + dst + _PSEUDO6.pack(length, proto)


def tcp_packet(
    src: IpAddress | bytes,
    dst: IpAddress | bytes,
    sport: int,
    dport: int,
    seq: int,
    ack: int,
    flags: int,
    payload: bytes = b"",
    *,
    ident: int = 0,
    window: int = 65535,
) -> bytes:
    """One IP packet carrying one TCP segment (no options), checksums filled in. Addresses
    as objects or packed (4 bytes IPv4, 16 IPv6: what a recorder keeps per connection)."""
    s, d = _packed(src), _packed(dst)
    header = _TCP.pack(
        sport, dport, seq & 0xFFFFFFFF, ack & 0xFFFFFFFF, 5 << 4, flags, window, 0, 0
    )
    segment = header + payload
    sum_ = checksum(_pseudo_header(s, d, IPPROTO_TCP, len(segment)) + segment)
    segment = header[:16] + sum_.to_bytes(2, "big") + header[18:] + payload
    return _ip(s, d, IPPROTO_TCP, segment, ident)


def udp_packet(
    src: IpAddress | bytes,
    dst: IpAddress | bytes,
    sport: int,
    dport: int,
    payload: bytes,
    *,
    ident: int = 0,
) -> bytes:
    """One IP packet carrying one UDP datagram, checksums filled in (0 is sent as FFFFH)."""
    s, d = _packed(src), _packed(dst)
    length = 8 + len(payload)
    header = _UDP.pack(sport, dport, length, 0)
    sum_ = checksum(_pseudo_header(s, d, IPPROTO_UDP, length) + header + payload) or 0xFFFF
    return _ip(s, d, IPPROTO_UDP, header[:6] + sum_.to_bytes(2, "big") + payload, ident)


def _tlv(tag: int, value: bytes) -> bytes:
    padded = value + b"\x00" * (-len(value) % 4)
    return _TLV.pack(tag, len(padded)) + padded


def upper_pdu(dissector: str, sent: bool, payload: bytes) -> bytes:
    """A packet of link type ``WIRESHARK_UPPER_PDU``: ``payload`` handed to the dissector
    registered as ``dissector``, with its direction (``sent``: P2P_DIR_SENT, else RECV).

    A dissector name is a string tag, padded with NULs to a multiple of four: the format says
    a reader must accept trailing NULs in a string tag's length."""
    return (
        _tlv(_TAG_DISSECTOR_NAME, dissector.encode("ascii"))
        + _tlv(_TAG_P2P_DIRECTION, (0 if sent else 1).to_bytes(4, "big"))
        + _TLV.pack(_TAG_END, 0)
        + payload
    )


@dataclass(frozen=True, slots=True)
class IpPacket:
    """What the replay needs of one IP packet: addresses, ports, TCP state, payload."""

    src: IpAddress
    dst: IpAddress
    proto: int
    sport: int
    dport: int
    payload: bytes
    #: TCP only (0 for UDP)
    seq: int = 0
    ack: int = 0
    flags: int = 0


def parse_ip(packet: bytes) -> IpPacket | None:
    """The TCP or UDP content of an IP packet; None for anything else (another protocol, a
    fragment, a truncated or damaged header): the replay skips what it cannot use."""
    if not packet:
        return None
    version = packet[0] >> 4
    if version == 4:
        if len(packet) < 20:
            return None
        ihl = (packet[0] & 0x0F) * 4
        total = int.from_bytes(packet[2:4], "big")
        frag = int.from_bytes(packet[6:8], "big")
        if ihl < 20 or total < ihl or len(packet) < total or frag & 0x3FFF:
            return None
        proto = packet[9]
        src: IpAddress = ipaddress.IPv4Address(packet[12:16])
        dst: IpAddress = ipaddress.IPv4Address(packet[16:20])
        body = packet[ihl:total]
    elif version == 6:
        if len(packet) < 40:
            return None
        length = int.from_bytes(packet[4:6], "big")
        proto = packet[6]
        if len(packet) < 40 + length:
            return None
        src = ipaddress.IPv6Address(packet[8:24])
        dst = ipaddress.IPv6Address(packet[24:40])
        body = packet[40 : 40 + length]
    else:
        return None
    if proto == IPPROTO_TCP and len(body) >= 20:
        sport, dport, seq, ack, offset, flags, _, _, _ = _TCP.unpack_from(body)
        start = (offset >> 4) * 4
        if start < 20 or start > len(body):
            return None
        return IpPacket(src, dst, proto, sport, dport, bytes(body[start:]), seq, ack, flags)
    if proto == IPPROTO_UDP and len(body) >= 8:
        sport, dport, length, _ = _UDP.unpack_from(body)
        if length < 8 or length > len(body):
            return None
        return IpPacket(src, dst, proto, sport, dport, bytes(body[8:length]))
    return None
