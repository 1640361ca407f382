"""Store-and-forward queue: FIFO across memory and disk, acks, the byte budget, restarts."""

from __future__ import annotations

import tempfile
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from plcstack.north.buffer import OVERHEAD, StoreAndForward

ops = st.lists(
    st.one_of(
        st.tuples(st.just("put"), st.binary(max_size=60)),
        st.tuples(st.just("ack"), st.integers(0, 5)),
        st.tuples(st.just("reopen"), st.none()),
    ),
    max_size=60,
)


@settings(max_examples=30, deadline=None)
@given(ops=ops, memory=st.integers(0, 300), budget=st.integers(200, 2000))
def test_behaves_like_a_bounded_fifo_that_survives_reopening(
    ops: list[tuple[str, object]], memory: int, budget: int
) -> None:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "q.sqlite"
        q = StoreAndForward(path, memory_bytes=memory, max_bytes=budget)
        model: list[tuple[int, bytes]] = []
        dropped = 0
        for op, arg in ops:
            if op == "put":
                assert isinstance(arg, bytes)
                m = q.put("t/x", arg)
                model.append((m.seq, arg))
                while sum(len(p) + 3 + OVERHEAD for _, p in model) > budget:
                    model.pop(0)
                    dropped += 1
            elif op == "ack":
                assert isinstance(arg, int)
                head = q.peek(arg)
                if head:
                    q.ack(head[-1].seq)
                    del model[: len(head)]
            else:
                q.close()
                q = StoreAndForward(path, memory_bytes=memory, max_bytes=budget)
            assert [(m.seq, m.payload) for m in q.peek(1000)] == model
            assert len(q) == len(model)
            assert q.backlog_bytes <= budget
        assert q.dropped <= dropped  # drops are counted per queue object (a reopen restarts it)
        q.close()


def test_spills_the_oldest_to_disk_and_reads_them_back_first(tmp_path: Path) -> None:
    q = StoreAndForward(tmp_path / "q.sqlite", memory_bytes=500, max_bytes=100_000)
    for i in range(100):
        q.put("t", b"%03d" % i + b"." * 20)
    assert q.on_disk > 50 and q.spilled == q.on_disk
    seen = []
    while len(q):
        batch = q.peek(7)
        seen += [int(m.payload[:3]) for m in batch]
        q.ack(batch[-1].seq)
    assert seen == list(range(100))
    assert q.backlog_bytes == 0


def test_without_disk_the_budget_bounds_memory() -> None:
    q = StoreAndForward(None, max_bytes=1000)
    for i in range(1000):
        q.put("t", b"%04d" % i)
    assert q.backlog_bytes <= 1000 and q.dropped == 1000 - len(q)
    assert [int(m.payload) for m in q.peek(5)] == list(range(1000 - len(q), 1000 - len(q) + 5))
