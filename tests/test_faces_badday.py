"""The native faces on a bad day, each face against its PLC: an area the PLC lacks, a write
outside the allow-list, the PLC going offline mid-request, a client going away mid-request, a
malformed frame. Each is answered with the protocol's own code (byte for byte what the PLC or
its simulator answers where it has an answer of its own), told to the write record, and
leaves the PLC's connection and the poll working."""

from __future__ import annotations

import asyncio

import pytest

from plcstack.codecs import fetchwrite as fw_codec
from plcstack.codecs import s5lan as lan_codec
from plcstack.codecs.e71 import (
    Code,
    Device,
    E71ClientConnection,
    MonitorWords,
    ReadWords,
    RegisterMonitorWords,
    WriteBits,
    WriteWords,
)
from plcstack.codecs.e71_devices import DeviceRef
from plcstack.gateway import e71server
from plcstack.gateway.allow import DeviceAllowList
from plcstack.sim import as511 as as511_sim
from plcstack.sim import e71 as e71_sim
from plcstack.sim import s5lan as lan_sim
from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.sim.s5memory import Area
from tests.aio_helpers import eventually
from tests.faces_helpers import RawDatagrams, RawStream, e71_faces, polled, s5_faces


async def _bytes_for(host: str, port: int, frame: bytes) -> tuple[bytes, bool]:
    """Send ``frame`` on a connection of its own: the answer (what came until 0.1 s passed
    without a byte, at most 5 s in all), and whether the peer closed the connection."""
    reader, writer = await asyncio.open_connection(host, port)
    got = b""
    closed = False
    try:
        writer.write(frame)
        async with asyncio.timeout(5):
            got = await reader.read(65536)  # the first bytes, or b"" for a close
        closed = not got
        while not closed:
            try:
                async with asyncio.timeout(0.1):
                    chunk = await reader.read(65536)
            except TimeoutError:
                break
            got += chunk
            closed = not chunk
    finally:
        writer.close()
        await asyncio.gather(writer.wait_closed(), return_exceptions=True)
    return got, closed


# -- an area the PLC lacks -----------------------------------------------------------------------


async def test_s5_areas_the_plc_lacks_get_each_protocols_own_code() -> None:
    module = await lan_sim.start()  # DB1..DB10, 256 words each
    twin = await lan_sim.start(module.memory, max_connections=8)
    async with (
        module,
        twin,
        polled(module.url, 'v = "DB1.DW0"') as poller,
        s5_faces(poller) as (
            lan,
            fw,
            _,
            _,
        ),
    ):
        face = await RawStream.open(lan.host, lan.port, lan_codec.ClientConnection())
        direct = await RawStream.open(twin.host, twin.port, lan_codec.ClientConnection())
        try:
            for request in (
                lan_codec.Request.read("D", "W", 0, 1, db=99),  # no DB99: Err 2
                lan_codec.Request.read("D", "W", 250, 10, db=1),  # beyond DB1's end: Err 3
                lan_codec.Request.read("M", "B", 250, 10),  # beyond the flags: Err 3
            ):
                answer, raw = await face.ask(request)
                _, expected = await direct.ask(request)
                assert answer.err in (2, 3) and raw == expected
        finally:
            await face.aclose()
            await direct.aclose()
        # FETCH/WRITE asks for what no S5-LAN module has: answered "does not exist"
        fetch = RawStream.open(fw.host, fw.port, fw_codec.ClientConnection())
        stream = await fetch
        try:
            for org in (fw_codec.Org.AS, fw_codec.Org.BS):
                answer, _ = await stream.ask(fw_codec.FetchRequest(org, 0, 0, 4))
                assert answer.error == 0x02
            answer, _ = await stream.ask(fw_codec.FetchRequest(fw_codec.Org.DB, 99, 0, 4))
            assert answer.error == 0x02
        finally:
            await stream.aclose()
        assert poller.stats["kiln1"].bad_samples == 0


