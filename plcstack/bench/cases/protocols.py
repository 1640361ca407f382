"""The protocol variants of cases 1-3: E71 TCP/UDP, S5-LAN, FETCH/WRITE raw and MK, AS511 over TCP.

Memory layout used everywhere (so every side reads known values):

* E71: ``D0..D63`` hold :func:`sample_words`; writes go to ``D1000..D1063``.
* S5 (one :class:`~plcstack.sim.s5memory.S5Memory`): ``DB10`` with 128 data words, ``DW0..DW63``
  hold :func:`sample_words`; writes go to ``DB10.DW64..DW127``. With the memory's default RAM start
  the block header is at 0100h, DW0 at 010Ah (AS511 reads absolute addresses from there).
"""

from __future__ import annotations

import importlib
import struct
from types import ModuleType
from typing import Any

from plcstack.bench import frames
from plcstack.bench.cases import WORDS, ProtocolCase, Unavailable, sample_words
from plcstack.bench.cases.codecs import as511_codec, e71_codec, fw_codec, s5lan_codec

__all__ = ["PROTOCOLS", "by_key"]

DB = 10
DB_WORDS = 2 * WORDS
WRITE_SEED = 0x3003


# -- memories --------------------------------------------------------------------------------------
def e71_memory(sim: ModuleType) -> Any:
    memory = importlib.import_module("plcstack.sim.melsec_memory").MelsecMemory()
    memory.write_words("D", 0, sample_words())
    return memory


def s5_memory(sim: ModuleType | None = None) -> Any:
    from plcstack.sim.s5memory import S5Memory

    memory = S5Memory(default_dbs={DB: DB_WORDS})
    memory.write_db_words(DB, 0, sample_words())
    return memory


def _s5_block() -> tuple[int, bytes]:
    """``(DW0 address, 10-byte header)`` of the benchmark DB in the simulator's memory."""
    from plcstack.sim.s5memory import BlockType

    address, header = s5_memory().block_info(BlockType.DB, DB)
    return int(address), bytes(header)


# -- floor jobs ------------------------------------------------------------------------------------
def e71_read() -> frames.FloorJob:
    reply = frames.e71_reply_words(sample_words())
    return frames.FloorJob(frames.e71_read_words("D", 0, WORDS), len(reply), reply)


def e71_write() -> frames.FloorJob:
    request = frames.e71_write_words("D", 1000, sample_words(seed=WRITE_SEED))
    return frames.FloorJob(request, 2, b"\x83\x00")


def s5lan_read() -> frames.FloorJob:
    job = frames.s5lan_read_words(DB, 0, WORDS)
    reply = frames.s5lan_header(b"R", b"W", b"D", DB, 0, WORDS, version=104) + struct.pack(
        f"<{WORDS}H", *sample_words()
    )
    return frames.FloorJob(job.request, job.reply_len, reply)


def s5lan_write() -> frames.FloorJob:
    job = frames.s5lan_write_words(DB, WORDS, sample_words(seed=WRITE_SEED))
    reply = frames.s5lan_header(b"W", b"W", b"D", DB, WORDS, WORDS, version=104)
    return frames.FloorJob(job.request, job.reply_len, reply)


def fw_read() -> frames.FloorJob:
    job = frames.fw_fetch(0x01, DB, 0, WORDS)
    reply = frames.fw_ack(0x06) + struct.pack(f">{WORDS}H", *sample_words())
    return frames.FloorJob(job.request, job.reply_len, reply)


def fw_write() -> frames.FloorJob:
    data = struct.pack(f">{WORDS}H", *sample_words(seed=WRITE_SEED))
    job = frames.fw_write(0x01, DB, WORDS, data)
    return frames.FloorJob(job.request, job.reply_len, frames.fw_ack(0x04))


def fw_mk_read() -> frames.FloorJob:
    return frames.fw_mk(fw_read())


def fw_mk_write() -> frames.FloorJob:
    return frames.fw_mk(fw_write())


