"""Misconfiguration hints: the real client against the real simulator configured the other way.

Each case runs over loopback TCP (or UDP) and asserts the error type (unchanged by the hint) and
the hint's wording; fake peers answering garbage check that no misleading hint is given.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from plcstack import connect
from plcstack.diagnose import (
    as511_hint,
    e71_hint,
    fetchwrite_hint,
    identify,
    looks_like_e71_ascii,
    looks_like_e71_binary,
    s5lan_hint,
)
from plcstack.errors import (
    ConnectionLost,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
)
from plcstack.sim import as511 as as511sim
from plcstack.sim import e71 as e71sim
from plcstack.sim import fetchwrite as fwsim
from plcstack.sim import s5lan as s5lansim
from plcstack.sim.base import Simulator
from tests.aio_helpers import ends_quietly

H = bytes.fromhex
FAST = "timeout=0.5"

# -- the signatures, on golden vectors of the specs -----------------------------------------------

IDENTIFY_CASES = [
    # melsec-e71 §12 #5 (binary and ASCII answers), §4 undefined subheader answer (65H -> E5 50)
    (H("81 00 34 12 76 98 09 01"), "E71 in binary mode"),
    (b"8100123498760109", "E71 in ASCII mode"),
    (H("E5 50"), "E71 in binary mode"),
    (b"FF54", "E71 in ASCII mode"),
    # siemens-s5 C.1 MK header (a life ack, and a data telegram), C.6.2 FETCH ack
    (H("4D 4B 00 00 00 00 01 00"), "MK header"),
    (H("4D 4B 10 00 00 00 00 00 53 35 10 01 03 06 0F 03"), "MK header"),
    (H("53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00"), "FETCH/WRITE port"),
    # A.10 response block (PLCType '5', Interface 0, PLCNo 0, HdLen 26)
    (H("35 00 00 00 1A 52 57 44 0A 00 05 00 14 00 00 00 68 00 11 22 33 44 00 00 00 00"), "S5-LAN"),
    # B.11 AS511: DLE ACK, DLE NAK, accept frame
    (H("10 06"), "AS511"),
    (H("10 15"), "AS511"),
    (H("16 10 03"), "AS511"),
]


@pytest.mark.parametrize(("reply", "expected"), IDENTIFY_CASES)
def test_identify_golden(reply: bytes, expected: str) -> None:
    found = identify(reply)
    assert found is not None and expected in found


@pytest.mark.parametrize(
    "reply",
    [b"", b"\x00\x01\x02\x03garbage!", b"HTTP/1.0 400 Bad Request\r\n", b"\x81", b"81", b"S"],
)
def test_identify_garbage(reply: bytes) -> None:
    assert identify(reply) is None


def test_e71_code_signatures_exclude_each_other_on_goldens() -> None:
    assert looks_like_e71_binary(H("81 00")) and not looks_like_e71_ascii(H("81 00"))
    assert looks_like_e71_ascii(b"8100") and not looks_like_e71_binary(b"8100")
    # a command echo (bit 7 clear) is no answer in either code
    assert not looks_like_e71_ascii(b"0100") and not looks_like_e71_binary(H("01 00"))


FAILURES = st.sampled_from(["malformed", "timeout", "closed"])


def _all_hints(failure: str, reply: bytes, first: bool) -> list[str]:
    f = failure  # Literal narrowing is not needed at run time
    return [
        e71_hint(f, reply, code="binary", first=first),  # type: ignore[arg-type]
        e71_hint(f, reply, code="ascii", first=first),  # type: ignore[arg-type]
        fetchwrite_hint(f, reply, mk=False, first=first),  # type: ignore[arg-type]
        fetchwrite_hint(f, reply, mk=True, first=first),  # type: ignore[arg-type]
        s5lan_hint(f, reply, first=first),  # type: ignore[arg-type]
        as511_hint(f, reply, serial=False, first=first),  # type: ignore[arg-type]
    ]


# random bytes, and random bytes behind the first bytes of each signature (near misses)
REPLIES = st.one_of(
    st.binary(min_size=1, max_size=40),
    st.builds(
        bytes.__add__,
        st.sampled_from([b"S", b"S5", b"MK", b"8", b"F", b"\x10", b"\x16", b"5\x00", b"\x81"]),
        st.binary(max_size=12),
    ),
    st.builds(
        bytes.__add__,
        st.text("0123456789ABCDEFabcdef", max_size=6).map(str.encode),
        st.binary(max_size=6),
    ),
).filter(bool)


@settings(max_examples=200, suppress_health_check=[HealthCheck.too_slow])
@given(failure=FAILURES, reply=REPLIES, first=st.booleans())
def test_unrecognised_bytes_get_no_protocol_hint(failure: str, reply: bytes, first: bool) -> None:
    """Bytes that carry no protocol's signature never produce a setting to try (only AS511 may
    say that the line settings look wrong, and only when no control character arrived)."""
    hints = _all_hints(failure, reply, first)
    assert all(isinstance(h, str) for h in hints)
    if identify(reply) is None:
        assert hints[:5] == ["", "", "", "", ""]
        if any(b in (0x02, 0x10, 0x16) for b in reply) or failure == "closed":
            assert hints[5] == ""
        else:
            assert "line settings" in hints[5]


@settings(max_examples=200)
@given(
    head=st.sampled_from([b"8100", b"FF54", b"\x81\x00", b"MK\x00\x00\x00\x00", b"S5\x10\x01"]),
    tail=st.binary(max_size=20),
    failure=FAILURES,
    first=st.booleans(),
)
def test_hints_never_raise_on_recognised_heads(
    head: bytes, tail: bytes, failure: str, first: bool
) -> None:
    """Quoting a reply must survive any bytes after a recognised head (the hint is built on
    the failure path, where a second exception would lose it)."""
    for hint in _all_hints(failure, head + tail, first):
        assert isinstance(hint, str)


def test_ascii_quote_of_non_ascii_tail() -> None:
    hint = e71_hint("malformed", b"FF54\xff\xfe", code="binary", first=True)
    assert '"FF54\\xff\\xfe"' in hint and "try ?code=ascii" in hint


def test_no_hint_for_silence_after_the_first_request() -> None:
    """A silent or closing peer later in a connection proves nothing about the settings."""
    for failure in ("timeout", "closed"):
        assert _all_hints(failure, b"", False) == [""] * 6


# -- helpers ----------------------------------------------------------------------------------


def hostport(sim: Simulator) -> str:
    return f"{sim.host}:{sim.port}"


async def failure_of(url: str, op: Callable[[object], Awaitable[object]]) -> PlcError:
    async with connect(url) as plc:
        with pytest.raises(PlcError) as info:
            await op(plc)
    return info.value


def read(address: str, count: int = 2) -> Callable[[object], Awaitable[object]]:
    return lambda plc: plc.read(address, count)  # type: ignore[attr-defined]


def write(address: str, values: list[int]) -> Callable[[object], Awaitable[object]]:
    return lambda plc: plc.write(address, values)  # type: ignore[attr-defined]


@asynccontextmanager
async def fake_peer(answer: bytes, *, close: bool = False) -> AsyncIterator[str]:
    """A TCP peer that answers every chunk it receives with ``answer`` (then maybe closes)."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while await reader.read(4096):
                writer.write(answer)
                await writer.drain()
                if close:
                    break
        except ConnectionError:
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(ends_quietly(handle), "127.0.0.1", 0)
    try:
        yield f"127.0.0.1:{server.sockets[0].getsockname()[1]}"
    finally:
        server.close()
        await server.wait_closed()


