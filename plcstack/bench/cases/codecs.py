"""Case 1: codec cost per operation, encode the request + decode the reply, per protocol.

Each adapter returns :class:`CodecOps`: the stack side drives the protocol's Sans-IO client
connection exactly as its client does (build the request event, ``send``, ``receive_data`` of the
reply bytes, ``next_event`` until the response event); the floor side does the same job with
``struct`` only (pack the request header, check the reply's status bytes, unpack the words). The
reply bytes are built once from the spec rules (:mod:`plcstack.bench.frames`). One call is verified
outside the timing, so a codec that decodes something else fails the benchmark.

The adapters import the codecs lazily: a protocol not merged yet raises :class:`Unavailable`.
"""

from __future__ import annotations

import importlib
import struct
from collections.abc import Callable
from types import ModuleType
from typing import Any

from plcstack.bench import frames
from plcstack.bench.cases import WORDS, CodecOps, Unavailable, sample_words

__all__ = ["as511_codec", "e71_codec", "fw_codec", "s5lan_codec"]

DB = 10
_WORDS_LE = struct.Struct(f"<{WORDS}H")
_WORDS_BE = struct.Struct(f">{WORDS}H")


def _module(name: str) -> ModuleType:
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and name.startswith(exc.name):
            raise Unavailable(f"not merged yet ({name} missing)") from None
        raise


def _verified(op: Callable[[], object], check: Callable[[object], bool], what: str) -> Any:
    result = op()
    if not check(result):
        raise AssertionError(f"{what}: unexpected result {result!r:.200}")
    return op


def _need_data(mod: ModuleType) -> object:
    return importlib.import_module("plcstack.codecs._common").NEED_DATA


def _drive(codec: Any, request: Any, reply: bytes, need_data: object) -> Any:
    codec.send(request)
    codec.receive_data(reply)
    event = codec.next_event()
    if event is need_data:
        raise AssertionError("codec wants more bytes than the spec-built reply has")
    return event


# -- S5 FETCH/WRITE --------------------------------------------------------------------------------
def fw_codec(*, mk: bool) -> CodecOps:
    fw = _module("plcstack.codecs.fetchwrite")
    need = _need_data(fw)
    values = sample_words()
    read_reply = frames.fw_ack(0x06) + _WORDS_BE.pack(*values)
    write_data = _WORDS_BE.pack(*sample_words(seed=0x3003))
    write_reply = frames.fw_ack(0x04)
    # One telegram is replayed, its SeqNo staying 0: the benchmark turns the sequence check off
    # (on by default), which costs the same either way.
    codec = (
        fw.ClientConnection("mk", mk=_module("plcstack.codecs.mk").MkConnection(check_seq=False))
        if mk
        else fw.ClientConnection("raw")
    )
    if mk:
        read_reply = frames.mk_wrap(read_reply, 0)[0]
        write_reply = frames.mk_wrap(write_reply, 0)[0]

    def stack_read() -> Any:
        return _drive(codec, fw.FetchRequest(1, DB, 0, WORDS), read_reply, need)

    def stack_write() -> Any:
        return _drive(codec, fw.WriteRequest.of(1, DB, WORDS, write_data), write_reply, need)

    header = struct.Struct(">2sBBBBBBBBHHBB")
    raw_read_reply = read_reply[8:] if mk else read_reply
    seq = [0]

    def wrap(payload: bytes) -> bytes:
        if not mk:
            return payload
        seq[0] = (seq[0] + 1) & 0xFFFF
        return b"MK" + struct.pack("<HHH", len(payload), 0, seq[0]) + payload

    def floor_read() -> Any:
        wrap(header.pack(b"S5", 16, 1, 3, 5, 3, 8, 1, DB, 0, WORDS, 0xFF, 2))
        reply = raw_read_reply
        if reply[:2] != b"S5" or reply[5] != 6 or reply[8] != 0:
            raise AssertionError("bad ack")
        return reply[16:]

    def floor_write() -> Any:
        wrap(header.pack(b"S5", 16, 1, 3, 3, 3, 8, 1, DB, WORDS, WORDS, 0xFF, 2) + write_data)
        reply = write_reply[8:] if mk else write_reply
        if reply[:2] != b"S5" or reply[5] != 4 or reply[8] != 0:
            raise AssertionError("bad ack")
        return reply[8]

    expected = _WORDS_BE.pack(*values)
    return CodecOps(
        stack_read=_verified(stack_read, lambda e: getattr(e, "data", None) == expected, "FETCH"),
        stack_write=_verified(stack_write, lambda e: getattr(e, "error", None) == 0, "WRITE"),
        floor_read=_verified(floor_read, lambda d: d == expected, "floor FETCH"),
        floor_write=floor_write,
    )