async def test_e71_devices_the_cpu_lacks_are_answered_with_its_end_codes() -> None:
    memory = MelsecMemory("I")  # an A1S: no file registers R, D0-D1023
    plc = await e71_sim.start(memory)
    twin = await e71_sim.start(memory, transport="udp")
    async with plc, twin, polled(plc.url, 'd = "D0"') as poller, e71_faces(poller) as faces:
        face = faces[0][("tcp", Code.BINARY)]
        mine = await RawStream.open(face.host, face.port, E71ClientConnection())
        direct = await RawDatagrams.open(twin.host, twin.port, E71ClientConnection(transport="udp"))
        try:
            for request in (
                ReadWords(DeviceRef(Device.R, 0), 4),  # no R on group I: 58H
                ReadWords(DeviceRef(Device.D, 2000), 4),  # beyond D1023: 58H
                ReadWords(DeviceRef(Device.D, 1020), 10),  # runs past the end: 57H
            ):
                answer, raw = await mine.ask(request)
                _, expected = await direct.ask(request)
                assert raw == expected and answer.end_code in (0x57, 0x58), answer
        finally:
            await mine.aclose()
            await direct.aclose()


# -- writes outside the allow-list ---------------------------------------------------------------


async def test_writes_outside_the_allow_list_never_reach_the_plc() -> None:
    module = await lan_sim.start()
    async with (
        module,
        polled(module.url, 'v = "DB1.DW0"') as poller,
        s5_faces(poller, writable="DB5") as (lan, fw, store, writes),
    ):
        lan_stream = await RawStream.open(lan.host, lan.port, lan_codec.ClientConnection())
        fw_stream = await RawStream.open(fw.host, fw.port, fw_codec.ClientConnection())
        try:
            refused, _ = await lan_stream.ask(
                lan_codec.Request.write("D", "W", 0, b"\x01\x00", db=6)
            )
            assert refused.err == 6
            refused_fw, _ = await fw_stream.ask(
                fw_codec.WriteRequest.of(fw_codec.Org.MB, 0, 0, b"\x01")
            )
            assert refused_fw.error == 0x01
            allowed, _ = await lan_stream.ask(
                lan_codec.Request.write("D", "W", 0, b"\x34\x12", db=5)
            )
            assert allowed.err == 0
        finally:
            await lan_stream.aclose()
            await fw_stream.aclose()
        assert module.memory.read_db_words(6, 0, 1) == [0]
        assert module.memory.read_area(Area.FLAGS, 0, 1) == b"\x00"
        assert module.memory.read_db_words(5, 0, 1) == [0x1234]
        assert [(w.address, w.result, w.may_have_executed) for w in writes] == [
            ("DB6+0", "write_denied", False),
            ("M+0", "write_denied", False),
            ("DB5+0", "ok", True),
        ]
        assert all(w.peer and w.peer.startswith("127.0.0.1:") for w in writes)
        assert store.stats.denied == 2 and store.stats.line_writes == 1


async def test_e71_writes_outside_the_allow_list_are_55h_and_the_audit_has_the_value_before() -> (
    None
):
    memory = MelsecMemory()
    memory.write_words(Device.D, 100, [7, 8])
    plc = await e71_sim.start(memory)
    async with (
        plc,
        polled(plc.url, 'd = "D0"', interval=30.0) as poller,  # one scan, at the start
        e71_faces(poller, writable="D100-101", read_previous=True) as (faces, executor, writes),
    ):
        face = faces[("tcp", Code.ASCII)]
        mine = await RawStream.open(face.host, face.port, E71ClientConnection(Code.ASCII))
        await eventually(lambda: poller.stats["kiln1"].requests == 1, "the first scan")
        try:
            requests = plc.requests  # the requests the E71 received: none more for refusals
            denied, _ = await mine.ask(WriteWords(DeviceRef(Device.D, 101), (1, 2)))  # D102 not
            bits, _ = await mine.ask(WriteBits(DeviceRef(Device.Y, 0), (True,)))
            assert denied.end_code == bits.end_code == 0x55
            assert plc.requests == requests and memory.read_words(Device.D, 101, 2) == [8, 0]
            done, _ = await mine.ask(WriteWords(DeviceRef(Device.D, 100), (70, 80)))
            assert done.command == 0x03 and not hasattr(done, "end_code")
        finally:
            await mine.aclose()
        assert memory.read_words(Device.D, 100, 2) == [70, 80]
        assert [(w.address, w.value, w.previous, w.result) for w in writes] == [
            ("D101", [1, 2], None, "write_denied"),
            ("Y0", [True], None, "write_denied"),
            ("D100", [70, 80], [7, 8], "ok"),
        ]
        assert executor.counts["denied"] == 2


