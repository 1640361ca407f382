"""Optional interop: PyPI ``hslcommunication`` 1.2.0 (an independent FETCH/WRITE client, spec E)
against our simulator. Its licence allows only local test use, so it is never a dependency: marked
``hsl``, left out of the default run; ``PYTHONPATH=/path/to/hslpeer pytest -m hsl ...`` runs it,
and fails naming the package when it cannot import it."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from plcstack.sim import fetchwrite as fwsim
from plcstack.sim.s5memory import Area
from tests.peers import hsl_peer

pytestmark = pytest.mark.hsl


@pytest.fixture
def hsl() -> Any:
    return hsl_peer()


async def test_hsl_client_against_simulator(hsl: Any) -> None:
    async with await fwsim.start() as sim:
        peer: Any = hsl.SiemensFetchWriteNet("127.0.0.1", sim.port)

        def run() -> list[Any]:
            return [
                peer.Read("DB10.5", 40),
                peer.Read("DB99.0", 2),
                peer.Write("M100", bytearray(b"\xde\xad\xbe\xef")),
                peer.Read("M100", 4),
                peer.Write("Q2", bytearray(b"\x01\x02")),
            ]

        fetch, missing, write_m, read_m, write_q = await asyncio.to_thread(run)
        assert fetch.IsSuccess
        assert bytes(fetch.Content) == b"".join((0x1000 + i).to_bytes(2, "big") for i in range(20))
        assert not missing.IsSuccess and missing.ErrorCode == 2
        assert write_m.IsSuccess and read_m.IsSuccess
        assert bytes(read_m.Content) == b"\xde\xad\xbe\xef"
        assert write_q.IsSuccess and sim.memory.read_area(Area.OUTPUTS, 2, 2) == b"\x01\x02"
        assert sim.memory.read_area(Area.FLAGS, 100, 4) == b"\xde\xad\xbe\xef"