def as511_read() -> frames.ScriptJob:
    """One 04h transaction from the block header on: what plcstack's AS511 client sends for a DB
    read with a cached address (it re-reads the 10-byte header to check that the block did not
    move), so floor and stack do the same wire work."""
    dw0, header = _s5_block()
    return frames.as511_read(dw0 - 10, header + struct.pack(f">{WORDS}H", *sample_words()))


def as511_write() -> frames.ScriptJob:
    """B_INFO, then 03h: the client asks for the block address before every write (as
    libnodave does), so the floor replays both transactions."""
    dw0, header = _s5_block()
    data = struct.pack(f">{WORDS}H", *sample_words(seed=WRITE_SEED))
    return frames.as511_chain(
        frames.as511_b_info(0x01, DB, dw0, header), frames.as511_write(dw0 + 2 * WORDS, data)
    )


# -- cases -----------------------------------------------------------------------------------------
PROTOCOLS: list[ProtocolCase] = [
    ProtocolCase(
        key="e71+tcp",
        modules=("plcstack.sim.e71", "plcstack.clients.e71", "plcstack.codecs.e71"),
        sim_module="plcstack.sim.e71",
        make_memory=e71_memory,
        read_address="D0",
        write_address="D1000",
        floor_read=e71_read,
        floor_write=e71_write,
        codec=e71_codec,
    ),
    ProtocolCase(
        key="e71+udp",
        modules=("plcstack.sim.e71", "plcstack.clients.e71", "plcstack.codecs.e71"),
        sim_module="plcstack.sim.e71",
        make_memory=e71_memory,
        sim_kwargs={"transport": "udp"},
        read_address="D0",
        write_address="D1000",
        floor_read=e71_read,
        floor_write=e71_write,
        udp=True,
    ),
    ProtocolCase(
        key="s5lan",
        modules=("plcstack.sim.s5lan", "plcstack.clients.s5lan", "plcstack.codecs.s5lan"),
        sim_module="plcstack.sim.s5lan",
        make_memory=s5_memory,
        # the module takes one connection (A1.3); floor and stack are connected side by side
        sim_kwargs={"max_connections": 2},
        read_address=f"DB{DB}.DW0",
        write_address=f"DB{DB}.DW{WORDS}",
        floor_read=s5lan_read,
        floor_write=s5lan_write,
        codec=s5lan_codec,
    ),
    ProtocolCase(
        key="fetchwrite",
        modules=(
            "plcstack.sim.fetchwrite",
            "plcstack.clients.fetchwrite",
            "plcstack.codecs.fetchwrite",
        ),
        sim_module="plcstack.sim.fetchwrite",
        make_memory=s5_memory,
        read_address=f"DB{DB}.DW0",
        write_address=f"DB{DB}.DW{WORDS}",
        floor_read=fw_read,
        floor_write=fw_write,
        codec=lambda: fw_codec(mk=False),
    ),
    ProtocolCase(
        key="fetchwrite+mk",
        modules=(
            "plcstack.sim.fetchwrite",
            "plcstack.clients.fetchwrite",
            "plcstack.codecs.fetchwrite",
        ),
        sim_module="plcstack.sim.fetchwrite",
        make_memory=s5_memory,
        sim_kwargs={"mk": True},
        read_address=f"DB{DB}.DW0",
        write_address=f"DB{DB}.DW{WORDS}",
        floor_read=fw_mk_read,
        floor_write=fw_mk_write,
        codec=lambda: fw_codec(mk=True),
    ),
    ProtocolCase(
        key="as511+tcp",
        modules=("plcstack.sim.as511", "plcstack.clients.as511", "plcstack.codecs.as511"),
        sim_module="plcstack.sim.as511",
        make_memory=s5_memory,
        read_address=f"DB{DB}.DW0",
        write_address=f"DB{DB}.DW{WORDS}",
        floor_read=as511_read,
        floor_write=as511_write,
        codec=as511_codec,
    ),
]


def by_key(key: str) -> ProtocolCase:
    for case in PROTOCOLS:
        if case.key == key:
            return case
    raise Unavailable(f"unknown protocol case {key!r}")
