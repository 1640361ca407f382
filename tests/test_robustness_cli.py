"""Promise 3: error messages, end to end through the ``plcstack read`` command line.

For each protocol one PLC error code: exit 1 and exactly one stderr line that names the URL, the
request and the meaning of the code. A bad address: exit 2, one line, and the PLC sees no bytes.
The simulators (and the byte-counting proxies in front of them) run in the test's event loop.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from plcstack.clients import connect
from plcstack.errors import PlcErrorResponse
from plcstack.sim import as511 as as511_sim
from plcstack.sim import e71 as e71_sim
from plcstack.sim import fetchwrite as fw_sim
from plcstack.sim import s5lan as s5lan_sim
from plcstack.sim.melsec_memory import MelsecMemory
from tests.cli_helpers import cli_in_process
from tests.ports import free_port
from tests.robust_helpers import MisbehavingProxy, record_loop_errors


async def _cli(*args: str) -> tuple[int, list[str], str]:
    """``plcstack ARGS`` as ``python -m plcstack`` runs it (its ``main``), in this process: the
    entry point itself is proven in test_cli_basic.py; a new interpreter per case was most of
    this file's CPU time."""
    code, out, err = await cli_in_process(*args)
    return code, err.splitlines(), out


async def _expected_error(url: str, address: str) -> PlcErrorResponse:
    """The same read in-process: the error the CLI line must render."""
    async with connect(url, timeout=2) as plc:
        with pytest.raises(PlcErrorResponse) as info:
            await plc.read(address)
    return info.value


Starter = Callable[[], Awaitable[Any]]

#: name -> (simulator, address the PLC refuses with an error code, a malformed address)
CASES: dict[str, tuple[Starter, str, str]] = {
    # CPU group I has no R device and D only up to D1023: the E71 answers an end code
    "e71-tcp": (lambda: e71_sim.start(MelsecMemory("I")), "R0", "Q5"),
    "e71-udp-ascii": (
        lambda: e71_sim.start(MelsecMemory("I"), transport="udp", code="ascii"),
        "R0",
        "D-1",
    ),
    "s5lan": (lambda: s5lan_sim.start(), "DB99.DW0", "DB.DW"),
    "fetchwrite-mk": (lambda: fw_sim.start(mk=True), "DB99.DW0", "MX5"),
    "as511-tcp": (lambda: as511_sim.start(), "DB50.DW0", "Q5"),
    "as511-pty": (lambda: as511_sim.start_pty(), "DB50.DW0", ""),
}


@pytest.mark.parametrize("name", sorted(CASES))
async def test_plc_error_code_is_one_line_with_url_request_and_meaning(name: str) -> None:
    starter, address, _ = CASES[name]
    async with record_loop_errors() as errors:
        sim = await starter()
        try:
            expected = await _expected_error(sim.url, address)
            code, err, out = await _cli("read", sim.url, address, "--timeout", "2")
            assert (code, out) == (1, ""), err
            assert len(err) == 1, err
            line = err[0]
            assert line == f"plcstack: error: {expected}"
            assert sim.url in line and f"read {address}" in line
            assert expected.code_text in line and expected.meaning in line and expected.meaning
        finally:
            await sim.aclose()
    assert errors.describe() == []


TCP_BAD = sorted(n for n in CASES if CASES[n][2] and "udp" not in n)


async def _bad_address_over_tcp(name: str) -> None:
    starter, _, bad = CASES[name]
    sim = await starter()
    proxy = await MisbehavingProxy(sim.host, sim.port).start()
    url = sim.url.replace(f":{sim.port}", f":{proxy.port}", 1)
    try:
        # read for every protocol, write for one
        verb, extra = ("write", ["1"]) if name == "s5lan" else ("read", [])
        code, err, out = await _cli(verb, url, bad, *extra)
        assert (code, out) == (2, ""), (name, err)
        assert len(err) == 1 and url in err[0] and f"{verb} {bad}" in err[0], err
        assert proxy.script.chunks == []  # the PLC saw no byte
    finally:
        await proxy.aclose()
        await sim.aclose()


async def _bad_address_with_plc_unreachable() -> None:
    """The address is checked before connecting: a typo is exit 2 even with the PLC offline."""
    port = free_port()  # nobody listens there
    url = f"e71+tcp://127.0.0.1:{port}"
    code, err, _ = await _cli("read", url, "Q5")
    assert code == 2 and len(err) == 1 and url in err[0] and "read Q5" in err[0], err


async def test_bad_address_is_exit_2_and_nothing_is_sent() -> None:
    """All protocols at once."""
    await asyncio.gather(
        *(_bad_address_over_tcp(name) for name in TCP_BAD), _bad_address_with_plc_unreachable()
    )


class _CountingUdp(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.datagrams = 0

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.datagrams += 1


async def test_bad_address_over_udp_sends_no_datagram() -> None:
    loop = asyncio.get_running_loop()
    counter = _CountingUdp()
    transport, _ = await loop.create_datagram_endpoint(lambda: counter, local_addr=("127.0.0.1", 0))
    port = transport.get_extra_info("sockname")[1]
    url = f"e71+udp://127.0.0.1:{port}?code=ascii"
    try:
        code, err, _ = await _cli("read", url, "D100", "0")  # a bad count is bad input too
        assert code == 2 and len(err) == 1 and url in err[0] and "read D100" in err[0], err
        assert counter.datagrams == 0
    finally:
        transport.close()
