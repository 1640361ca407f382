"""The S5 faces (S5-LAN-LINK, FETCH/WRITE) in front of any S5 PLC, sharing its one connection
with the poller: many network clients through one S5-LAN module that takes one connection,
through an AS511 line, through a FETCH/WRITE CP; each answer byte for byte what the PLC itself
answers; the poll goes on meanwhile."""

from __future__ import annotations

import asyncio
import struct

import pytest

from plcstack.clients import connect
from plcstack.codecs import fetchwrite as fw_codec
from plcstack.codecs import s5lan as lan_codec
from plcstack.codecs.mk import MkConnection
from plcstack.errors import AddressError, PlcErrorResponse
from plcstack.gateway.faces import FaceSettings, PlcFaces
from plcstack.poll.engine import Poller, Quality
from plcstack.sim import as511 as as511_sim
from plcstack.sim import fetchwrite as fw_sim
from plcstack.sim import s5lan as lan_sim
from plcstack.sim.s5memory import S5Memory
from tests.aio_helpers import eventually
from tests.faces_helpers import RawStream, polled, s5_faces


def _patterned(memory: S5Memory) -> S5Memory:
    for db in range(1, 11):
        memory.write_db_words(db, 0, [(db << 8) | (i & 0xFF) for i in range(256)])
    return memory


def _good_scans(poller: Poller) -> int:
    stats = poller.stats["kiln1"]
    return stats.samples - stats.bad_samples


async def test_twenty_s5lan_clients_share_the_one_connection_of_an_s5lan_module() -> None:
    memory = _patterned(lan_sim.default_memory())
    module = await lan_sim.start(memory)  # one connection, as the hardware
    twin = await lan_sim.start(memory, max_connections=32)  # the same CPU, asked directly
    async with module, twin:
        tags = 'temp = "DB1.DW0"\nrow = { address = "DB2.DW0", count = 16 }'
        async with polled(module.url, tags) as poller, s5_faces(poller, writable="DB10") as faces:
            lan, _, store, writes = faces
            before = _good_scans(poller)

            async def client(k: int) -> None:
                face = await RawStream.open(lan.host, lan.port, lan_codec.ClientConnection())
                direct = await RawStream.open(twin.host, twin.port, lan_codec.ClientConnection())
                try:
                    for i in range(8):
                        code = bytes([k, i, 0x5A, 0xA5])
                        read = lan_codec.Request.read(
                            "D", "W", k, 32, db=1 + (k + i) % 9, user_code=code
                        )
                        flag = lan_codec.Request.read("M", "B", k, 7, user_code=code)
                        value = struct.pack("<H", (k << 8) | i)  # low byte first on the wire
                        write = lan_codec.Request.write("D", "W", 100 + k, value, db=10)
                        for request in (read, flag, write):
                            answer, raw = await face.ask(request)
                            assert answer.err == 0
                            _, expected = await direct.ask(request)
                            assert raw == expected, (k, i, request)
                finally:
                    await face.aclose()
                    await direct.aclose()

            await asyncio.gather(*(client(k) for k in range(20)))
            assert memory.read_db_words(10, 100, 20) == [(k << 8) | 7 for k in range(20)]
            assert store.stats.busy == store.stats.expired == store.stats.failed == 0
            assert len(writes) == 160 and all(w.ok for w in writes)
            # the poll went on meanwhile, every sample good
            await eventually(lambda: _good_scans(poller) >= before + 20, "20 more good samples")
            assert poller.stats["kiln1"].bad_samples == 0
        assert module.connection_count.peak == 1 and module.refused_connections == 0
        assert lan.refused_connections == 0


