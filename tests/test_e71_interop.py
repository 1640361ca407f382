"""The E71 simulator driven by an independent 1E client: HslCommunication's ``MelsecA1ENet``.

Not a dependency of plcstack: marked ``hsl``, left out of the default run; with ``-m hsl`` it fails
naming the package when it cannot import it. E.g.
``pip install --target /tmp/hsl --no-deps hslcommunication==1.2.0`` and
``PYTHONPATH=/tmp/hsl python -m pytest -m hsl tests/test_e71_interop.py``. HSL 1.2.0 is binary
only and waits for data after end codes other than 00H/5BH (a limitation of that version), so
only those paths are driven here.
"""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from plcstack.sim import e71 as sim_e71
from tests.peers import hsl_peer

pytestmark = pytest.mark.hsl


@pytest.fixture
def hsl() -> Any:
    return hsl_peer()


async def test_hsl_melsec_a1enet_against_simulator(hsl: Any) -> None:
    sim = await sim_e71.start()
    try:
        sim.memory.write_words("D", 100, [0x1234, 0x9876, 0x0109])
        sim.memory.write_bits("M", 100, [True, False, True])

        def drive() -> list[Any]:
            plc = hsl.MelsecA1ENet("127.0.0.1", sim.port)
            plc.ConnectTimeOut = 5000
            plc.ReceiveTimeOut = 5000
            out: list[Any] = [plc.ConnectServer().IsSuccess]
            r = plc.ReadUInt16("D100", 3)
            out.append((r.IsSuccess, list(r.Content or [])))
            r = plc.ReadBool("M100", 3)
            out.append((r.IsSuccess, list(r.Content or [])))
            out.append(plc.WriteInt16("D200", [7, -2]).IsSuccess)
            out.append(plc.WriteBool("M50", [False, True, True]).IsSuccess)
            plc.PLCNumber = 5
            r = plc.ReadInt16("D100", 1)
            out.append((r.IsSuccess, r.ErrorCode))
            plc.PLCNumber = 0xFF
            r = plc.ReadUInt16("D100", 200)
            out.append((r.IsSuccess, len(r.Content or [])))
            plc.ConnectClose()
            return out

        result = await asyncio.wait_for(asyncio.to_thread(drive), 30)
        assert result == [
            True,
            (True, [0x1234, 0x9876, 0x0109]),
            (True, [True, False, True]),
            True,
            True,
            (False, 0x10),  # 5BH + abnormal code 10H, and the connection goes on
            (True, 200),
        ]
        assert sim.memory.read_words("D", 200, 2) == [7, 0xFFFE]
        assert sim.memory.read_bits("M", 50, 3) == [False, True, True]
    finally:
        await sim.aclose()
