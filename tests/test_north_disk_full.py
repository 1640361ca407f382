"""Store-and-forward on a full disk: losses counted and said once, removals the disk refuses
never re-send what was delivered, live data flows when the broker is back."""

from __future__ import annotations

import asyncio
import collections
import logging
import os
import sqlite3
import tempfile
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.north.buffer import StoreAndForward
from plcstack.north.mqtt import MqttSettings, MqttSink
from plcstack.north.queue_file import RETRY_SECONDS, SETTLE_SECONDS
from plcstack.north.supervise import Supervisor
from tests.aio_helpers import eventually
from tests.disk_helpers import fill, small_disk
from tests.north_helpers import sample, subscriber
from tests.scan_helpers import scan
from tests.servers import Mosquitto

PAYLOAD = "x" * 900  # about 1 KB a message: a 256 KiB disk is full after a few hundred
TOTAL = 1500  # more than the disk and the memory it leaves (1 MiB) take
#: a memory file system for the many small files of the property test, where there is one
SHM = "/dev/shm" if os.path.isdir("/dev/shm") else None


class Clock:
    """A monotonic clock the test moves (the queue's retries and settling)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def agree(q: StoreAndForward) -> None:
    """The two backlog figures describe the same messages."""
    waiting = q.peek(len(q) + 1)
    assert len(waiting) == len(q)
    assert sum(m.cost for m in waiting) == q.backlog_bytes


def rows_in(path: Path) -> int:
    with sqlite3.connect(path) as db:
        (count,) = db.execute("SELECT COUNT(*) FROM queue").fetchone()
    return int(count)


def levels(caplog: pytest.LogCaptureFixture, level: int) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno == level and r.name == "plcstack.north.buffer"
    ]


def test_a_full_disk_is_one_error_counted_losses_and_one_warning_when_it_is_back(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    clock = Clock()
    with small_disk(tmp_path / "disk") as disk:
        q = StoreAndForward(disk / "q.sqlite", memory_bytes=0, max_bytes=8 << 20, clock=clock)
        filler = fill(disk)
        for n in range(1500):  # 1.5 MB: more than memory may hold while the disk refuses
            q.put("t", b"%05d" % n + b"." * 1000)
            agree(q) if n % 100 == 0 else None
        agree(q)
        assert q.on_disk == 0 and q.dropped == q.lost_to_disk > 0
        failure = q.failure
        assert failure is not None and failure.lost == q.dropped and "full" in failure.error
        assert "q.sqlite cannot be written (" in failure.describe()
        assert f"{q.dropped} messages lost" in failure.describe()
        # the newest are kept, in order, within the memory the refusal leaves
        kept = [int(m.payload[:5]) for m in q.peek(len(q))]
        assert kept == list(range(1500 - len(q), 1500))
        assert q.backlog_bytes <= 1 << 20
        [error] = levels(caplog, logging.ERROR)
        assert str(disk / "q.sqlite") in error and "database or disk is full" in error
        assert levels(caplog, logging.WARNING) == []
        # some space again: the next try (a second later) spills what fits, in order
        filler.unlink()
        clock.now += RETRY_SECONDS
        q.put("t", b"late")
        assert q.on_disk > 0 and q.failure is not None  # full again before it settled
        assert [int(m.payload[:5]) for m in q.peek(2)] == kept[:2]
        agree(q)
        # the broker takes everything; the file's removal needs no space (it is replaced)
        q.ack(q.peek(len(q))[-1].seq)
        assert len(q) == 0 and q.backlog_bytes == 0
        clock.now += RETRY_SECONDS
        q.put("t", b"written")
        assert q.on_disk == 1 and q.failure is not None  # taken, not yet for long enough
        clock.now += SETTLE_SECONDS
        q.put("t", b"settled")
        assert q.failure is None
        [back] = levels(caplog, logging.WARNING)
        assert "writable again" in back and f"{q.dropped} messages were lost" in back
        assert len(levels(caplog, logging.ERROR)) == 1
        agree(q)
        q.close()


def test_a_removal_the_disk_refuses_is_never_sent_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    clock = Clock()
    with small_disk(tmp_path / "disk") as disk:
        path = disk / "q.sqlite"
        q = StoreAndForward(path, memory_bytes=0, max_bytes=8 << 20, clock=clock)
        for n in range(20):
            q.put("t", b"%02d" % n)
        assert q.on_disk == 20
        filler = fill(disk)
        head = q.peek(8)
        q.ack(head[-1].seq)  # delivered: the DELETE cannot be written
        assert [int(m.payload) for m in q.peek(100)] == list(range(8, 20))
        agree(q)
        assert q.failure is not None and rows_in(path) == 20
        # a retry while the disk is still full changes nothing; the queue stays right
        clock.now += RETRY_SECONDS
        q.ack(q.peek(1)[0].seq)
        assert [int(m.payload) for m in q.peek(100)] == list(range(9, 20))
        # with space, the next try deletes them
        filler.unlink()
        clock.now += RETRY_SECONDS
        q.ack(q.peek(1)[0].seq)
        assert rows_in(path) == 10 and len(q) == 10
        agree(q)
        q.close()
        assert [int(m.payload) for m in StoreAndForward(path).peek(100)] == list(range(10, 20))


def test_a_drained_file_is_replaced_when_its_removals_cannot_be_written(tmp_path: Path) -> None:
    """Delivering everything on a full disk: the file is replaced by an empty one (an unlink
    needs no space), so the space is free again and a restart sends nothing twice."""
    with small_disk(tmp_path / "disk") as disk:
        path = disk / "q.sqlite"
        q = StoreAndForward(path, memory_bytes=0, max_bytes=8 << 20, clock=Clock())
        for n in range(30):
            q.put("t", b"%02d" % n)
        filler = fill(disk)
        q.ack(q.peek(10)[-1].seq)
        assert rows_in(path) == 30
        filler.unlink()  # make room for the new file only after the refusal
        fill(disk, "filler2")
        (disk / "filler2").unlink()
        q.ack(q.peek(100)[-1].seq)
        assert len(q) == 0 and rows_in(path) == 0
        q.put("t", b"new")
        q.close()
        assert [m.payload for m in StoreAndForward(path).peek(10)] == [b"new"]


def test_what_a_full_disk_refuses_at_the_stop_is_said_and_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with small_disk(tmp_path / "disk") as disk:
        path = disk / "q.sqlite"
        q = StoreAndForward(path, memory_bytes=1 << 20, max_bytes=8 << 20, clock=Clock())
        for n in range(5):
            q.put("t", b"%d" % n)
        fill(disk)
        q.close()  # the memory part cannot be written
        assert q.dropped == q.lost_to_disk == 5
        [error] = levels(caplog, logging.ERROR)
        assert "5 messages waiting in memory could not be saved" in error
        assert "they are lost" in error and str(path) in error


def test_a_file_that_cannot_be_opened_at_the_start_is_opened_later(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A restart on a full disk: the old backlog cannot be opened (WAL needs its -shm); the
    run goes on in memory, opens the file when the disk takes writes again, and sends the old
    messages first."""
    clock = Clock()
    with small_disk(tmp_path / "disk") as disk:
        path = disk / "q.sqlite"
        first = StoreAndForward(path, memory_bytes=0)
        for n in range(3):
            first.put("t", b"old%d" % n)
        first.close()
        filler = fill(disk)
        q = StoreAndForward(path, memory_bytes=0, clock=clock)
        assert q.failure is not None and len(q) == 0
        q.put("t", b"new0")
        filler.unlink()
        clock.now += RETRY_SECONDS
        q.put("t", b"new1")
        assert [m.payload for m in q.peek(10)] == [b"old0", b"old1", b"old2", b"new0", b"new1"]
        agree(q)
        q.close()


