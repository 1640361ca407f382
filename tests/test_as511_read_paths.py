"""Issue 16: the AS511 client's one-await word read decides exactly as the general path.

``AS511Client.read`` of a DB/DX word range whose block address is cached and whose header +
data fit one transaction runs as a single awaited transaction (``read_prepared``); everything else,
and every failure after which the general path drops the cached address and asks B_INFO again,
goes through ``read_block_bytes``. Two clients, one as shipped and one whose prepared read
always declines (the general path, :class:`GeneralPath`), each
against its own simulator holding the same memory, get the same sequence of reads and memory
changes (blocks moved by compress, deleted, re-created longer, an answer one byte short): the
same results or errors, the same bytes on the wire, the same address cache and counters.
"""

from __future__ import annotations

import struct
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from plcstack.clients import connect
from plcstack.clients.as511 import AS511Client
from plcstack.codecs.as511 import FN_READ
from plcstack.errors import PlcError
from plcstack.sim import as511 as sim_as511
from plcstack.sim.s5memory import BlockType, S5Memory

_READS = [
    ("DB3.DW0", 2),
    ("DB3.DW0", 64),  # the bench's read
    ("DB3.DW10", 4),
    ("DB3.DW79", 1),  # the last word
    ("DB3.DW80", 1),  # beyond the block: AddressError
    ("DB3.DW60", 30),  # runs past the end
    ("DB3.DW33", 2),  # offset 66 bytes: past the signature gap, no header read
    ("DB5.DW0", 300),  # more than one transaction
    ("DB1.DW1", 3),
    ("DB1.DW4", 8),  # past the end of DB1 unless it grew: the cached length decides first
    ("DX1.DW0", 2),
    ("MW0", 2),  # not a block
    ("DB3.DL0", 2),  # bytes, not words
]
_CHANGES = ["move", "recreate", "delete", "short answer", "restore", "grow"]


def _memory() -> S5Memory:
    mem = S5Memory(default_dbs={1: 8, 2: 8, 3: 80, 4: 8, 5: 400})
    mem.create_block(BlockType.DX, 1, 4, bytes(range(8)))
    for number, words in ((1, 8), (3, 80), (5, 400)):
        mem.write_db_words(number, 0, [(number << 8 | i) & 0xFFFF for i in range(words)])
    return mem


class GeneralPath(AS511Client):
    """The reference: every read takes the general path (``read_block_bytes``)."""

    async def read_prepared(self, address: str, count: int) -> list[int] | None:
        return None


class _Side:
    """One client against its own simulator; records what it sends."""

    def __init__(self, fast: bool) -> None:
        self.fast = fast
        self.sent: list[bytes] = []
        self.short_next = False

    async def __aenter__(self) -> _Side:
        self.mem = _memory()
        self.sim = await sim_as511.start(self.mem)
        machine = self.sim.machine
        execute = machine.execute

        def maybe_short(fn: int, params: bytes) -> Any:
            answer = execute(fn, params)
            if fn == FN_READ and self.short_next and isinstance(answer, bytes):
                self.short_next = False
                return answer[:-1]
            return answer

        machine.execute = maybe_short  # type: ignore[method-assign]
        plc = connect(self.sim.url, nak_backoff=0.01)  # the B5.1 pause, short for tests
        assert isinstance(plc, AS511Client)
        if not self.fast:
            plc = GeneralPath(plc.name, plc.transport, nak_backoff=0.01)
        self.plc = plc
        await plc.open()
        write = plc.transport.write

        def spy(data: bytes) -> None:
            self.sent.append(bytes(data))
            write(data)

        plc.transport.write = spy  # type: ignore[method-assign]
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.plc.aclose()
        await self.sim.aclose()

    def change(self, what: str) -> None:
        mem = self.mem
        if what == "move" and (BlockType.DB, 2) in dict.fromkeys(mem.blocks()):
            mem.delete_block(BlockType.DB, 2)
            mem.compress()  # DB3, DB4, DB5 move down
        elif what == "recreate":
            mem.create_block(BlockType.DB, 3, 80, b"\x12\x34" * 80)  # same size, at the end
        elif what == "delete" and (BlockType.DB, 1) in dict.fromkeys(mem.blocks()):
            mem.delete_block(BlockType.DB, 1)
        elif what == "short answer":
            self.short_next = True
        elif what == "restore":
            mem.create_block(BlockType.DB, 1, 8, bytes(16))
        elif what == "grow":
            mem.create_block(BlockType.DB, 1, 16, bytes(range(32)))

    async def read(self, address: str, count: int) -> Any:
        self.sent.clear()
        try:
            outcome: Any = ("values", await self.plc.read(address, count))
        except PlcError as exc:
            outcome = ("error", type(exc).__name__, str(exc).replace(self.plc.name, "PLC"))
        cache = {key: (info.dw0, info.header) for key, info in self.plc.block_cache.items()}
        stats = (self.plc.stats.requests, self.plc.stats.errors)
        return outcome, b"".join(self.sent), cache, stats