# -- MELSEC E71 ----------------------------------------------------------------------------
def e71_codec() -> CodecOps:
    e71 = _module("plcstack.codecs.e71")
    need = _need_data(e71)
    values = sample_words()
    write_values = tuple(sample_words(seed=0x3003))
    read_reply = frames.e71_reply_words(values)
    codec = e71.E71ClientConnection("binary")
    d0 = e71.parse_address("D0")
    d1000 = e71.parse_address("D1000")

    read_words = e71.ReadWords

    def stack_read() -> Any:
        # _drive inlined: the floor is one function too, so the row prices the codec only
        codec.send(read_words(d0, WORDS))
        codec.receive_data(read_reply)
        event = codec.next_event()
        if event is need:
            raise AssertionError("codec wants more bytes than the spec-built reply has")
        return event

    def stack_write() -> Any:
        return _drive(codec, e71.WriteWords(d1000, write_values), b"\x83\x00", need)

    head = struct.Struct("<BBHIHBB")

    def floor_read() -> Any:
        head.pack(0x01, 0xFF, 0x0A, 0, 0x4420, WORDS, 0)
        if read_reply[0] != 0x81 or read_reply[1] != 0:
            raise AssertionError("bad reply")
        return list(_WORDS_LE.unpack_from(read_reply, 2))

    def floor_write() -> Any:
        head.pack(0x03, 0xFF, 0x0A, 1000, 0x4420, WORDS, 0) + _WORDS_LE.pack(*write_values)
        reply = b"\x83\x00"
        if reply[0] != 0x83 or reply[1] != 0:
            raise AssertionError("bad reply")
        return reply

    return CodecOps(
        stack_read=_verified(
            stack_read, lambda e: list(getattr(e, "values", ())) == values, "E71 01H"
        ),
        stack_write=_verified(stack_write, lambda e: type(e).__name__ == "Ack", "E71 03H"),
        floor_read=_verified(floor_read, lambda v: v == values, "floor 01H"),
        floor_write=floor_write,
    )


