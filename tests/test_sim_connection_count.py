"""The simulators count concurrent client connections (what the scale-out tests assert on)."""

from __future__ import annotations

import plcstack
from plcstack.sim import e71, s5lan
from tests.aio_helpers import eventually


async def test_e71_counts_current_and_peak_connections() -> None:
    async with await e71.start() as sim:
        assert isinstance(sim, e71.E71TcpSimulator)
        count = sim.connection_count
        async with plcstack.connect(sim.url) as a:
            await a.read("D0", 1)
            async with plcstack.connect(sim.url) as b:
                await b.read("D0", 1)
                assert (count.current, count.peak) == (2, 2)
            await eventually(lambda: count.current == 1, "1 connection(s) open", 2.0)
            await a.read("D0", 1)
        await eventually(lambda: count.current == 0, "0 connection(s) open", 2.0)
        assert (count.peak, count.total) == (2, 2)


async def test_stream_simulators_count_through_track() -> None:
    async with await s5lan.start() as sim:
        count = sim.connection_count
        async with plcstack.connect(sim.url) as plc:
            await plc.read("DB1.DW0", 1)
            assert (count.current, count.peak) == (1, 1)
        await eventually(lambda: count.current == 0, "0 connection(s) open", 2.0)
        assert count.total == 1