# -- the PLC going offline mid-request -----------------------------------------------------------


async def test_an_e71_going_silent_mid_request_is_60h_and_said_may_have_executed() -> None:
    plc = await e71_sim.start()
    assert isinstance(plc, e71_sim.E71TcpSimulator)
    async with (
        plc,
        polled(plc.url, 'd = "D0"', interval=0.5, timeout=0.3) as poller,
        e71_faces(poller, writable="D") as (faces, _, writes),
    ):
        face = faces[("udp", Code.BINARY)]
        mine = await RawDatagrams.open(face.host, face.port, E71ClientConnection(transport="udp"))
        try:
            plc.mute = True  # the E71 takes the request and never answers
            answer, _ = await mine.ask(WriteWords(DeviceRef(Device.D, 5), (5,)))
            assert answer.end_code == 0x60
            plc.mute = False
            for _ in range(50):  # the connection comes back (after the client's backoff)
                answer, _ = await mine.ask(ReadWords(DeviceRef(Device.D, 5), 1))
                if not hasattr(answer, "end_code"):
                    break
                assert answer.end_code == 0x60
                await asyncio.sleep(0.05)
            assert answer.values == (0,)  # the muted E71 did not execute it
        finally:
            await mine.aclose()
        (write,) = writes
        assert write.result == "plc_timeout" and write.may_have_executed


async def test_s5_plcs_going_offline_mid_request_get_each_protocols_timeout_code() -> None:
    line = await as511_sim.start()
    async with (
        line,
        polled(
            f"{line.url}?char_timeout=0.2", 'v = "DB3.DW0"', interval=5.0, timeout=0.5
        ) as poller,
        s5_faces(poller, writable="DB5") as (lan, fw, _store, writes),
    ):
        line.machine.mute = True  # the cable is pulled
        lan_stream = await RawStream.open(lan.host, lan.port, lan_codec.ClientConnection())
        fw_stream = await RawStream.open(fw.host, fw.port, fw_codec.ClientConnection())
        try:
            read, _ = await lan_stream.ask(lan_codec.Request.read("D", "W", 0, 4, db=3))
            assert read.err == 9
            write, _ = await fw_stream.ask(
                fw_codec.WriteRequest.of(fw_codec.Org.DB, 5, 0, b"\x12\x34")
            )
            assert write.error == 0x04
            line.machine.mute = False
            for _ in range(50):
                again, _ = await fw_stream.ask(fw_codec.FetchRequest(fw_codec.Org.DB, 3, 0, 1))
                if again.error == 0:
                    break
                await asyncio.sleep(0.05)
            assert again.data == b"\x03\x00"
        finally:
            await lan_stream.aclose()
            await fw_stream.aclose()
        assert writes[0].result == "plc_timeout"
        assert writes[0].may_have_executed  # sent on the line, never confirmed


# -- a client going away mid-request -------------------------------------------------------------