# -- S5-LAN-LINK ------------------------------------------------------------------------------
def s5lan_codec() -> CodecOps:
    lan = _module("plcstack.codecs.s5lan")
    need = _need_data(lan)
    values = sample_words()
    read_reply = frames.s5lan_header(b"R", b"W", b"D", DB, 0, WORDS, version=104) + (
        _WORDS_LE.pack(*values)
    )
    write_data = _WORDS_LE.pack(*sample_words(seed=0x3003))
    write_reply = frames.s5lan_header(b"W", b"W", b"D", DB, WORDS, WORDS, version=104)
    codec = lan.ClientConnection()

    def stack_read() -> Any:
        return _drive(codec, lan.Request.read("D", "W", 0, WORDS, db=DB), read_reply, need)

    def stack_write() -> Any:
        request = lan.Request.write("D", "W", WORDS, write_data, db=DB)
        return _drive(codec, request, write_reply, need)

    header = struct.Struct("<BHBBcccHHHhH4s4s")
    zeros = bytes(4)

    def floor_read() -> Any:
        header.pack(0x35, 0, 0, 26, b"R", b"W", b"D", DB, 0, WORDS, 0, 0, zeros, zeros)
        reply = header.unpack_from(read_reply)
        if reply[10] != 0 or reply[9] != WORDS:
            raise AssertionError("bad reply")
        return list(_WORDS_LE.unpack_from(read_reply, 26))

    def floor_write() -> Any:
        header.pack(0x35, 0, 0, 26, b"W", b"W", b"D", DB, WORDS, WORDS, 0, 0, zeros, zeros) + (
            write_data
        )
        reply = header.unpack_from(write_reply)
        if reply[10] != 0:
            raise AssertionError("bad reply")
        return reply

    expected = _WORDS_LE.pack(*values)
    return CodecOps(
        stack_read=_verified(stack_read, lambda e: getattr(e, "data", None) == expected, "LAN R"),
        stack_write=_verified(stack_write, lambda e: getattr(e, "err", None) == 0, "LAN W"),
        floor_read=_verified(floor_read, lambda v: v == values, "floor LAN R"),
        floor_write=floor_write,
    )


# -- AS511 ------------------------------------------------------------------------------------
def as511_codec() -> CodecOps:
    """The whole PG dialogue of one transaction, fed with the AG's answers step by step (split
    as a real line delivers them: one chunk per PG step). The floor walks the same steps and
    un-stuffs the data frame with ``bytes.replace``."""
    as511 = _module("plcstack.codecs.as511")
    need = _need_data(as511)
    values = sample_words()
    dw0 = 0x010A
    data = _WORDS_BE.pack(*values)
    read_script = frames.as511_read(dw0, data)
    write_data = _WORDS_BE.pack(*sample_words(seed=0x3003))
    write_script = frames.as511_write(dw0 + 2 * WORDS, write_data)

    def chunks(script: frames.ScriptJob) -> list[bytes]:
        out, pos = [], 0
        assert script.expect is not None
        for _send, count in script.steps:
            out.append(script.expect[pos : pos + count])
            pos += count
        return out

    read_chunks, write_chunks = chunks(read_script), chunks(write_script)
    pg = as511.PGConnection()

    def run(job: Any, answers: list[bytes]) -> Any:
        pg.submit(job, 0.0)
        pg.data_to_send()
        for chunk in answers:
            if chunk:
                pg.receive_data(chunk, 0.0)
            pg.data_to_send()
        event = pg.next_event()
        if event is need:
            raise AssertionError("AS511 dialogue did not complete")
        return event

    def stack_read() -> Any:
        return run(as511.read_job(dw0, 2 * WORDS), read_chunks)

    def stack_write() -> Any:
        return run(as511.write_job(dw0 + 2 * WORDS, write_data), write_chunks)

    read_sends = [send for send, _ in read_script.steps]
    write_sends = [send for send, _ in write_script.steps]
    params = struct.Struct(">HH")
    frame = read_chunks[4]

    def floor_read() -> Any:
        params.pack(dw0, dw0 + 2 * WORDS - 1)
        for _send in read_sends:
            pass
        payload = frame[:-2].replace(b"\x10\x10", b"\x10")
        return list(_WORDS_BE.unpack_from(payload, 5))

    def floor_write() -> Any:
        (struct.pack(">H", dw0 + 2 * WORDS) + write_data).replace(b"\x10", b"\x10\x10")
        for _send in write_sends:
            pass
        return write_chunks[-2]

    prefix = b"\x00" * 5
    return CodecOps(
        stack_read=_verified(
            stack_read, lambda e: getattr(e, "data", None) == prefix + data, "AS511 04h"
        ),
        stack_write=_verified(stack_write, lambda e: getattr(e, "data", None) == b"", "AS511 03h"),
        floor_read=_verified(floor_read, lambda v: v == values, "floor 04h"),
        floor_write=floor_write,
    )