def hint_of(exc: PlcError) -> str:
    assert "Hint: " in exc.message, exc.message
    return exc.message.split("Hint: ", 1)[1]


# -- E71: binary vs ASCII (DIP SW2) ----------------------------------------------------------


async def test_binary_client_against_ascii_e71() -> None:
    async with await e71sim.start(code="ascii") as sim:
        exc = await failure_of(f"e71+tcp://{hostport(sim)}?{FAST}", read("D100"))
    assert type(exc) is RemoteProtocolError
    hint = hint_of(exc)
    assert "ASCII-coded 1E frame" in hint and '"FF54"' in hint and "try ?code=ascii" in hint


async def test_binary_write_against_ascii_e71_keeps_the_write_outcome() -> None:
    async with await e71sim.start(code="ascii") as sim:
        exc = await failure_of(f"e71+tcp://{hostport(sim)}?{FAST}", write("D100", [1, 2]))
    assert type(exc) is RemoteProtocolError
    assert "the write may or may not have been executed. Hint: " in exc.message
    assert "try ?code=ascii" in hint_of(exc)


async def test_ascii_client_against_binary_e71() -> None:
    async with await e71sim.start(code="binary") as sim:
        exc = await failure_of(f"e71+tcp://{hostport(sim)}?code=ascii&{FAST}", read("D100"))
    # the binary answer B0 50 is shorter than an ASCII subheader and end code: no complete answer
    assert type(exc) is PlcTimeout
    hint = hint_of(exc)
    assert "binary 1E frame (B0 50)" in hint and "try ?code=binary" in hint