_steps = st.lists(
    st.one_of(
        st.sampled_from(_READS).map(lambda r: ("read", *r)),
        st.sampled_from(_CHANGES).map(lambda c: ("change", c)),
    ),
    min_size=1,
    max_size=10,
)


async def _compare(steps: list[tuple[Any, ...]]) -> None:
    async with _Side(True) as fast, _Side(False) as general:
        for step in [("read", "DB3.DW0", 64), *steps, ("read", "DB3.DW0", 64)]:
            if step[0] == "change":
                fast.change(step[1])
                general.change(step[1])
                continue
            _, address, count = step
            got, expected = await fast.read(address, count), await general.read(address, count)
            assert got == expected, step


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(steps=_steps)
async def test_one_await_word_read_is_the_general_path(steps: list[tuple[Any, ...]]) -> None:
    await _compare(steps)


_DB3 = ("read", "DB3.DW0", 64)
_ODD_COUNTS = [("read", "DB3.DW0", 2), ("read", "DB3.DW0", 2.0), ("read", "DB3.DW0", True)]
_SCENARIOS: dict[str, list[tuple[Any, ...]]] = {
    "block moved by compress": [_DB3, ("change", "move"), _DB3, _DB3],
    "block re-created elsewhere": [_DB3, ("change", "recreate"), _DB3, _DB3],
    "answer one byte short": [_DB3, ("change", "short answer"), _DB3, _DB3],
    "past the cached length, then grown": [
        ("read", "DB1.DW4", 8),
        ("read", "DB1.DW4", 8),
        ("change", "grow"),
        ("read", "DB1.DW4", 8),
        ("read", "DB1.DW4", 8),
    ],
    "counts equal to a planned one but no int": [*_ODD_COUNTS, *_ODD_COUNTS],
    "block deleted, then back": [
        ("read", "DB1.DW1", 3),
        ("change", "delete"),
        ("read", "DB1.DW1", 3),
        ("change", "restore"),
        ("read", "DB1.DW1", 3),
        ("read", "DB1.DW1", 3),
    ],
}


@pytest.mark.parametrize("name", sorted(_SCENARIOS))
async def test_one_await_word_read_scenarios(name: str) -> None:
    """The transitions the random sequences may miss, each spelled out once."""
    await _compare(_SCENARIOS[name])


async def test_the_one_await_read_is_taken_and_counts_one_transaction(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The differential test proves nothing if the fast path never runs: a repeated DB read
    does not enter read_block_bytes and costs one transaction (header + data)."""
    async with _Side(True) as side:
        values = await side.plc.read("DB3.DW0", 64)
        assert values == [(3 << 8) | i for i in range(64)]
        monkeypatch.setattr(AS511Client, "read_block_bytes", lambda *a: pytest.fail("general path"))
        requests = side.plc.stats.requests
        assert await side.plc.read("DB3.DW0", 64) == values
        assert side.plc.stats.requests == requests + 1
        start = side.plc.block_cache[(1, 3)].dw0 - 10
        assert struct.pack(">HH", start, start + 10 + 128 - 1) in b"".join(side.sent)
