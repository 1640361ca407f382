"""The E71 face in front of an E71, sharing its connection with the poller: more clients than
the E71's eight connections, binary and ASCII, TCP and UDP, each answer byte for byte what the
E71 itself answers in that code; monitoring per client, the allow-list, a dead PLC, a client
that goes away, malformed frames."""

from __future__ import annotations

import asyncio

from plcstack.codecs.e71 import (
    Code,
    Device,
    E71ClientConnection,
    ReadBits,
    ReadWords,
    WriteWords,
)
from plcstack.codecs.e71_devices import DeviceRef
from plcstack.gateway import e71server
from plcstack.sim import e71 as e71_sim
from plcstack.sim.melsec_memory import MelsecMemory
from tests.faces_helpers import KINDS, RawDatagrams, RawStream, Transport, e71_faces, polled


def _patterned() -> MelsecMemory:
    memory = MelsecMemory()
    memory.write_words(Device.D, 0, [(0x1100 + i) & 0xFFFF for i in range(512)])
    memory.write_bits(Device.M, 0, [i % 3 == 0 for i in range(512)])
    memory.write_bits(Device.X, 0, [i % 5 == 0 for i in range(256)])
    return memory


async def _raw(transport: Transport, code: Code, host: str, port: int) -> RawStream | RawDatagrams:
    codec = E71ClientConnection(code, transport=transport)
    if transport == "tcp":
        return await RawStream.open(host, port, codec)
    return await RawDatagrams.open(host, port, codec)


async def test_twelve_clients_of_every_kind_share_the_e71_s_one_connection_with_the_poll() -> None:
    memory = _patterned()
    plc = await e71_sim.start(memory)  # binary, TCP: at most 8 connections
    # the same CPU asked directly in each code (UDP: no connection limit for the comparison)
    twins = {code: await e71_sim.start(memory, code=code, transport="udp") for code in Code}
    assert isinstance(plc, e71_sim.E71TcpSimulator)
    async with plc, twins[Code.BINARY], twins[Code.ASCII]:
        tags = 'd = { address = "D0", count = 8 }'
        async with (
            polled(plc.url, tags) as poller,
            e71_faces(poller, writable="D1000-1099") as (
                faces,
                executor,
                writes,
            ),
        ):

            async def client(k: int) -> None:
                transport, code = KINDS[k % 4]
                face = faces[transport, code]
                mine = await _raw(transport, code, face.host, face.port)
                twin = twins[code]
                direct = await _raw("udp", code, twin.host, twin.port)
                try:
                    for i in range(6):
                        requests = (
                            ReadWords(DeviceRef(Device.D, 10 * k), 16),
                            ReadBits(DeviceRef(Device.M, 16 * k + i), 13),
                            ReadWords(DeviceRef(Device.X, 16 * i), 2),  # 32 inputs as 2 words
                            WriteWords(DeviceRef(Device.D, 1000 + k), ((k << 8) | i,)),
                        )
                        for request in requests:
                            answer, raw = await mine.ask(request)
                            _, expected = await direct.ask(request)
                            assert raw == expected, (k, i, request, answer)
                finally:
                    await mine.aclose()
                    await direct.aclose()

            await asyncio.gather(*(client(k) for k in range(12)))
            assert memory.read_words(Device.D, 1000, 12) == [(k << 8) | 5 for k in range(12)]
            assert len(writes) == 72 and all(w.ok for w in writes)
            assert executor.counts["ok"] == 12 * 6 * 4
            assert poller.stats["kiln1"].bad_samples == 0
            for face in faces.values():
                if isinstance(face, e71server.E71TcpFace):
                    assert face.refused_connections == 0
        assert plc.connection_count.peak == 1 and plc.refused_connections == 0