def received(sub: Any) -> collections.Counter[int]:
    return collections.Counter(record["values"]["n"][0] for record in sub.json())


async def test_a_full_disk_loses_counted_messages_and_recovers_when_the_broker_returns(
    mosquitto: Mosquitto, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Broker down, the disk under buffer_path full: losses are counted and said once; with
    the broker back the backlog drains, live data flows, no message arrives more than twice
    and the sink never fails (before: the DELETE of delivered messages raised, the sink
    crash-looped and sent the same window again and again)."""
    caplog.set_level(logging.DEBUG)
    with small_disk(tmp_path / "disk") as disk:
        async with subscriber(mosquitto.host, mosquitto.port, "plcstack/+/data/#") as sub:
            mosquitto.stop()
            buffer = StoreAndForward(disk / "q.sqlite", memory_bytes=4096, max_bytes=8 << 20)
            supervisor = Supervisor()
            sink = MqttSink(
                MqttSettings(host=mosquitto.host, port=mosquitto.port, reconnect_max=0.2),
                buffer=buffer,
            )
            sink.supervisor = supervisor
            await sink.start()
            for n in range(TOTAL):  # as the run delivers scans: through the supervisor
                scans = [scan(sample("p", "n", [n, PAYLOAD]))]
                supervisor.submit(sink.name, sink.submit, scans, sink.probe)
                if n % 50 == 0:
                    await asyncio.sleep(0.001)
                    agree(buffer)
            lost = buffer.dropped
            assert lost > 0, "the disk never filled: the test proves nothing"
            failure = buffer.failure
            assert failure is not None and "full" in failure.error
            assert failure.lost == buffer.lost_to_disk == lost  # the budget dropped none
            errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
            assert len(errors) == 1 and str(disk / "q.sqlite") in errors[0], errors
            mosquitto.start()
            await sink.wait_connected(10)
            # live data flows again: a message submitted after the return arrives
            supervisor.submit(sink.name, sink.submit, [scan(sample("p", "n", [TOTAL, "live"]))])
            await sub.wait_for(lambda s: TOTAL in received(s), timeout=20)
            await eventually(lambda: len(buffer) == 0, "the backlog drains")
            counts = received(sub)
            assert max(counts.values()) <= 2, counts.most_common(3)
            # every data message was delivered or counted lost, none both
            assert len(counts) + lost == TOTAL + 1, (len(counts), lost)
            assert sink.stats.sent == sink.stats.submitted - lost
            assert not supervisor.errors
            # the drained file was replaced: the disk has room again
            assert rows_in(disk / "q.sqlite") == 0
            await sink.aclose()
            await supervisor.aclose()


class _Flaky:
    """A connection to the queue's file whose writes fail while ``refusing`` is set, as a full
    disk's do (reads go on working)."""

    refusing = False

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def execute(self, sql: str, args: Any = ()) -> Any:
        if _Flaky.refusing and not sql.lstrip().upper().startswith(("SELECT", "PRAGMA")):
            raise sqlite3.OperationalError("database or disk is full")
        return self._db.execute(sql, args)

    def executemany(self, sql: str, rows: Any) -> Any:
        if _Flaky.refusing:
            raise sqlite3.OperationalError("database or disk is full")
        return self._db.executemany(sql, rows)

    def __enter__(self) -> _Flaky:
        self._db.__enter__()
        return self

    def __exit__(self, *exc: Any) -> Any:
        return self._db.__exit__(*exc)

    def close(self) -> None:
        self._db.close()


ops = st.lists(
    st.one_of(
        st.tuples(st.just("put"), st.integers(0, 120)),
        st.tuples(st.just("ack"), st.integers(0, 40)),
        st.tuples(st.just("disk"), st.booleans()),
        st.tuples(st.just("later"), st.sampled_from([0.5, RETRY_SECONDS, SETTLE_SECONDS])),
    ),
    max_size=80,
)


@settings(max_examples=300, deadline=None)
@given(ops=ops, memory=st.integers(0, 500), budget=st.integers(2000, 20_000))
def test_whatever_the_disk_refuses_each_message_is_delivered_waiting_or_counted_once(
    ops: list[tuple[str, Any]], memory: int, budget: int
) -> None:
    """Any interleaving of puts, acknowledgements and a disk that refuses and takes writes
    again: the queue stays FIFO, never hands out a delivered message again, its figures agree,
    and every message put is exactly one of delivered, waiting or dropped (counted)."""
    clock = Clock()
    _Flaky.refusing = False
    with tempfile.TemporaryDirectory(dir=SHM) as d, pytest.MonkeyPatch.context() as patch:
        connect = sqlite3.connect
        patch.setattr(sqlite3, "connect", lambda path: _Flaky(connect(path)))  # queue_file.py's
        q = StoreAndForward(
            Path(d) / "q.sqlite", memory_bytes=memory, max_bytes=budget, clock=clock
        )
        put = 0
        delivered: list[int] = []
        for op, arg in ops:
            if op == "put":
                q.put("t/x", b"." * arg)
                put += 1
            elif op == "ack":
                head = q.peek(arg)
                if head:
                    q.ack(head[-1].seq)
                    delivered += [m.seq for m in head]
            elif op == "disk":
                _Flaky.refusing = arg
            else:
                clock.now += arg
            waiting = [m.seq for m in q.peek(len(q) + 1)]
            assert waiting == sorted(waiting) and len(waiting) == len(q)
            assert not set(waiting) & set(delivered)
            agree(q)
            assert len(delivered) + len(q) + q.dropped == put
            assert q.backlog_bytes <= max(budget, 1 << 20) + 64 * 200  # plus an in-flight window
        assert len(set(delivered)) == len(delivered)
        _Flaky.refusing = False
        q.close()