async def test_a_write_of_an_s5_client_that_went_away_while_it_waited_is_never_sent() -> None:
    module = await lan_sim.start()
    async with (
        module,
        polled(module.url, 'v = "DB1.DW0"') as poller,
        s5_faces(poller, writable="DB5") as (lan, fw, store, writes),
    ):
        client = poller.client("kiln1")
        for host, port, frame in (
            (lan.host, lan.port, lan_codec.ClientConnection().send(
                lan_codec.Request.write("D", "W", 1, b"\x11\x11", db=5))),
            (fw.host, fw.port, fw_codec.encode_request(
                fw_codec.WriteRequest.of(fw_codec.Org.DB, 5, 2, b"\x22\x22"))),
        ):  # fmt: skip
            async with client.turn():  # a long request of someone else's on the connection
                _reader, writer = await asyncio.open_connection(host, port)
                writer.write(frame)
                await eventually(lambda: store.stats.writes == 1, "the write at the store")
                await asyncio.sleep(0.05)
                writer.transport.abort()  # the client is gone before its turn
                await eventually(lambda: len(writes) == 1, "write given up")
            assert [(w.result, w.may_have_executed) for w in writes] == [("cancelled", False)]
            writes.clear()
            store.stats.writes = 0
        await asyncio.sleep(0.1)  # the turn passed: anything queued would have run by now
        assert module.memory.read_db_words(5, 1, 2) == [0, 0]
        assert poller.stats["kiln1"].bad_samples == 0


async def test_an_e71_client_gone_mid_request_sends_nothing_queued_and_completes_what_ran() -> None:
    memory = MelsecMemory()
    plc = await e71_sim.start(memory)
    assert isinstance(plc, e71_sim.E71TcpSimulator)
    async with (
        plc,
        polled(plc.url, 'd = "D0"') as poller,
        e71_faces(poller, writable="D") as (
            faces,
            _,
            writes,
        ),
    ):
        face = faces[("tcp", Code.BINARY)]
        assert isinstance(face, e71server.E71TcpFace)
        client = poller.client("kiln1")
        frame = E71ClientConnection().send(WriteWords(DeviceRef(Device.D, 300), (3,)))
        async with client.turn():
            _reader, writer = await asyncio.open_connection(face.host, face.port)
            writer.write(frame)
            await eventually(lambda: face.requests == 1, "the write at the face")
            await asyncio.sleep(0.05)
            writer.transport.abort()
            await eventually(lambda: [w.result for w in writes] == ["cancelled"], "given up")
        assert not writes[0].may_have_executed
        # gone after it was sent: the write completes, and the record says so
        plc.delay = 0.3  # the E71 executes at once and answers 0.3 s later
        _reader, writer = await asyncio.open_connection(face.host, face.port)
        writer.write(E71ClientConnection().send(WriteWords(DeviceRef(Device.D, 301), (4,))))
        await eventually(lambda: memory.read_words(Device.D, 301, 1) == [4], "D301 written")
        writer.transport.abort()
        await eventually(lambda: writes[-1].address == "D301", "recorded")
        assert writes[-1].result == "ok"
        assert memory.read_words(Device.D, 300, 1) == [0]


# -- malformed frames ----------------------------------------------------------------------------