async def test_fetchwrite_clients_with_mk_through_an_as511_line() -> None:
    async with await as511_sim.start() as line:
        memory = line.machine.memory
        twin = await fw_sim.start(memory, mk=True, max_connections=32)
        async with twin:
            async with (
                polled(line.url, 'level = "DB3.DW0"', interval=0.05) as poller,
                s5_faces(poller, writable="DB5, M", mk=True) as faces,
            ):
                _, fw, store, writes = faces

                async def client(k: int) -> None:
                    face = await RawStream.open(fw.host, fw.port, _mk_client())
                    direct = await RawStream.open(twin.host, twin.port, _mk_client())
                    try:
                        for i in range(3):
                            requests = (
                                fw_codec.FetchRequest(fw_codec.Org.DB, 2 + k % 4, i, 16),
                                fw_codec.FetchRequest(fw_codec.Org.MB, 0, 10 * k, 4),
                                fw_codec.WriteRequest.of(
                                    fw_codec.Org.DB, 5, 10 + k, struct.pack(">H", 0x100 * k + i)
                                ),
                            )
                            for request in requests:
                                answer, raw = await face.ask(request)
                                assert answer.error == 0, (k, i, request, answer)
                                _, expected = await direct.ask(request)
                                assert raw == expected, (k, i, request)
                    finally:
                        await face.aclose()
                        await direct.aclose()

                await asyncio.gather(*(client(k) for k in range(8)))
                assert memory.read_db_words(5, 10, 8) == [0x100 * k + 2 for k in range(8)]
                assert len(writes) == 24 and all(w.ok for w in writes)
                assert store.stats.failed == 0
                assert poller.stats["kiln1"].bad_samples == 0
            assert line.connection_count.peak == 1


def _mk_client() -> fw_codec.ClientConnection:
    return fw_codec.ClientConnection("mk", mk=MkConnection())


async def test_values_reach_the_poller_and_faces_alike() -> None:
    """A write through a face is what the next scan reads: one PLC, one memory."""
    memory = _patterned(lan_sim.default_memory())
    async with (
        await lan_sim.start(memory) as module,
        polled(module.url, 'v = "DB10.DW7"') as poller,
        s5_faces(poller, writable="DB10") as faces,
    ):
        lan = faces[0]
        face = await RawStream.open(lan.host, lan.port, lan_codec.ClientConnection())
        try:
            answer, _ = await face.ask(
                lan_codec.Request.write("D", "W", 7, struct.pack("<H", 0xBEEF), db=10)
            )
            assert answer.err == 0
        finally:
            await face.aclose()
        async with asyncio.timeout(10):
            async for sample in poller:
                if sample.value == 0xBEEF:
                    assert sample.quality is Quality.GOOD
                    break


async def test_faces_of_one_plc_each_with_its_own_allow_list() -> None:
    memory = _patterned(lan_sim.default_memory())
    async with (
        await lan_sim.start(memory) as module,
        polled(module.url, 'v = "DB1.DW0"') as poller,
    ):
        faces = PlcFaces(
            "kiln1",
            poller.client("kiln1"),
            [
                FaceSettings("s5lan", "127.0.0.1", 0, "kiln1", writable="DB10"),
                FaceSettings("fetchwrite", "127.0.0.1", 0, "kiln1", mk=True),  # read-only
            ],
        )
        async with faces:
            lan, fw = faces.servers
            async with connect(lan.url) as a, connect(fw.url) as b:
                await a.write("DB10.DW1", [0x1111])
                with pytest.raises(PlcErrorResponse) as refused:
                    await b.write("DB10.DW2", [0x2222])
                assert refused.value.code == 0x01
                assert await b.read("DB10.DW1", 2) == [0x1111, 0x0A02]
        assert faces.servers == []
        assert memory.read_db_words(10, 1, 2) == [0x1111, 0x0A02]


def test_face_settings_are_checked_before_anything_listens() -> None:
    for bad, message in (
        (dict(protocol="modbus"), "a face speaks"),
        (dict(protocol="s5lan", mk=True), "FETCH/WRITE option"),
        (dict(protocol="s5lan", transport="udp"), "options of the e71 face"),
        (dict(protocol="s5lan", writable="D100"), "writable"),
        (dict(protocol="e71", writable="DB10"), "writable"),
        (dict(protocol="e71", max_connections=0), "at least 1"),
    ):
        with pytest.raises(AddressError, match=message):
            FaceSettings(**{"host": "127.0.0.1", "port": 0, "plc": "p", **bad})  # type: ignore[arg-type]
    assert FaceSettings("e71", "h", 1, "p", transport="udp", code="ascii").describe() == (
        "e71 face (udp, ascii) of p"
    )
