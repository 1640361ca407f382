"""Plain-words hints for the most common field failure: a wrong setting, not a broken PLC.

Runs on the failure path only. Each client's ``diagnose`` hook (see
:meth:`plcstack.clients.base.Client.diagnose`) hands over how the request failed and every byte
received for it; the functions here return one sentence saying what is probably misconfigured and
which URL option to try, or ``""`` when the bytes support no such statement. A hint never changes
the error type; it is only appended to the message.

Rules: name a setting only when the bytes carry that setting's signature (the MK magic, the
``'S5'`` header, an E71 subheader with an end code, AS511 control characters, a 26-byte S5-LAN
block); when nothing came back, list the likely causes for that protocol and say they are likely,
not certain. Binary versus ASCII E71 is a heuristic (spec melsec-e71 §11.4 allows it for
diagnostics only); the codecs never switch code on their own.
"""

from __future__ import annotations

from typing import Literal

from plcstack.codecs.as511_frames import ACCEPT_FRAME, DLE_ACK, DLE_NAK, TERMINATE_FRAME
from plcstack.codecs.e71_end_codes import END_CODES
from plcstack.codecs.e71_wire import HEX

__all__ = [
    "Failure",
    "as511_hint",
    "e71_hint",
    "fetchwrite_hint",
    "identify",
    "looks_like_e71_ascii",
    "looks_like_e71_binary",
    "s5lan_hint",
]

#: how a request failed: a reply the codec refused, no complete reply before the deadline, or
#: the peer closed the connection
Failure = Literal["malformed", "timeout", "closed"]

#: E71 end codes (melsec-e71 §10): 00H and the documented error codes, from the codec's table
_END_CODES = frozenset(END_CODES)
#: AS511 handshakes an AG sends (siemens-s5 B.2): DLE ACK, DLE NAK, the accept frame
#: SYN DLE ETX and the terminate frame DC2 DLE ETX
_AS511_STARTS = (DLE_ACK, DLE_NAK, ACCEPT_FRAME, TERMINATE_FRAME)
#: at most this many reply bytes are quoted in a hint
_QUOTE = 8


def _hex(data: bytes) -> str:
    more = " …" if len(data) > _QUOTE else ""
    return data[:_QUOTE].hex(" ").upper() + more


def _text(data: bytes) -> str:
    more = "…" if len(data) > _QUOTE else ""
    return '"' + data[:_QUOTE].decode("ascii", "backslashreplace") + more + '"'


def looks_like_e71_binary(reply: bytes) -> bool:
    """A binary 1E answer: subheader with bit 7 set, then a known end code (§4, §13)."""
    return len(reply) >= 2 and reply[0] >= 0x80 and reply[1] in _END_CODES


def looks_like_e71_ascii(reply: bytes) -> bool:
    """An ASCII 1E answer: 4 hex characters, subheader >= 80H, then a known end code (§11.4)."""
    if len(reply) < 4 or not all(b in HEX for b in reply[:4]):
        return False
    return int(reply[:2], 16) >= 0x80 and int(reply[2:4], 16) in _END_CODES


def _looks_like_mk(reply: bytes) -> bool:
    # C.1: 'MK', length, flags (bits 1-15 reserved, byte 5 = 0), sequence number
    return reply[:2] == b"MK" and (len(reply) < 6 or reply[5] == 0)


def _looks_like_s5_header(reply: bytes) -> bool:
    # C.6: 'S5', header length 10h, ID OP code 01h
    return reply[:2] == b"S5" and reply[2:4] in (b"", b"\x10", b"\x10\x01")


def _looks_like_s5lan(reply: bytes) -> bool:
    # A.2: PLCType '5' (35h; 05h see D.A2), Interface 0, PLCNo 0, HdLen 26
    return len(reply) >= 5 and reply[0] in (0x35, 0x05) and reply[1:5] == b"\x00\x00\x00\x1a"


def _looks_like_as511(reply: bytes) -> bool:
    return reply.startswith(_AS511_STARTS)


def identify(reply: bytes) -> str | None:
    """Which of our protocols ``reply`` resembles, as ``"protocol (scheme)"``, else ``None``.

    Checked from the most to the least specific signature, so a few random bytes rarely match.
    """
    if _looks_like_mk(reply):
        return "a Tani module with the MK header (fetchwrite://…?mk=1)"
    if _looks_like_s5_header(reply):
        return "an S5 FETCH/WRITE port (fetchwrite://)"
    if _looks_like_s5lan(reply):
        return "an S5-LAN-LINK module (s5lan://)"
    if _looks_like_as511(reply):
        return "an AS511 programming port, e.g. behind a serial device server (as511+tcp://)"
    if looks_like_e71_ascii(reply):
        return "a MELSEC E71 in ASCII mode (e71+tcp://…?code=ascii)"
    if looks_like_e71_binary(reply):
        return "a MELSEC E71 in binary mode (e71+tcp://)"
    return None


def _other_protocol(reply: bytes, ours: str) -> str:
    """The sentence for a reply in another protocol's format, or ``""``."""
    other = identify(reply)
    if other is None:
        return ""
    return (
        f"the reply ({_hex(reply)}) looks like it comes from {other}, not {ours}; "
        "check the URL scheme and the port"
    )


