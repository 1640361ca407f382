"""The AS511 face: a PG reaches the S5 through plcstack on TCP while the poller polls it over
the S5's one programming-port connection; each transaction's answer is the AG's own, byte for
byte; writes and mode changes only as the allow-list says."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import pytest

from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.clients.share import SharedConnection
from plcstack.codecs.as511_jobs import (
    Job,
    b_info_job,
    block_list_job,
    operating_mode_job,
    read_job,
    system_parameters_job,
    write_job,
)
from plcstack.errors import PlcErrorResponse
from plcstack.gateway import as511face
from plcstack.gateway.allow import WriteAllowList
from plcstack.gateway.record import FaceWrite
from plcstack.poll.engine import Poller
from plcstack.sim import as511 as as511_sim
from tests.aio_helpers import eventually
from tests.faces_helpers import polled


@asynccontextmanager
async def as511_face(
    poller: Poller, *, writable: str = "", read_previous: bool = False
) -> AsyncIterator[tuple[as511face.As511Face, list[FaceWrite]]]:
    writes: list[FaceWrite] = []
    share = SharedConnection(poller.client("kiln1"), name="kiln1")
    executor = as511face.As511Executor(
        share,
        writable=WriteAllowList.parse(writable),
        on_write=writes.append,
        read_previous=read_previous,
    )
    async with share, await as511face.start(executor) as face:
        yield face, writes


def _pg(url: str, char_timeout: float = 0.5) -> AS511Client:
    """A PG's client of ``url``; ``char_timeout``: how long it waits for each character."""
    client = connect(url, nak_backoff=0.05, timeout=5.0, char_timeout=char_timeout)
    assert isinstance(client, AS511Client)
    return client


async def test_a_pg_through_the_face_gets_the_ags_own_answers_while_the_poll_goes_on() -> None:
    line = await as511_sim.start()
    twin = await as511_sim.start(line.memory)
    async with (
        line,
        twin,
        polled(line.url, 'v = "DB5.DW0"') as poller,
        as511_face(poller) as (face, _),
    ):
        before = poller.stats["kiln1"].samples
        async with _pg(face.url) as pg, _pg(twin.url) as direct:
            jobs: list[Job] = [
                system_parameters_job(),
                b_info_job(1, 5),
                read_job(0x1000, 200),
                block_list_job(1),
            ]
            for _ in range(3):
                for job in jobs:
                    assert await pg.transact(job, "test") == await direct.transact(job, "test")
            assert await pg.read("DB5.DW0", 64) == [0x0500 | k for k in range(64)]
        assert poller.stats["kiln1"].samples > before
        assert poller.stats["kiln1"].bad_samples == 0
    assert line.connection_count.peak == 1  # the poller's connection, nothing else


async def test_writes_and_mode_changes_only_as_writable_says() -> None:
    line = await as511_sim.start()
    memory = line.memory
    async with line, polled(line.url, 'v = "DB5.DW0"') as poller:
        async with as511_face(poller) as (face, writes), _pg(face.url) as pg:
            with pytest.raises(PlcErrorResponse):
                await pg.write("DB5.DW1", [0x1234])
            with pytest.raises(PlcErrorResponse):
                await pg.transact(operating_mode_job(0), "stop", is_write=True)
            assert memory.read_db_words(5, 1, 1) == [0x0501] and line.machine.running
            assert [w.result for w in writes] == ["write_denied", "write_denied"]
        async with (
            as511_face(poller, writable="AS", read_previous=True) as (face, writes),
            _pg(face.url) as pg,
        ):
            await pg.write("DB5.DW1", [0x1234])
            assert memory.read_db_words(5, 1, 1) == [0x1234]
            with pytest.raises(PlcErrorResponse):  # a mode change needs *
                await pg.transact(operating_mode_job(0), "stop", is_write=True)
            (write,) = [w for w in writes if w.result == "ok"]
            assert write.value == [0x12, 0x34] and write.previous == [0x05, 0x01]
        async with as511_face(poller, writable="*") as (face, _), _pg(face.url) as pg:
            await pg.transact(operating_mode_job(0), "stop", is_write=True)
            assert not line.machine.running