async def test_malformed_frames_are_answered_as_the_plcs_own_servers_answer_them() -> None:
    memory = MelsecMemory()
    plc = await e71_sim.start(memory)
    twins = {
        (t, c): await e71_sim.start(memory, transport=t, code=c)
        for t in ("tcp", "udp")
        for c in Code
    }
    async with plc, polled(plc.url, 'd = "D0"') as poller, e71_faces(poller) as (faces, _, _):
        frames = {
            Code.BINARY: [
                b"\x65\xff\x0a\x00",
                b"\x01\xff\x0a\x00" + b"\x00\x00\x00\x00\x20\x44" + b"\x00\x00",
            ],
            Code.ASCII: [b"ZZFF000A", b"01FF000A4420000000000000", b"01ff000a44200000000001000"],
        }
        for (transport, code), face in faces.items():
            twin = twins[transport, code]
            for frame in frames[code]:
                if transport == "tcp":
                    got, _ = await _bytes_for(face.host, face.port, frame)
                    expected, _ = await _bytes_for(twin.host, twin.port, frame)
                else:
                    got = await _datagram(face.host, face.port, frame)
                    expected = await _datagram(twin.host, twin.port, frame)
                assert got == expected and got, (transport, code, frame)
        for twin in twins.values():
            await twin.aclose()
    # S5-LAN: a wrong header is Err 6 and the connection closed; FETCH/WRITE: closed unanswered
    module = await lan_sim.start()
    twin_lan = await lan_sim.start(module.memory, max_connections=4)
    async with (
        module,
        twin_lan,
        polled(module.url, 'v = "DB1.DW0"') as poller,
        s5_faces(poller) as (
            lan,
            fw,
            _,
            _,
        ),
    ):
        bad_header = bytes([0x35, 0, 0, 0, 0x1B]) + bytes(21)  # HdLen 27
        got, closed = await _bytes_for(lan.host, lan.port, bad_header)
        expected, _ = await _bytes_for(twin_lan.host, twin_lan.port, bad_header)
        assert got == expected and closed and got[14] == 6
        got, closed = await _bytes_for(fw.host, fw.port, b"XX" + bytes(14))
        assert got == b"" and closed
        assert poller.stats["kiln1"].bad_samples == 0


async def _datagram(host: str, port: int, frame: bytes) -> bytes:
    stream = await RawDatagrams.open(host, port, E71ClientConnection(transport="udp"))
    try:
        stream.transport.sendto(frame)
        async with asyncio.timeout(5):
            return await stream.queue.get()
    finally:
        await stream.aclose()


# -- monitoring, per client ----------------------------------------------------------------------


async def test_each_client_monitors_what_it_registered() -> None:
    memory = MelsecMemory()
    memory.write_words(Device.D, 0, list(range(100, 140)))
    plc = await e71_sim.start(memory)
    async with plc, polled(plc.url, 'd = "D0"') as poller, e71_faces(poller) as (faces, _, _):
        streams = [
            await RawStream.open(face.host, face.port, E71ClientConnection(code))
            for (transport, code), face in faces.items()
            if transport == "tcp"
        ]
        a, b = streams
        face = faces[("tcp", Code.BINARY)]
        try:
            unregistered, _ = await _bytes_for(face.host, face.port, b"\x09\xff\x0a\x00")
            assert unregistered == b"\x89\x57"  # nothing registered yet: as the E71 answers
            for stream, points in ((a, (1, 5, 9)), (b, (20, 30))):
                refs = tuple(DeviceRef(Device.D, p) for p in points)
                ack, _ = await stream.ask(RegisterMonitorWords(refs))
                assert ack.command == 0x07
            for _ in range(3):
                answer_a, _ = await a.ask(MonitorWords())
                answer_b, _ = await b.ask(MonitorWords())
                assert answer_a.values == (101, 105, 109) and answer_b.values == (120, 130)
        finally:
            for stream in streams:
                await stream.aclose()


def test_allow_list_of_devices() -> None:
    allow = DeviceAllowList.parse("D100-199, y0-1F, M, W10-W1F")
    assert allow.allows(Device.D, 100, 100) and not allow.allows(Device.D, 150, 51)
    assert allow.allows(Device.Y, 0x10, 16) and not allow.allows(Device.Y, 0x20)
    assert allow.allows(Device.M, 8000) and allow.allows(Device.W, 0x1F)
    assert not allow.allows(Device.X, 0)
    assert str(allow) == "D100-D199, Y0-Y1F, M, W10-W1F"
    assert str(DeviceAllowList.parse("")) == "nothing"
    for bad in ("D200-100", "DB10", "Q1"):
        with pytest.raises(Exception, match="writable"):
            DeviceAllowList.parse(bad)
