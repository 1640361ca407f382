"""Case 1: codec cost per operation, encode the request + decode the reply, per protocol.

Each adapter returns :class:`CodecOps`: the stack side drives the protocol's Sans-IO client
connection exactly as its client does (build the request event, ``send``, ``receive_data`` of the
reply bytes, ``next_event`` until the response event); the floor side does the same job with
``struct`` only (pack the request header, check the reply's status bytes, unpack the words). The
reply bytes are built once from the spec rules (:mod:`benchmarks.frames`). One call is verified
outside the timing, so a codec that decodes something else fails the benchmark.

The adapters import the codecs lazily: a protocol not merged yet raises :class:`Unavailable`.
"""

from __future__ import annotations

import importlib
import struct
from collections.abc import Callable
from types import ModuleType
from typing import Any

from benchmarks import frames
from benchmarks.cases import WORDS, CodecOps, Unavailable, sample_words

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
    codec = fw.ClientConnection("mk" if mk else "raw")
    # The peer's MK sequence numbers are not enforced by default (C.2), so one telegram
    # can be replayed; its SeqNo stays 0.
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


# -- placeholders filled in as each protocol lands -------------------------------------------------
def e71_codec() -> CodecOps:
    _module("plcstack.codecs.e71")
    raise Unavailable("codec adapter for E71 pending")


def s5lan_codec() -> CodecOps:
    _module("plcstack.codecs.s5lan")
    raise Unavailable("codec adapter for S5-LAN pending")


def as511_codec() -> CodecOps:
    _module("plcstack.codecs.as511")
    raise Unavailable("codec adapter for AS511 pending")