async def test_a_function_the_face_does_not_pass_on_and_a_second_pg_are_refused() -> None:
    line = await as511_sim.start()
    async with (
        line,
        polled(line.url, 'v = "DB5.DW0"') as poller,
        as511_face(poller) as (face, _),
        _pg(face.url) as pg,
    ):
        with pytest.raises(PlcErrorResponse):
            await pg.transact(Job(0x05, b"\x01\x05", True, None), "write block")
        assert await pg.read("DB5.DW2") == [0x0502]  # the line still works
        reader, writer = await asyncio.open_connection(face.host, face.port)
        async with asyncio.timeout(5):
            assert await reader.read(1) == b""  # turned away at once: one PG at a time
        writer.close()
        assert face.refused_connections == 1


# -- the AS511 face on a bad day ----------------------------------------------------------------


async def test_a_plc_going_offline_mid_transaction_is_a_nak_and_the_write_may_have_executed() -> (
    None
):
    line = await as511_sim.start()
    async with (
        line,
        polled(
            f"{line.url}?char_timeout=0.2", 'v = "DB5.DW0"', interval=5.0, timeout=0.5
        ) as poller,
        as511_face(poller, writable="AS") as (face, writes),
        _pg(face.url, char_timeout=3.0) as pg,  # longer than the PLC side takes to give up
    ):
        before = await pg.transact(read_job(0x1000, 2), "read")
        line.machine.mute = True  # the cable is pulled
        with pytest.raises(PlcErrorResponse):  # DLE NAK: the PG tries again, as after a busy AG
            await pg.transact(write_job(0x1000, b"\x12\x34"), "write", is_write=True)
        line.machine.mute = False
        for _ in range(50):  # the line comes back (after the poller's client backs off)
            try:
                after = await pg.transact(read_job(0x1000, 2), "read")
                break
            except PlcErrorResponse:
                await asyncio.sleep(0.05)
        else:
            pytest.fail("the line did not come back")
        assert after == before  # the muted AG executed nothing
        (write,) = writes
        assert write.result == "plc_timeout" and write.may_have_executed, write


async def test_a_pg_gone_while_its_write_waits_is_never_sent() -> None:
    line = await as511_sim.start()
    async with (
        line,
        polled(line.url, 'v = "DB5.DW0"') as poller,
        as511_face(poller, writable="AS") as (face, writes),
    ):
        async with _pg(face.url) as pg:
            before = await pg.transact(read_job(0x1000, 2), "read")
        client = poller.client("kiln1")
        async with client.turn():  # a long request of someone else's on the connection
            pg = _pg(face.url, char_timeout=3.0)
            job = write_job(0x1000, b"\x12\x34")
            write = asyncio.ensure_future(pg.transact(job, "write", is_write=True))
            await eventually(lambda: face.executor.transactions >= 1, "the write at the face")
            await asyncio.sleep(0.1)
            write.cancel()  # the PG gives up and goes
            await asyncio.gather(write, return_exceptions=True)
            await pg.aclose()
            await eventually(lambda: len(writes) == 1, "the write given up")
        await asyncio.sleep(0.1)  # the turn passed: anything queued would have run by now
        assert [(w.result, w.may_have_executed) for w in writes] == [("cancelled", False)]
        async with _pg(face.url) as pg:
            assert await pg.transact(read_job(0x1000, 2), "read") == before


async def test_bytes_that_are_no_transaction_are_answered_as_the_ag_answers_them() -> None:
    line = await as511_sim.start()
    twin = await as511_sim.start(line.memory)
    async with line, twin, polled(line.url, 'v = "DB5.DW0"') as poller:
        async with as511_face(poller) as (face, _):
            answers = []
            # noise the AG ignores; an STX it acknowledges and a transaction it refuses (NAK)
            for garbage in (b"\x00\xff\x13", b"\x02" + bytes(8), b"\x10\x10\x10\x03"):
                got, expected = await asyncio.gather(
                    _answer(face.host, face.port, garbage), _answer(twin.host, twin.port, garbage)
                )
                assert got == expected, garbage
                answers.append(got)
            assert answers[1] == b"\x10\x06\x10\x15"  # DLE ACK, then DLE NAK
            async with _pg(face.url) as pg:  # the face and the line go on
                assert await pg.read("DB5.DW0") == [0x0500]
        assert poller.stats["kiln1"].bad_samples == 0


async def _answer(host: str, port: int, frame: bytes) -> bytes:
    """What a peer answers ``frame`` on a connection of its own within 0.5 s."""
    reader, writer = await asyncio.open_connection(host, port)
    got = b""
    try:
        writer.write(frame)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(0.5):
                while chunk := await reader.read(100):
                    got += chunk
    finally:
        writer.close()
        await asyncio.gather(writer.wait_closed(), return_exceptions=True)
    return got
