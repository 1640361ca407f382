"""Wire bytes for the floor clients, written from the spec rules (not taken from plcstack's codecs).

The floor must not share code with the stack it is compared against, or a bug or a cost in the
codec would show up on both sides. These builders follow the byte layouts of
``specs/melsec-e71.md`` (sections 4, 7.3, 12) and ``specs/siemens-s5.md`` (A.2, B.4, C.1, C.6);
``tests/test_bench.py`` checks them against the spec's golden vectors byte for byte, then the
benchmarks use the same builders for 64-word jobs.

A *job* is what a floor client replays: for request/response protocols one request and the exact
reply length; for AS511 a scripted dialogue of ``(bytes to send, bytes to expect)`` steps.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

__all__ = [
    "E71_DEVICE_CODES",
    "FloorJob",
    "ScriptJob",
    "as511_b_info",
    "as511_chain",
    "as511_read",
    "as511_stuff",
    "as511_write",
    "e71_read_words",
    "e71_reply_words",
    "e71_write_words",
    "fw_ack",
    "fw_fetch",
    "fw_write",
    "mk_wrap",
    "s5lan_header",
    "s5lan_read_words",
    "s5lan_write_words",
]


@dataclass(frozen=True)
class FloorJob:
    """One request and the exact reply length (``expect``: the reply bytes, for a warm-up check)."""

    request: bytes
    reply_len: int
    expect: bytes | None = None
    #: the Tani MK header needs a fresh SeqNo per telegram: offsets of the SeqNo fields to patch
    mk_seq_offsets: tuple[int, ...] = ()


@dataclass(frozen=True)
class ScriptJob:
    """A dialogue (AS511): send ``steps[i][0]``, then wait for exactly ``steps[i][1]`` bytes."""

    steps: tuple[tuple[bytes, int], ...]
    expect: bytes | None = None  # everything the peer sends during one job, for a warm-up check


# -- MELSEC E71 1E frame, binary (melsec-e71.md 4.2, 4.3, 7.3) ------------------------------------
E71_DEVICE_CODES = {
    "X": 0x5820, "Y": 0x5920, "M": 0x4D20, "F": 0x4620, "B": 0x4220,
    "TS": 0x5453, "TC": 0x5443, "TN": 0x544E, "CS": 0x4353, "CC": 0x4343, "CN": 0x434E,
    "D": 0x4420, "W": 0x5720, "R": 0x5220,
}  # fmt: skip


def _e71_head(command: int, pc: int = 0xFF, timer: int = 0x000A) -> bytes:
    return struct.pack("<BBH", command, pc, timer)


def _e71_dev(device: str, number: int) -> bytes:
    return struct.pack("<IH", number, E71_DEVICE_CODES[device])


def e71_read_words(device: str, number: int, count: int) -> bytes:
    """Command 01H, batch read in word units (count 256 is sent as 00H)."""
    return _e71_head(0x01) + _e71_dev(device, number) + bytes([count & 0xFF, 0])


def e71_reply_words(words: list[int]) -> bytes:
    """Normal 81H response carrying ``words`` (little-endian)."""
    return b"\x81\x00" + struct.pack(f"<{len(words)}H", *words)


def e71_write_words(device: str, number: int, words: list[int]) -> bytes:
    """Command 03H, batch write in word units; the reply is ``83 00``."""
    head = _e71_head(0x03) + _e71_dev(device, number) + bytes([len(words) & 0xFF, 0])
    return head + struct.pack(f"<{len(words)}H", *words)


# -- S5-LAN-LINK (siemens-s5.md A.2, A.6) ---------------------------------------------------------
_S5LAN = struct.Struct("<BHBBcccHHHhH4s4s")


def s5lan_header(
    cmd: bytes,
    data_type: bytes,
    area: bytes,
    db: int,
    start: int,
    count: int,
    *,
    err: int = 0,
    version: int = 0,
    user: bytes = b"\x00" * 4,
) -> bytes:
    """The 26-byte block, header fields little-endian (decision A.3)."""
    return _S5LAN.pack(0x35, 0, 0, 26, cmd, data_type, area, db, start, count, err, version, user,
                       b"\x00" * 4)  # fmt: skip


def s5lan_read_words(db: int, dw: int, count: int) -> FloorJob:
    request = s5lan_header(b"R", b"W", b"D", db, dw, count)
    return FloorJob(request, 26 + 2 * count)


def s5lan_write_words(db: int, dw: int, words: list[int]) -> FloorJob:
    """Words travel low byte first (A.6); the reply is the bare 26-byte block."""
    request = s5lan_header(b"W", b"W", b"D", db, dw, len(words))
    return FloorJob(request + struct.pack(f"<{len(words)}H", *words), 26)


# -- S5 FETCH/WRITE (C.6) and the Tani MK header (C.1, C.4) --------------------------------------
_FW_ORG_WORDS = {0x01, 0x06, 0x07, 0x08, 0x09, 0x0A, 0x10}


def _fw_header(opcode: int, org: int, db: int, start: int, length: int) -> bytes:
    return struct.pack(">2sBBBBBBBBHHBB", b"S5", 16, 1, 3, opcode, 3, 8, org, db, start, length,
                       0xFF, 2)  # fmt: skip


def fw_fetch(org: int, db: int, start: int, length: int) -> FloorJob:
    unit = 2 if org in _FW_ORG_WORDS else 1
    return FloorJob(_fw_header(0x05, org, db, start, length), 16 + unit * length)


def fw_write(org: int, db: int, start: int, data: bytes) -> FloorJob:
    unit = 2 if org in _FW_ORG_WORDS else 1
    return FloorJob(_fw_header(0x03, org, db, start, len(data) // unit) + data, 16)


def fw_ack(opcode: int, error: int = 0) -> bytes:
    """The 16-byte acknowledgement: opcode 06H (FETCH) or 04H (WRITE)."""
    return struct.pack(">2sBBBBBBBBB5s", b"S5", 16, 1, 3, opcode, 0x0F, 3, error, 0xFF, 7,
                       b"\x00" * 5)  # fmt: skip


def mk_wrap(message: bytes, seq: int, max_data: int = 512) -> tuple[bytes, tuple[int, ...], int]:
    """Split ``message`` into MK telegrams (C.4) starting at SeqNo ``seq``.

    Returns the bytes, the offsets of the SeqNo fields (so a replaying client can renumber them)
    and how many SeqNos were used.
    """
    out = bytearray()
    offsets: list[int] = []
    chunks = [message[i : i + max_data] for i in range(0, len(message), max_data)] or [b""]
    for index, chunk in enumerate(chunks):
        more = 1 if index < len(chunks) - 1 else 0
        offsets.append(len(out) + 6)
        out += b"MK" + struct.pack("<HHH", len(chunk), more, (seq + index) & 0xFFFF) + chunk
    return bytes(out), tuple(offsets), len(chunks)


def mk_length(message_len: int, max_data: int = 512) -> int:
    """Bytes on the wire for one message of ``message_len`` bytes in MK telegrams."""
    telegrams = max(1, -(-message_len // max_data))
    return message_len + 8 * telegrams


def fw_mk(job: FloorJob, max_data: int = 512) -> FloorJob:
    """The same job inside the MK header; SeqNo fields are renumbered by the floor client."""
    wrapped, offsets, _ = mk_wrap(job.request, 0, max_data)
    return FloorJob(wrapped, mk_length(job.reply_len, max_data), mk_seq_offsets=offsets)


# -- AS511 (B.3, B.4, B.7.3, B.7.4) ----------------------------------------------------------------
DLE_ACK = b"\x10\x06"


def as511_stuff(data: bytes) -> bytes:
    """DLE transparency: every data byte 10h is sent twice."""
    return data.replace(b"\x10", b"\x10\x10")


def _as511_script(fn: int, params: bytes, response: bytes | None) -> ScriptJob:
    """The 17-step skeleton of B.4 for one function, as the PG (client) side replays it.

    ``response`` is the AG's unstuffed data frame (``None`` for a function without one). The final
    ``10 06`` is sent together with the next job's ``02``: the AG expects nothing in between.
    """
    steps: list[tuple[bytes, int]] = [
        (b"\x02", 2),  # STX -> DLE ACK
        (bytes([fn]), 1),  # function -> STX
        (DLE_ACK, 3),  # ACK -> accept frame 16 10 03
    ]
    ag = bytearray(DLE_ACK + b"\x02" + b"\x16\x10\x03")
    frame = as511_stuff(params) + b"\x10\x04"
    if response is not None:
        data_frame = as511_stuff(response) + b"\x10\x03"
        steps += [
            (DLE_ACK + frame, 3),  # ACK + parameter frame -> 10 06 02
            (DLE_ACK, len(data_frame)),  # ACK -> data frame
            (DLE_ACK, 1),  # ACK -> STX of the terminate phase
        ]
        ag += DLE_ACK + b"\x02" + data_frame + b"\x02"
    else:
        steps += [(DLE_ACK + frame, 3)]  # ACK + parameter frame -> 10 06 02 (terminate STX)
        ag += DLE_ACK + b"\x02"
    steps += [(DLE_ACK, 3), (DLE_ACK, 0)]  # ACK -> 12 10 03; final ACK
    ag += b"\x12\x10\x03"
    return ScriptJob(tuple(steps), bytes(ag))


def as511_read(start: int, data: bytes) -> ScriptJob:
    """Function 04h: read ``len(data)`` bytes from absolute ``start``; ``data`` is what the AG
    holds there (needed to know the stuffed reply length)."""
    params = struct.pack(">HH", start, start + len(data) - 1)
    return _as511_script(0x04, params, b"\x00" * 5 + data)


def as511_write(start: int, data: bytes) -> ScriptJob:
    """Function 03h: write ``data`` at absolute ``start`` (no response data frame)."""
    return _as511_script(0x03, struct.pack(">H", start) + data, None)


def as511_b_info(block_type: int, number: int, dw0: int, header: bytes) -> ScriptJob:
    """Function 1Ah (B_INFO): the AG answers ``00``, the DW0 address and the 10-byte header."""
    return _as511_script(
        0x1A, bytes([block_type, number]), b"\x00" + struct.pack(">H", dw0) + header
    )


def as511_chain(*jobs: ScriptJob) -> ScriptJob:
    """Several transactions replayed back to back as one job (e.g. B_INFO, then a write)."""
    steps = tuple(step for job in jobs for step in job.steps)
    expects = [job.expect for job in jobs]
    expect = b"".join(e for e in expects if e is not None) if None not in expects else None
    return ScriptJob(steps, expect)


def as511_pg_stream(job: ScriptJob) -> bytes:
    """Everything the PG sends for one job (for comparing with the spec's "PG stream")."""
    return b"".join(send for send, _ in job.steps)
