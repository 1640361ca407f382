"""A capture read back as conversations: who was the client, who the server, and the bytes
each sent, in order (Sans-IO: bytes of a file in, objects out).

TCP is reassembled per direction by sequence number: segments seen twice (retransmissions)
are taken once, segments that arrive early wait for the gap to fill, a gap never filled ends
what can be read of that direction (said in :attr:`Conversation.gaps`). The client is the end
that sent the SYN; without a handshake in the capture, the end that sent first. UDP datagrams
stay datagrams. AS511 lines (our exported PDUs) give the programming device as the client.
Exchanges are what the replay serves: the client's bytes up to the server's next bytes, and
those bytes up to the client's next ones.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Literal

from plcstack.wire.packets import ACK, FIN, IPPROTO_TCP, RST, SYN, IpPacket, parse_ip
from plcstack.wire.pcapng import (
    LINKTYPE_ETHERNET,
    LINKTYPE_IPV4,
    LINKTYPE_IPV6,
    LINKTYPE_LINUX_SLL,
    LINKTYPE_LINUX_SLL2,
    LINKTYPE_LOOP,
    LINKTYPE_NULL,
    LINKTYPE_RAW,
    LINKTYPE_WIRESHARK_UPPER_PDU,
    Packet,
    read_capture,
)

__all__ = ["Chunk", "Conversation", "Exchange", "conversations", "exchanges"]

Kind = Literal["tcp", "udp", "serial"]


@dataclass(frozen=True, slots=True)
class Chunk:
    """Bytes one end sent (one datagram for UDP), at ``nanos``."""

    from_client: bool
    data: bytes
    nanos: int


@dataclass(slots=True)
class Conversation:
    """One connection (TCP), one pair of ends (UDP), or one serial line."""

    kind: Kind
    #: ``host:port`` (``[v6]:port``), or the serial device for the server of a line
    client: str
    server: str
    chunks: list[Chunk] = field(default_factory=list)
    #: where bytes of a TCP direction were never captured (replay stops using it there)
    gaps: int = 0


@dataclass(frozen=True, slots=True)
class Exchange:
    """What the client sent and what the server answered (one datagram each for UDP), with
    the time the answer took."""

    request: bytes
    answers: tuple[bytes, ...]
    delay: float
    nanos: int


def _endpoint(host: object, port: int) -> str:
    text = str(host)
    return f"[{text}]:{port}" if ":" in text else f"{text}:{port}"


def _ip_of(packet: Packet) -> IpPacket | None:
    """The IP packet inside a link-layer frame of the types captures commonly have."""
    data, linktype = packet.data, packet.linktype
    if linktype in (LINKTYPE_RAW, LINKTYPE_IPV4, LINKTYPE_IPV6):
        return parse_ip(data)
    if linktype == LINKTYPE_ETHERNET:
        offset = 12
        ethertype = int.from_bytes(data[offset : offset + 2], "big")
        while ethertype in (0x8100, 0x88A8) and len(data) >= offset + 6:  # VLAN tags
            offset += 4
            ethertype = int.from_bytes(data[offset : offset + 2], "big")
        return parse_ip(data[offset + 2 :]) if ethertype in (0x0800, 0x86DD) else None
    if linktype in (LINKTYPE_NULL, LINKTYPE_LOOP):
        return parse_ip(data[4:])
    if linktype == LINKTYPE_LINUX_SLL:
        return parse_ip(data[16:])
    if linktype == LINKTYPE_LINUX_SLL2:
        return parse_ip(data[20:])
    return None


def _upper_pdu(data: bytes) -> tuple[str, int | None, bytes] | None:
    """(dissector name, P2P direction, payload) of an exported PDU; None when damaged."""
    offset = 0
    name = ""
    direction: int | None = None
    while offset + 4 <= len(data):
        tag, length = struct.unpack_from("!HH", data, offset)
        offset += 4
        if tag == 0:
            return name, direction, data[offset:]
        value = data[offset : offset + length]
        if tag == 12:
            name = value.rstrip(b"\x00").decode("ascii", "replace")
        elif tag == 35 and len(value) == 4:
            direction = int.from_bytes(value, "big", signed=True)
        offset += length
    return None


@dataclass(slots=True)
class _Direction:
    next_seq: int | None = None
    early: dict[int, bytes] = field(default_factory=dict)
    #: the acknowledgement number this direction last carried: where the other one stands
    acked: int | None = None


@dataclass(slots=True)
class _Tcp:
    conversation: Conversation
    client_key: tuple[str, str]
    directions: dict[bool, _Direction] = field(
        default_factory=lambda: {True: _Direction(), False: _Direction()}
    )
    closed: bool = False


def _tcp_data(state: _Tcp, ip: IpPacket, from_client: bool, nanos: int) -> None:
    direction = state.directions[from_client]
    seq, payload = ip.seq, ip.payload
    if ip.flags & ACK:
        direction.acked = ip.ack
    if ip.flags & SYN:
        direction.next_seq = (seq + 1) & 0xFFFFFFFF
        return
    if not payload:
        return
    if direction.next_seq is None:
        # no handshake captured: start where the other end's acknowledgement says this
        # direction stands (a segment that came early then waits), else at this segment
        other = state.directions[not from_client].acked
        direction.next_seq = seq if other is None else other
    gap = (seq - direction.next_seq) & 0xFFFFFFFF
    if gap == 0 or gap >= 0x80000000:  # in order, or (partly) seen before
        skip = 0 if gap == 0 else (0x100000000 - gap)
        if skip >= len(payload):
            return  # a retransmission of bytes already taken
        fresh = payload[skip:]
        state.conversation.chunks.append(Chunk(from_client, fresh, nanos))
        direction.next_seq = (direction.next_seq + len(fresh)) & 0xFFFFFFFF
        while direction.next_seq in direction.early:
            waiting = direction.early.pop(direction.next_seq)
            state.conversation.chunks.append(Chunk(from_client, waiting, nanos))
            direction.next_seq = (direction.next_seq + len(waiting)) & 0xFFFFFFFF
    else:
        direction.early[seq] = payload  # before a gap: waits until the gap is filled


def conversations(capture: bytes) -> list[Conversation]:
    """Every conversation of a pcap or pcapng file, in the order they began.

    Raises :class:`~plcstack.wire.pcapng.CaptureError` for a file that is not a capture."""
    result: list[Conversation] = []
    tcp: dict[tuple[str, str], _Tcp] = {}
    udp: dict[tuple[str, str], tuple[Conversation, str]] = {}
    serial: dict[int, Conversation] = {}
    for packet in read_capture(capture):
        if packet.linktype == LINKTYPE_WIRESHARK_UPPER_PDU:
            pdu = _upper_pdu(packet.data)
            if pdu is None or pdu[1] not in (0, 1) or not pdu[2]:
                continue
            line = serial.get(packet.interface_id)
            if line is None:
                device = packet.interface or f"serial line {packet.interface_id}"
                line = serial[packet.interface_id] = Conversation("serial", "PG", device)
                result.append(line)
            line.chunks.append(Chunk(pdu[1] == 0, pdu[2], packet.nanos))
            continue
        ip = _ip_of(packet)
        if ip is None:
            continue
        src, dst = _endpoint(ip.src, ip.sport), _endpoint(ip.dst, ip.dport)
        key = (src, dst) if src < dst else (dst, src)
        if ip.proto == IPPROTO_TCP:
            state = tcp.get(key)
            starts = ip.flags & SYN and not ip.flags & 0x10  # a SYN without ACK: a new connection
            if state is None or (starts and state.closed):
                if not starts and not ip.payload:
                    continue  # the end of a connection that began before the capture
                client, server = (src, dst)
                state = tcp[key] = _Tcp(Conversation("tcp", client, server), (src, dst))
                result.append(state.conversation)
            from_client = (src, dst) == state.client_key
            _tcp_data(state, ip, from_client, packet.nanos)
            if ip.flags & (FIN | RST):
                state.closed = True
        else:
            known = udp.get(key)
            if known is None:
                known = udp[key] = (Conversation("udp", src, dst), src)
                result.append(known[0])
            conversation, client = known
            if ip.payload:
                conversation.chunks.append(Chunk(src == client, ip.payload, packet.nanos))
    for state in tcp.values():
        state.conversation.gaps = sum(1 for d in state.directions.values() if d.early)
    return result


def exchanges(conversation: Conversation) -> list[Exchange]:
    """The conversation as requests and their answers. Bytes the server sent before the
    client's first request are dropped (a greeting our protocols do not have)."""
    result: list[Exchange] = []
    request = bytearray()
    answers: list[bytes] = []
    asked_at = answered_at = 0
    datagrams = conversation.kind == "udp"

    def flush() -> None:
        if request:
            delay = max(0, answered_at - asked_at) / 1e9 if answers else 0.0
            result.append(Exchange(bytes(request), tuple(answers), delay, asked_at))

    for chunk in conversation.chunks:
        if chunk.from_client:
            if answers or (datagrams and request):
                flush()
                request = bytearray()
                answers = []
            if not request:
                asked_at = chunk.nanos
            request += chunk.data
        elif request:
            if not answers:
                answered_at = chunk.nanos
            if datagrams or not answers:
                answers.append(chunk.data)
            else:
                answers[-1] += chunk.data
    flush()
    return result