async def test_binary_client_against_ascii_e71_over_udp() -> None:
    async with await e71sim.start(code="ascii", transport="udp") as sim:
        exc = await failure_of(f"e71+udp://{hostport(sim)}?{FAST}", read("D100"))
    assert type(exc) is RemoteProtocolError
    assert "try ?code=ascii" in hint_of(exc)


async def test_e71_client_against_s5lan_module() -> None:
    async with await s5lansim.start() as sim:
        exc = await failure_of(f"e71+tcp://{hostport(sim)}?{FAST}", read("D100"))
    assert type(exc) is PlcTimeout
    assert "probably not an E71 MC-protocol port" in hint_of(exc)


async def test_e71_client_against_tani_module_that_closes() -> None:
    async with await fwsim.start(mk=True) as sim:
        exc = await failure_of(f"e71+tcp://{hostport(sim)}?{FAST}", read("D100"))
    assert type(exc) is ConnectionLost
    assert "closed the connection right after our first request" in hint_of(exc)


async def test_a_ninth_e71_client_is_told_of_the_connection_limit() -> None:
    """Before: "this port is probably not an E71 MC-protocol port" (the module closes the ninth
    connection; an E71 never closes on a request, so on an E71 port that is the limit). After:
    the limit of 8 connections is named first, the wrong port second."""
    async with await e71sim.start() as sim:
        held = [connect(f"e71+tcp://{hostport(sim)}") for _ in range(8)]
        try:
            for plc in held:
                await plc.aopen()
                await plc.read("D100", 1)
            exc = await failure_of(f"e71+tcp://{hostport(sim)}?{FAST}", read("D100"))
        finally:
            for plc in held:
                await plc.aclose()
    assert type(exc) is ConnectionLost
    hint = hint_of(exc)
    assert "an E71 serves 8 connections at once" in hint, hint
    assert hint.index("8 connections") < hint.index("probably not an E71"), hint


async def test_e71_client_against_as511_device_server() -> None:
    async with await as511sim.start() as sim:
        exc = await failure_of(f"e71+tcp://{hostport(sim)}?{FAST}", read("D100"))
    assert type(exc) is RemoteProtocolError
    hint = hint_of(exc)
    assert "(10 06 10 15)" in hint and "AS511" in hint and "as511+tcp://" in hint


# -- S5-LAN -----------------------------------------------------------------------------------


async def test_s5lan_client_against_e71() -> None:
    async with await e71sim.start() as sim:
        exc = await failure_of(f"s5lan://{hostport(sim)}?{FAST}", read("DB10.DW0"))
    assert type(exc) is PlcTimeout
    hint = hint_of(exc)
    assert "MELSEC E71 in binary mode" in hint and "e71+tcp://" in hint


async def test_s5lan_client_against_fetchwrite_port_names_both_causes() -> None:
    """A first request closed unanswered: the request was sent, so it is a lost connection
    (not ``ConnectFailed``); the hint names the one-connection rule as a thing to check and
    the wrong port as the alternative, and blames no other client."""
    async with await fwsim.start(mk=True) as sim:
        exc = await failure_of(f"s5lan://{hostport(sim)}?{FAST}", read("DB10.DW0"))
    assert type(exc) is ConnectionLost
    hint = hint_of(exc)
    assert "accepts one connection at a time" in hint and "not an S5-LAN module" in hint
    assert "another client" not in exc.message


async def test_s5lan_header_byte_order_hint_still_given() -> None:
    async with await s5lansim.start(header_byte_order="big") as sim:
        exc = await failure_of(f"s5lan://{hostport(sim)}?{FAST}", read("DB10.DW0"))
    assert type(exc) is PlcErrorResponse
    assert "try the option header_byte_order=big" in exc.message


# -- FETCH/WRITE: MK header expected but not sent, or sent but not expected ---------------------


async def test_raw_client_against_tani_module() -> None:
    async with await fwsim.start(mk=True) as sim:
        exc = await failure_of(f"fetchwrite://{hostport(sim)}?{FAST}", read("DB10.DW0"))
    assert type(exc) is ConnectionLost
    hint = hint_of(exc)
    assert "MK header switched on" in hint and "try ?mk=1" in hint


async def test_mk_client_against_plain_cp() -> None:
    async with await fwsim.start(mk=False) as sim:
        exc = await failure_of(f"fetchwrite://{hostport(sim)}?mk=1&{FAST}", read("DB10.DW0"))
    assert type(exc) is ConnectionLost
    assert "try without ?mk=1" in hint_of(exc)


