"""What a tap sees, as pcapng blocks: the Sans-IO core of the capture file and the flight
recorder (events and times in, bytes out; no file, no clock).

How each kind of connection is written:

* **TCP**: real addresses and ports, one IPv4/IPv6 packet (link type RAW) per chunk sent or
  received, with sequence and acknowledgement numbers that run on consistently, so Wireshark
  follows the stream and reassembles what a PDU spans. The handshake (SYN, SYN-ACK, ACK) at the
  start and the FIN exchange at the end are synthesised, from the end that opened or closed:
  the kernel does them, we see only their outcome. Synthesised packets carry a comment.
* **UDP**: one packet per datagram, as it was.
* **Serial** (AS511 on a PG port): link type ``WIRESHARK_UPPER_PDU`` (252), one interface per
  line named for its device. Why that one: a serial line has no addresses, and the registry's
  byte-stream types either carry no direction (``USER0``..``USER15`` need a user table in each
  Wireshark to mean anything) or a link protocol of their own (PPP, LAPB, SLIP). An exported
  PDU names the dissector to call (``as511``) and the direction (P2P sent = programming device
  to PLC, whichever end recorded it), which is exactly what a line's bytes need. The
  ``epb_flags`` of every packet say inbound or outbound as seen by the recording end.
"""

from __future__ import annotations

import itertools
import zlib
from dataclasses import dataclass, field
from ipaddress import IPv6Address
from typing import Final

from plcstack.transports.tap import Endpoints
from plcstack.wire.packets import (
    ACK,
    FIN,
    MAX_SEGMENT,
    PSH,
    SYN,
    IpAddress,
    ip_address,
    tcp_packet,
    udp_packet,
    upper_pdu,
)
from plcstack.wire.pcapng import (
    DIRECTION_INBOUND,
    DIRECTION_OUTBOUND,
    LINKTYPE_RAW,
    LINKTYPE_WIRESHARK_UPPER_PDU,
    enhanced_packet,
    interface_description,
    section_header,
)

__all__ = ["IP_INTERFACE", "SERIAL_DISSECTOR", "Recording", "Stream"]

#: the interface of every TCP and UDP packet (the first of each file)
IP_INTERFACE: Final = 0
#: the dissector a serial line's bytes are handed to (the Lua dissector of that name)
SERIAL_DISSECTOR: Final = "as511"

_IP_NAME: Final = "plcstack"
_IP_DESCRIPTION: Final = (
    "TCP and UDP as plcstack sent and received them; TCP handshakes and closes synthesised"
)


@dataclass(slots=True, eq=False)
class Stream:
    """One recorded connection: its endpoints and where its TCP sequence numbers stand."""

    endpoints: Endpoints
    interface: int
    local_ip: IpAddress | None = None
    remote_ip: IpAddress | None = None
    #: the addresses packed (4 or 16 bytes), as every packet needs them
    local_packed: bytes = b""
    remote_packed: bytes = b""
    #: next sequence number of the local and of the remote end (TCP)
    local_seq: int = 0
    remote_seq: int = 0
    ended: bool = False
    _ident: itertools.count[int] = field(default_factory=lambda: itertools.count(1))


def _isn(endpoints: Endpoints, salt: int) -> int:
    """A stable initial sequence number per connection (captures of one run compare equal)."""
    return zlib.crc32(f"{endpoints}{salt}".encode()) & 0x7FFFFFFF