def e71_hint(failure: Failure, reply: bytes, *, code: str, first: bool) -> str:
    """MELSEC E71 1E frame: binary vs ASCII (DIP SW2), or not an E71 port at all."""
    if reply:
        if code == "binary" and looks_like_e71_ascii(reply):
            return (
                f"the reply looks like an ASCII-coded 1E frame ({_text(reply)}); "
                "is the E71 set to ASCII (DIP SW2 ON)? try ?code=ascii"
            )
        if code == "ascii" and looks_like_e71_binary(reply) and not looks_like_e71_ascii(reply):
            return (
                f"the reply looks like a binary 1E frame ({_hex(reply)}); "
                "is the E71 set to binary (DIP SW2 OFF)? try ?code=binary"
            )
        other = identify(reply)
        if other is not None and not other.startswith("a MELSEC"):
            return _other_protocol(reply, "an E71")
        return ""
    if not first:
        return ""
    if failure == "timeout":
        return (
            "the peer accepted the connection but sent nothing; an E71 answers every 1E-frame "
            "request, even one in the wrong code, so this port is probably not an E71 "
            "MC-protocol port (an S5-LAN or FETCH/WRITE module, for one, waits silently for a "
            "longer request); check the port and that the E71 connection is 'with procedure'"
        )
    if failure == "closed":
        # An E71 answers even a request it cannot parse: on an E71 port, a close without an
        # answer is the module turning away a connection beyond its 8 (melsec-e71 §1.1).
        return (
            "the peer closed the connection right after our first request without answering; "
            "an E71 serves 8 connections at once and turns away any further one, so check "
            "how many other clients (pollers, HMIs, SCADA, engineering software) hold its "
            "connections; an E71 answers even a request it cannot parse, so otherwise this "
            "port is probably not an E71 MC-protocol port (a FETCH/WRITE or Tani MK module "
            "closes on such a request)"
        )
    return ""


def fetchwrite_hint(failure: Failure, reply: bytes, *, mk: bool, first: bool) -> str:
    """S5 FETCH/WRITE: the Tani MK header expected but not sent, or sent but not expected."""
    if reply:
        if not mk and _looks_like_mk(reply):
            return (
                f"the reply starts with the Tani MK header ({_hex(reply)}); "
                "the module expects the MK header: try ?mk=1"
            )
        if mk and _looks_like_s5_header(reply):
            return (
                f"the reply is a plain 'S5' FETCH/WRITE header without the MK header "
                f"({_hex(reply)}); the module does not use the Tani header: try without ?mk=1"
            )
        return _other_protocol(reply, "a FETCH/WRITE port")
    if not first:
        return ""
    if not mk:
        if failure == "closed":
            return (
                "the peer closed the connection right after our first job without answering; "
                "a Tani module with the MK header switched on does this when the header is "
                "missing: try ?mk=1 (else the port is probably not a FETCH/WRITE port)"
            )
        if failure == "timeout":
            return (
                "the peer accepted the connection but sent nothing; likely causes: the port "
                "is not a FETCH/WRITE port (an S5-LAN module, for one, waits for a longer "
                "request), or the module expects the Tani MK header (try ?mk=1)"
            )
        return ""
    if failure == "closed":
        return (
            "the peer closed the connection right after our first job without answering; a "
            "plain FETCH/WRITE CP does this when a job does not start with 'S5' (ours starts "
            "with the MK header): try without ?mk=1 (else the port is probably not a "
            "FETCH/WRITE port)"
        )
    if failure == "timeout":
        return (
            "the peer accepted the connection but sent nothing; likely causes: the module does "
            "not use the Tani MK header (try without ?mk=1), or the port is not a FETCH/WRITE "
            "port"
        )
    return ""


def s5lan_hint(failure: Failure, reply: bytes, *, first: bool) -> str:
    """S5-LAN-LINK: another protocol on the port (byte order is hinted on the error reply),
    or a first request closed unanswered. The latter is what the module does to a second
    connection, but also what other services do to bytes they cannot parse: the hint names the
    rule as one possible cause and blames no other client (we have no evidence of one)."""
    if reply:
        if _looks_like_s5lan(reply):
            return ""
        return _other_protocol(reply, "an S5-LAN-LINK module")
    if first and failure == "closed":
        return (
            "the peer closed the connection before answering the first request on it; an "
            "S5-LAN module accepts one connection at a time and closes any further one, so "
            "check whether another connection to it is open; else the port is probably not an "
            "S5-LAN module"
        )
    if first and failure == "timeout":
        return (
            "the peer accepted the connection but sent nothing; an S5-LAN module answers every "
            "26-byte request block, so this port is probably not an S5-LAN module (an E71, "
            "for one, waits silently for the rest of what it took for its own request); check "
            "the port"
        )
    return ""


def as511_hint(failure: Failure, reply: bytes, *, serial: bool, first: bool) -> str:
    """AS511: a TCP port that is not a serial device server, or wrong serial line settings."""
    if reply:
        other = _other_protocol(reply, "an AS511 programming port")
        if other and not _looks_like_as511(reply):
            return other
        if failure != "closed" and not any(b in (0x02, 0x10, 0x16) for b in reply):
            where = "the serial port" if serial else "the device server's serial side"
            option = "?baud=, ?parity= and ?stopbits=" if serial else "the device server"
            return (
                f"bytes arrived ({_hex(reply)}) but none is an AS511 control character "
                f"(STX, DLE, SYN): the line settings of {where} probably do not match the PLC "
                f"(9600 baud, 8E1); check {option}"
            )
        return ""
    if serial or not first:
        return ""
    if failure == "closed":
        return (
            "the peer closed the TCP connection right after our STX; a serial device server "
            "passes bytes through and keeps the connection, so this port is probably not one "
            "(a FETCH/WRITE or Tani MK port, for one, closes on bytes it cannot parse); check "
            "the host and port"
        )
    if failure == "timeout":
        return (
            "nothing came back over TCP; check that this port is a serial device server in raw "
            "TCP mode (no telnet/RFC 2217) whose serial side is wired to the PG port at 9600 "
            "baud 8E1 — a PLC protocol port (E71, S5-LAN, FETCH/WRITE) also stays silent on "
            "the single STX AS511 starts with"
        )
    return ""