async def test_raw_client_against_peer_that_answers_with_mk() -> None:
    """A Tani module that answers (instead of closing) shows its header: named exactly."""
    answer = H("4D 4B 10 00 00 00 00 00 53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00")
    async with fake_peer(answer) as hp:
        exc = await failure_of(f"fetchwrite://{hp}?{FAST}", read("DB10.DW0"))
    assert type(exc) is RemoteProtocolError
    hint = hint_of(exc)
    assert "(4D 4B 10 00 00 00 00 00 …)" in hint and "try ?mk=1" in hint


async def test_mk_client_against_peer_that_answers_plain_s5() -> None:
    answer = H("53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00")
    async with fake_peer(answer) as hp:
        exc = await failure_of(f"fetchwrite://{hp}?mk=1&{FAST}", read("DB10.DW0"))
    assert type(exc) is RemoteProtocolError
    assert "plain 'S5' FETCH/WRITE header" in hint_of(exc)


async def test_fetchwrite_client_against_e71_ascii() -> None:
    async with await e71sim.start(code="ascii") as sim:
        exc = await failure_of(f"fetchwrite://{hostport(sim)}?{FAST}", read("DB10.DW0"))
    assert type(exc) is PlcTimeout
    assert "MELSEC E71 in ASCII mode" in hint_of(exc)


# -- AS511 over TCP: is it a serial device server? --------------------------------------------


async def test_as511_tcp_against_e71_port() -> None:
    async with await e71sim.start() as sim:
        exc = await failure_of(f"as511+tcp://{hostport(sim)}?{FAST}", read("DB10.DW0"))
    assert type(exc) is PlcTimeout
    assert "serial device server in raw TCP mode" in hint_of(exc)


async def test_as511_tcp_against_tani_module_that_closes() -> None:
    async with await fwsim.start(mk=True) as sim:
        exc = await failure_of(f"as511+tcp://{hostport(sim)}?{FAST}", read("DB10.DW0"))
    assert type(exc) is ConnectionLost
    assert "probably not one" in hint_of(exc)


async def test_as511_tcp_against_s5lan_answering_peer() -> None:
    answer = H("35 00 00 00 1A 52 57 44 0A 00 05 00 14 00 00 00 68 00 11 22 33 44 00 00 00 00")
    async with fake_peer(answer) as hp:
        exc = await failure_of(f"as511+tcp://{hp}?{FAST}", read("DB10.DW0"))
    assert isinstance(exc, (PlcTimeout, RemoteProtocolError))
    assert "S5-LAN-LINK module (s5lan://)" in hint_of(exc)


async def test_as511_device_server_with_wrong_line_settings() -> None:
    """What a device server delivers when its baud rate or parity does not match the PLC:
    bytes, but never a control character."""
    async with fake_peer(H("FE 7F 80 E0 F8")) as hp:
        exc = await failure_of(f"as511+tcp://{hp}?{FAST}", read("DB10.DW0"))
    assert isinstance(exc, (PlcTimeout, RemoteProtocolError))
    hint = hint_of(exc)
    assert "none is an AS511 control character" in hint and "9600 baud, 8E1" in hint


# -- garbage gets no misleading hint ----------------------------------------------------------

GARBAGE = [b"\x00\x01\x02\x03garbage!", b"HTTP/1.0 400 Bad Request\r\n\r\n"]
CLIENT_URLS = [
    ("e71+tcp://{hp}?" + FAST, "D100"),
    ("e71+tcp://{hp}?code=ascii&" + FAST, "D100"),
    ("s5lan://{hp}?" + FAST, "DB10.DW0"),
    ("fetchwrite://{hp}?" + FAST, "DB10.DW0"),
    ("fetchwrite://{hp}?mk=1&" + FAST, "DB10.DW0"),
]


@pytest.mark.parametrize("garbage", GARBAGE, ids=["binary", "http"])
@pytest.mark.parametrize(("url", "address"), CLIENT_URLS, ids=[u[0][:12] for u in CLIENT_URLS])
async def test_garbage_reply_gets_no_hint(garbage: bytes, url: str, address: str) -> None:
    async with fake_peer(garbage) as hp:
        exc = await failure_of(url.format(hp=hp), read(address))
    assert isinstance(exc, (RemoteProtocolError, PlcTimeout))
    assert "Hint:" not in exc.message, exc.message