class Recording:
    """Turns connection events into pcapng blocks; one per file (or per rendered ring).

    ``header()`` is the start of a file: the section header and every interface known. The
    other methods return the blocks to append for one event (b"" when there are none).
    """

    def __init__(self, application: str = "plcstack") -> None:
        self.application = application
        #: (link type, name, description) of each interface, in id order
        self._interfaces: list[tuple[int, str, str]] = [(LINKTYPE_RAW, _IP_NAME, _IP_DESCRIPTION)]
        self._serial: dict[str, int] = {}
        self._streams: list[Stream] = []
        self._salt = itertools.count()

    def header(self) -> bytes:
        """Section header and interface descriptions: what a new file starts with."""
        return section_header(self.application) + b"".join(
            interface_description(*interface) for interface in self._interfaces
        )

    @property
    def open_streams(self) -> list[Stream]:
        return [stream for stream in self._streams if not stream.ended]

    # -- events ------------------------------------------------------------------------------
    def open(
        self, endpoints: Endpoints, micros: int, *, resumed: bool = False
    ) -> tuple[Stream, bytes]:
        """A connection opened at ``micros``: its stream, and the blocks that say so (a new
        serial line's interface; a TCP handshake). ``resumed``: it opened before what is
        recorded here began (a flight recorder's ring), the handshake says so."""
        blocks = b""
        if endpoints.kind == "serial":
            interface = self._serial.get(endpoints.device)
            if interface is None:
                interface = self._serial[endpoints.device] = len(self._interfaces)
                described = (
                    LINKTYPE_WIRESHARK_UPPER_PDU,
                    endpoints.device or "serial",
                    f"AS511 on {endpoints.device}; direction: sent = programming device to PLC",
                )
                self._interfaces.append(described)
                blocks = interface_description(*described)
            stream = Stream(endpoints, interface)
        else:
            local, remote = _one_version(
                ip_address(endpoints.local[0] or "0.0.0.0"),
                ip_address(endpoints.remote[0] or "0.0.0.0"),
            )
            stream = Stream(endpoints, IP_INTERFACE, local, remote, local.packed, remote.packed)
        salt = next(self._salt)
        stream.local_seq = _isn(endpoints, salt)
        stream.remote_seq = _isn(endpoints, salt + 1_000_003)
        self._streams.append(stream)
        if endpoints.kind == "tcp":
            blocks += self.handshake(stream, micros, resumed=resumed)
        self._forget_ended()
        return stream, blocks

    def handshake(self, stream: Stream, micros: int, resumed: bool) -> bytes:
        """SYN, SYN-ACK, ACK from the opening end, leading to where the stream's sequence
        numbers stand (``resumed``: the connection was open before this file or window)."""
        comment = (
            "handshake synthesised: the connection was open before this capture began"
            if resumed
            else "handshake synthesised by plcstack (made by the kernel)"
        )
        local_first = stream.endpoints.initiator == "local"
        a_seq, b_seq = (
            (stream.local_seq, stream.remote_seq)
            if local_first
            else (stream.remote_seq, stream.local_seq)
        )
        return (
            self._tcp(stream, local_first, micros, a_seq - 1, 0, SYN, b"", comment)
            + self._tcp(stream, not local_first, micros, b_seq - 1, a_seq, SYN | ACK, b"", "")
            + self._tcp(stream, local_first, micros, a_seq, b_seq, ACK, b"", "")
        )

    def data(self, stream: Stream, outbound: bool, data: bytes, micros: int) -> bytes:
        """``data`` sent (``outbound``) or received on ``stream`` at ``micros``."""
        if stream.ended or not data:
            return b""
        kind = stream.endpoints.kind
        if kind == "serial":
            from_pg = outbound == (stream.endpoints.initiator == "local")
            return enhanced_packet(
                stream.interface,
                micros,
                upper_pdu(SERIAL_DISSECTOR, from_pg, data),
                DIRECTION_OUTBOUND if outbound else DIRECTION_INBOUND,
            )
        if kind == "udp":
            src, dst, sport, dport = self._ends(stream, outbound)
            return enhanced_packet(
                IP_INTERFACE,
                micros,
                udp_packet(src, dst, sport, dport, data, ident=next(stream._ident)),
                DIRECTION_OUTBOUND if outbound else DIRECTION_INBOUND,
            )
        if len(data) <= MAX_SEGMENT:  # every PDU of our protocols: one segment
            return self._segment(stream, outbound, micros, data)
        return b"".join(
            self._segment(stream, outbound, micros, data[start : start + MAX_SEGMENT])
            for start in range(0, len(data), MAX_SEGMENT)
        )

    def _segment(self, stream: Stream, outbound: bool, micros: int, part: bytes) -> bytes:
        """One data segment from its end, the sequence numbers moved on past it."""
        if outbound:
            seq, ack = stream.local_seq, stream.remote_seq
            stream.local_seq += len(part)
        else:
            seq, ack = stream.remote_seq, stream.local_seq
            stream.remote_seq += len(part)
        return self._tcp(stream, outbound, micros, seq, ack, PSH | ACK, part, "")

    def end(self, stream: Stream, by_peer: bool, micros: int) -> bytes:
        """The connection ended: for TCP, FIN from the end that closed, FIN back, ACK."""
        if stream.ended:
            return b""
        stream.ended = True
        if stream.endpoints.kind != "tcp":
            return b""
        closer_local = not by_peer
        first_seq, first_ack = (
            (stream.local_seq, stream.remote_seq)
            if closer_local
            else (stream.remote_seq, stream.local_seq)
        )
        blocks = self._tcp(stream, closer_local, micros, first_seq, first_ack, FIN | ACK, b"", "")
        blocks += self._tcp(
            stream, not closer_local, micros, first_ack, first_seq + 1, FIN | ACK, b"", ""
        )
        blocks += self._tcp(
            stream, closer_local, micros, first_seq + 1, first_ack + 1, ACK, b"", ""
        )
        if closer_local:
            stream.local_seq += 1
            stream.remote_seq += 1
        else:
            stream.remote_seq += 1
            stream.local_seq += 1
        return blocks

    def resume(self, micros: int) -> bytes:
        """A new file continues the recording: its header, then a handshake for every TCP
        connection still open, so each file can be read on its own."""
        return self.header() + b"".join(
            self.handshake(stream, micros, resumed=True)
            for stream in self.open_streams
            if stream.endpoints.kind == "tcp"
        )

    # -- helpers -----------------------------------------------------------------------------
    def _ends(self, stream: Stream, outbound: bool) -> tuple[bytes, bytes, int, int]:
        local, remote = stream.local_packed, stream.remote_packed
        lport, rport = stream.endpoints.local[1], stream.endpoints.remote[1]
        return (local, remote, lport, rport) if outbound else (remote, local, rport, lport)

    def _tcp(
        self,
        stream: Stream,
        outbound: bool,
        micros: int,
        seq: int,
        ack: int,
        flags: int,
        payload: bytes,
        comment: str,
    ) -> bytes:
        src, dst, sport, dport = self._ends(stream, outbound)
        packet = tcp_packet(
            src, dst, sport, dport, seq, ack, flags, payload, ident=next(stream._ident)
        )
        direction = DIRECTION_OUTBOUND if outbound else DIRECTION_INBOUND
        return enhanced_packet(IP_INTERFACE, micros, packet, direction, comment)

    def _forget_ended(self) -> None:
        # ended streams are not resumed; keep the list as long as the open connections
        if len(self._streams) > 64 and len(self._streams) > 2 * len(self.open_streams):
            self._streams = self.open_streams


def _plain(address: IpAddress) -> IpAddress:
    if isinstance(address, IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped
    return address


def _one_version(local: IpAddress, remote: IpAddress) -> tuple[IpAddress, IpAddress]:
    """Both ends in one IP version: a dual-stack socket names an IPv4 peer ``::ffff:a.b.c.d``."""
    local, remote = _plain(local), _plain(remote)
    if local.version == remote.version:
        return local, remote
    if local.version == 4:
        return ip_address(f"::ffff:{local}"), remote
    return local, ip_address(f"::ffff:{remote}")