async def test_garbage_with_control_characters_gets_no_as511_hint() -> None:
    async with fake_peer(b"\x02\x10garbage") as hp:
        exc = await failure_of(f"as511+tcp://{hp}?{FAST}", read("DB10.DW0"))
    assert isinstance(exc, (RemoteProtocolError, PlcTimeout))
    assert "Hint:" not in exc.message, exc.message


async def test_matching_settings_still_work() -> None:
    async with (
        await e71sim.start(code="ascii") as sim,
        connect(f"e71+tcp://{hostport(sim)}?code=ascii") as plc,
    ):
        assert await plc.read("D100", 2) == [0, 0]
    async with (
        await fwsim.start(mk=True) as fw,
        connect(f"fetchwrite://{hostport(fw)}?mk=1") as plc,
    ):
        assert len(await plc.read("DB10.DW0", 2)) == 2


@asynccontextmanager
async def garbage_line(answer: bytes) -> AsyncIterator[str]:
    """A real pty pair whose far end answers every byte with ``answer``: what a PG receives
    when the serial line's baud rate or parity does not match the PLC. Yields the port path."""
    import os
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    loop = asyncio.get_running_loop()

    def readable() -> None:
        try:
            if os.read(master, 4096):
                os.write(master, answer)
        except OSError:
            pass  # EIO while the PG has the port closed

    loop.add_reader(master, readable)
    try:
        yield os.ttyname(slave)
    finally:
        loop.remove_reader(master)
        os.close(master)
        os.close(slave)


async def test_as511_serial_line_with_wrong_settings() -> None:
    async with garbage_line(H("FE 7F 80 E0 F8")) as path:
        exc = await failure_of(f"as511://{path}?{FAST}", read("DB10.DW0"))
    assert isinstance(exc, (PlcTimeout, RemoteProtocolError))
    hint = hint_of(exc)
    assert "line settings of the serial port" in hint and "?baud=, ?parity=" in hint


async def test_as511_serial_line_silent_gets_no_guess() -> None:
    """A silent serial line is already explained by the AS511 timeout message (cable, power,
    port); the bytes support no setting to name."""
    async with garbage_line(b"") as path:
        exc = await failure_of(f"as511://{path}?{FAST}", read("DB10.DW0"))
    assert type(exc) is PlcTimeout
    assert "Hint:" not in exc.message


async def test_a_failing_diagnosis_never_replaces_the_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from plcstack.clients.fetchwrite import FetchWriteClient

    def broken(self: object, failure: object, reply: bytes) -> str:
        raise ValueError("bug in a hint")

    monkeypatch.setattr(FetchWriteClient, "diagnose", broken)
    async with await fwsim.start(mk=True) as sim:
        exc = await failure_of(f"fetchwrite://{hostport(sim)}?{FAST}", read("DB10.DW0"))
    assert type(exc) is ConnectionLost
    assert "Hint:" not in exc.message


async def test_cli_prints_the_hint_on_its_one_error_line() -> None:
    import subprocess
    import sys

    async with await e71sim.start(code="ascii") as sim:
        url = f"e71+tcp://{hostport(sim)}?{FAST}"
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "read", url, "D100", "2", stderr=subprocess.PIPE
        )
        _, err = await proc.communicate()
    assert proc.returncode == 1
    lines = err.decode().strip().splitlines()
    assert len(lines) == 1 and lines[0].endswith("try ?code=ascii"), lines


async def test_no_wrong_port_hint_once_the_port_has_answered() -> None:
    """A PLC that answered and then closes a fresh connection on its first request (it restarts,
    a link drops) is no wrong port: seen in a soak, "this port is probably not an E71" on PLCs
    that had answered thousands of requests."""
    async with await e71sim.start() as sim:
        connections = 0

        async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            nonlocal connections
            connections += 1
            if connections > 1:  # a fresh connection: the first request, then the close
                await reader.read(4096)
                writer.transport.abort()
                return
            up_reader, up_writer = await asyncio.open_connection(sim.host, sim.port)
            try:
                while data := await reader.read(4096):
                    up_writer.write(data)
                    writer.write(await up_reader.read(4096))
            finally:
                up_writer.transport.abort()
                writer.transport.abort()

        server = await asyncio.start_server(ends_quietly(handle), "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        try:
            async with connect(f"e71+tcp://127.0.0.1:{port}?{FAST}") as plc:
                assert await plc.read("D0", 2) == [0, 0]
                plc.drop()  # the next request reconnects
                with pytest.raises(ConnectionLost) as info:
                    await plc.read("D0", 2)
        finally:
            server.close()
            await server.wait_closed()
    assert "Hint" not in info.value.message, info.value.message
