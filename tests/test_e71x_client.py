"""E71 client against the simulator over real loopback TCP/UDP sockets: commands 0AH-21H,
39H-3CH, 60H-62H (issue 3), CPU-mode gating of spec §7.1, errors end to end."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest

import plcstack
from plcstack.clients.e71 import E71Client
from plcstack.codecs.e71 import CpuGroup
from plcstack.errors import AddressError, PlcErrorResponse
from plcstack.sim import e71 as sim_e71
from plcstack.sim.e71_module import KeySwitch, module_of
from plcstack.sim.melsec_memory import CpuState, MelsecMemory

VARIANTS = [("tcp", "binary"), ("tcp", "ascii"), ("udp", "binary"), ("udp", "ascii")]
Sim = sim_e71.E71TcpSimulator | sim_e71.E71UdpSimulator


@pytest.fixture(params=VARIANTS, ids=["tcp-binary", "tcp-ascii", "udp-binary", "udp-ascii"])
async def sim(request: pytest.FixtureRequest) -> AsyncIterator[Sim]:
    transport, code = request.param
    s = await sim_e71.start(transport=transport, code=code)
    try:
        yield s
    finally:
        await s.aclose()


def state(memory: MelsecMemory) -> CpuState:
    return memory.state  # a call: mypy must not narrow the attribute across awaits


def client(url: str, **options: Any) -> E71Client:
    plc = plcstack.connect(url, **options)
    assert isinstance(plc, E71Client)
    return plc


async def error_code(coro: Awaitable[object]) -> str:
    with pytest.raises(PlcErrorResponse) as info:
        await coro
    return info.value.code_text


# -- 13H-16H ------------------------------------------------------------------------------------


async def test_model_status_run_stop(sim: Sim) -> None:
    async with client(sim.url) as plc:
        assert await plc.cpu_model() == (
            0x94,
            "A3A, A3U, A4U, Q3A, Q4A, AJ72LP25/BR15, AJ72QLP25/QBR15",
        )
        status = await plc.cpu_status()
        assert (status.state, status.model_code) == ("RUN", 0x94)
        await plc.remote_stop()
        assert state(sim.memory) is CpuState.STOP
        status = await plc.cpu_status()
        assert status.state == "STOP" and status.status_word == 0x21  # remote cause
        await plc.remote_run()
        assert state(sim.memory) is CpuState.RUN
        assert (await plc.cpu_status()).state == "RUN"


@pytest.mark.parametrize(
    ("group", "model"),
    [(CpuGroup.I, 0xA1), (CpuGroup.IV, 0xA3), (CpuGroup.V, 0x92), (CpuGroup.VII, 0x94)],
)
async def test_model_code_follows_cpu_group(group: CpuGroup, model: int) -> None:
    async with await sim_e71.start(MelsecMemory(group)) as s, client(s.url) as plc:
        assert (await plc.cpu_model())[0] == model
    module = module_of(MelsecMemory())
    module.model_code = 0xF3
    assert module.model_code == 0xF3


@pytest.mark.parametrize(
    ("switch", "after_run", "after_stop"),
    [
        (KeySwitch.RUN, CpuState.RUN, CpuState.STOP),
        (KeySwitch.STOP, CpuState.STOP, CpuState.STOP),
        (KeySwitch.PAUSE, CpuState.PAUSE, CpuState.STOP),
        (KeySwitch.STEP_RUN, CpuState.RUN, CpuState.STOP),  # §13 A13
    ],
)
async def test_key_switch_table_10_33(
    switch: KeySwitch, after_run: CpuState, after_stop: CpuState
) -> None:
    async with await sim_e71.start() as s, client(s.url) as plc:
        module = module_of(s.memory)
        module.set_key_switch(switch)
        await plc.remote_stop()
        assert state(s.memory) is after_stop
        await plc.remote_run()
        assert state(s.memory) is after_run
        if switch is KeySwitch.STEP_RUN:
            assert (await plc.cpu_status()).state == "STEP-RUN"


async def test_remote_run_refused_after_another_station_stopped() -> None:
    async with await sim_e71.start() as s, client(s.url) as plc:
        module_of(s.memory).remote_stop(by="AJ71C24")
        assert await error_code(plc.remote_run()) == "5BH/18H"
        assert await error_code(plc.remote_stop()) == "5BH/18H"
        assert state(s.memory) is CpuState.STOP
        with pytest.raises(PlcErrorResponse, match="remote RUN/STOP not possible"):
            await plc.remote_run()
        module_of(s.memory).remote_run(by="AJ71C24")
        await plc.remote_stop()
        await plc.remote_run()
        assert state(s.memory) is CpuState.RUN


async def test_loopback(sim: Sim) -> None:
    async with client(sim.url) as plc:
        assert await plc.loopback(b"\x12\x34\xab") == b"\x12\x34\xab"
        data = bytes(range(254))
        assert await plc.loopback(data) == data
        for bad in (b"", bytes(255)):
            with pytest.raises(AddressError):
                await plc.loopback(bad)


# -- random access buffer ---------------------------------------------------------------------


async def test_random_buffer(sim: Sim) -> None:
    module = module_of(sim.memory)
    async with client(sim.url) as plc:
        await plc.write_random_buffer(0, [0x1234, 0x5678, 0x9ABC])
        assert module.rab_read(0, 3) == [0x1234, 0x5678, 0x9ABC]
        module.rab_write(6140, [1, 2, 3, 4])  # the PLC program's side
        assert await plc.read_random_buffer(6140, 4) == [1, 2, 3, 4]
        values = [(i * 7) & 0xFFFF for i in range(2500)]  # several messages
        await plc.write_random_buffer(1000, values)
        assert await plc.read_random_buffer(1000, 2500) == values
        sim.memory.state = CpuState.STOP  # the buffer is the E71's: no mode gating
        await plc.write_random_buffer(6143, [9])
        assert await plc.read_random_buffer(6143) == [9]
        for address, count in [(6144, 1), (6143, 2), (-1, 1), (0, 0)]:
            with pytest.raises(AddressError):
                await plc.read_random_buffer(address, count)


async def test_random_buffer_six_char_ascii_form() -> None:
    async with await sim_e71.start(code="ascii") as s:
        module_of(s.memory).rab_ascii_sub_chars = 4
        async with client(s.url + "&rab_ascii_sub_chars=4") as plc:
            assert plc.rab_ascii_sub_chars == 4
            await plc.write_random_buffer(10, [1, 2])
            assert await plc.read_random_buffer(10, 2) == [1, 2]
        with pytest.raises(AddressError):
            client(s.url + "&rab_ascii_sub_chars=3")
        reader, writer = await asyncio.open_connection(s.host, s.port)
        writer.write(b"610017FF0002")
        assert await reader.readexactly(6) == b"E10052"
        writer.close()


async def test_random_buffer_end_codes_raw() -> None:
    async with await sim_e71.start() as s:
        reader, writer = await asyncio.open_connection(s.host, s.port)
        for request, answer in [
            ("61 00 00 18 01 00", "E1 51"),
            ("61 00 FF 17 02 00", "E1 52"),
            ("61 00 00 00 FA 03", "E1 52"),  # 1018 words: more than one message
            ("62 00 00 00 01 00 34 12", "E2 00"),
            ("61 00 00 00 01 00", "E1 00 34 12"),
            ("60 00 00 00", "E0 52"),  # fixed buffer telegram of 0 words
        ]:
            writer.write(bytes.fromhex(request))
            assert await reader.readexactly(len(bytes.fromhex(answer))) == bytes.fromhex(answer)
        writer.close()


# -- special function module buffer memory ------------------------------------------------------


async def test_special_module(sim: Sim) -> None:
    module = module_of(sim.memory)
    buf = module.add_special_module(0x13, 0x800)
    buf[0x7F0:0x7F4] = bytes.fromhex("09182034")
    async with client(sim.url) as plc:
        assert await plc.read_special(0x13, 0x7F0, 4) == bytes.fromhex("09182034")
        await plc.write_special(0x13, 0x750, bytes.fromhex("01234567"))
        assert buf[0x750:0x754] == bytes.fromhex("01234567")
        await plc.write_special_words(0x13, 1, [0x1234, 0xFFFF], offset=0x80)
        assert buf[0x82:0x86] == bytes.fromhex("3412FFFF")
        assert await plc.read_special_words(0x13, 1, 2, offset=0x80) == [0x1234, 0xFFFF]
        assert len(await plc.read_special(0x13, 0x700, 256)) == 256
        assert await error_code(plc.read_special(0x05, 0, 2)) == "5BH/12H"
        assert await error_code(plc.read_special(0x13, 0x7FF, 2)) == "57H"
        assert await error_code(plc.read_special(0x13, 0x800, 1)) == "58H"


# -- extended file registers --------------------------------------------------------------------


async def test_extended_file_registers(sim: Sim) -> None:
    module = module_of(sim.memory)
    async with client(sim.url) as plc:
        await plc.write_ext_file(2, 70, [0x1234, 0x8765, 0x013F])
        assert list(module.ext_blocks[2][70:73]) == [0x1234, 0x8765, 0x013F]
        assert await plc.read_ext_file(2, 70, 3) == [0x1234, 0x8765, 0x013F]
        number = plc.ext_direct_number(2, 70)
        assert number == 8192 + 70
        assert await plc.read_ext_direct(number, 3) == [0x1234, 0x8765, 0x013F]
        await plc.write_ext_direct(8190, [1, 2, 3, 4])  # spans blocks 1 and 2
        assert list(module.ext_blocks[1][8190:]) == [1, 2]
        assert list(module.ext_blocks[2][0:2]) == [3, 4]
        await plc.test_ext_file([(2, 26, 0x1234), (3, 19, 0x0109)])
        assert (module.ext_blocks[2][26], module.ext_blocks[3][19]) == (0x1234, 0x0109)
        await plc.register_monitor_ext([(2, 26), (3, 19)])
        assert await plc.monitor_ext() == [0x1234, 0x0109]
        module.ext_blocks[3][19] = 7
        assert await plc.monitor_ext() == [0x1234, 7]
        assert await error_code(plc.read_ext_file(9, 0, 1)) == "58H"  # block does not exist
        assert await error_code(plc.read_ext_file(33, 0, 1)) == "57H"  # beyond the cassette
        assert await error_code(plc.read_ext_file(1, 8190, 3)) == "57H"
        assert await error_code(plc.read_ext_direct(8 * 8192, 1)) == "58H"
        assert await error_code(plc.read_ext_direct(8 * 8192 - 1, 2)) == "57H"
        with pytest.raises(AddressError):
            await plc.read_ext_file(1, 0, 257)


async def test_extended_file_registers_on_a1_cpu() -> None:
    async with await sim_e71.start(MelsecMemory(CpuGroup.I)) as s, client(s.url) as plc:
        assert await error_code(plc.read_ext_file(1, 0, 1)) == "59H"
        assert await error_code(plc.read_ext_direct(0, 1)) == "59H"


async def test_monitor_registration_is_shared_by_all_connections() -> None:
    async with await sim_e71.start() as s, client(s.url) as a, client(s.url) as b:
        await a.register_monitor_ext([(1, 0)])
        assert await a.monitor_ext() == [0]
        await b.register_monitor_words(["D0"])  # replaces A's 1AH registration (§7.3)
        assert await error_code(a.monitor_ext()) == "57H"
        assert await b.monitor_words() == [0]
        await a.register_monitor_ext([(1, 0), (1, 1)])
        assert await error_code(b.monitor_words()) == "57H"
        assert await a.monitor_ext() == [0, 0]


# -- programs, parameters, comments ([R] layout) -----------------------------------------------


async def test_program_areas_streamed(sim: Sim) -> None:
    module = module_of(sim.memory)
    sim.memory.state = CpuState.STOP
    seen: list[tuple[int, int]] = []
    async with client(sim.url) as plc:
        params = bytes(range(256)) * 3
        await plc.write_area(0x11, 0, list(params), progress=lambda d, t: seen.append((d, t)))
        assert seen[-1] == (768, 768) and len(seen) == 3
        await plc.analyse_parameters()
        assert module.parameter_analyses == 1
        assert bytes(await plc.read_area(0x10, 0, 768, chunk=100)) == params
        steps = list(range(1000))
        await plc.write_area(0x0C, 0, steps)
        assert await plc.read_area(0x0A, 0, 1000) == steps
        await plc.write_area(0x0C, 0xFE00, [10, 0x8002])  # T0 K10, T1 D1
        assert list(module.set_values[0x0A][0:2]) == [10, 0x8002]
        await plc.write_area(0x1D, 0x10, list(b"pump 1"))
        assert bytes(await plc.read_area(0x1C, 0x10, 6)) == b"pump 1"
        await plc.write_area(0x3A, 0, list(b"x" * 300))
        assert bytes(await plc.read_area(0x39, 0, 300)) == b"x" * 300
        await plc.write_area(0x20, 0xE7FE, [1, 2])
        assert await plc.read_area(0x1E, 0xE7FE, 2) == [1, 2]
        await plc.write_area(0x21, 0, [3])
        assert await plc.read_area(0x1F, 0, 1) == [3]
        parts = [p async for p in plc.iter_area(0x1C, 0x10, 6, chunk=4)]
        assert parts == [tuple(b"pump"), tuple(b" 1")]
        assert await error_code(plc.read_area(0x0A, 0x7800, 1)) == "5BH/13H"
        assert await error_code(plc.read_area(0x10, 0xBFF, 2)) == "57H"
        assert await error_code(plc.read_area(0x1E, 0xE800, 1)) == "57H"
        with pytest.raises(AddressError):
            await plc.read_area(0x0C, 0, 1)  # a write command


# -- CPU mode gating exactly as §7.1 ---------------------------------------------------------

Op = Callable[[E71Client], Awaitable[object]]
ALLOW, REFUSE = True, False
# command -> (operation, STOP, RUN/W-en, RUN/W-dis)
GATING: dict[str, tuple[Op, bool, bool, bool]] = {
    "0AH": (lambda p: p.read_area(0x0A, 0, 1), ALLOW, ALLOW, ALLOW),
    "0BH": (lambda p: p.read_area(0x0B, 0, 1), ALLOW, ALLOW, ALLOW),
    "0CH program": (lambda p: p.write_area(0x0C, 0, [1]), ALLOW, REFUSE, REFUSE),
    "0CH set value": (lambda p: p.write_area(0x0C, 0xFE00, [1]), ALLOW, ALLOW, REFUSE),
    "0DH program": (lambda p: p.write_area(0x0D, 0, [1]), ALLOW, REFUSE, REFUSE),
    "0DH set value": (lambda p: p.write_area(0x0D, 0xFF00, [1]), ALLOW, ALLOW, REFUSE),
    "0EH": (lambda p: p.read_special(1, 0, 2), ALLOW, ALLOW, ALLOW),
    "0FH": (lambda p: p.write_special(1, 0, b"\x01"), ALLOW, ALLOW, REFUSE),
    "10H": (lambda p: p.read_area(0x10, 0, 1), ALLOW, ALLOW, ALLOW),
    "11H": (lambda p: p.write_area(0x11, 0, [1]), ALLOW, REFUSE, REFUSE),
    "12H": (lambda p: p.analyse_parameters(), ALLOW, REFUSE, REFUSE),
    "15H": (lambda p: p.cpu_model(), ALLOW, ALLOW, ALLOW),
    "16H": (lambda p: p.loopback(b"\x00"), ALLOW, ALLOW, ALLOW),
    "17H": (lambda p: p.read_ext_file(1, 0, 1), ALLOW, ALLOW, ALLOW),
    "18H": (lambda p: p.write_ext_file(1, 0, [1]), ALLOW, ALLOW, REFUSE),
    "19H": (lambda p: p.test_ext_file([(1, 0, 1)]), ALLOW, ALLOW, REFUSE),
    "1AH": (lambda p: p.register_monitor_ext([(1, 0)]), ALLOW, ALLOW, ALLOW),
    "1CH": (lambda p: p.read_area(0x1C, 0, 1), ALLOW, ALLOW, ALLOW),
    "1DH": (lambda p: p.write_area(0x1D, 0, [1]), ALLOW, ALLOW, REFUSE),
    "1EH": (lambda p: p.read_area(0x1E, 0, 1), ALLOW, ALLOW, ALLOW),
    "1FH": (lambda p: p.read_area(0x1F, 0, 1), ALLOW, ALLOW, ALLOW),  # §13 A12
    "20H": (lambda p: p.write_area(0x20, 0, [1]), ALLOW, REFUSE, REFUSE),
    "21H": (lambda p: p.write_area(0x21, 0, [1]), ALLOW, REFUSE, REFUSE),
    "39H": (lambda p: p.read_area(0x39, 0, 1), ALLOW, ALLOW, ALLOW),
    "3AH": (lambda p: p.write_area(0x3A, 0, [1]), ALLOW, ALLOW, REFUSE),
    "3BH": (lambda p: p.read_ext_direct(0, 1), ALLOW, ALLOW, ALLOW),
    "3CH": (lambda p: p.write_ext_direct(0, [1]), ALLOW, ALLOW, REFUSE),
    "61H": (lambda p: p.read_random_buffer(0, 1), ALLOW, ALLOW, ALLOW),
    "62H": (lambda p: p.write_random_buffer(0, [1]), ALLOW, ALLOW, ALLOW),
}
MODES = {
    "STOP": (CpuState.STOP, True),
    "RUN/W-en": (CpuState.RUN, True),
    "RUN/W-dis": (CpuState.RUN, False),
}


@pytest.mark.parametrize("mode", list(MODES))
async def test_cpu_mode_gating_table_7_1(mode: str) -> None:
    state, write_in_run = MODES[mode]
    column = list(MODES).index(mode) + 1
    async with await sim_e71.start() as s, client(s.url) as plc:
        s.memory.state, s.memory.write_in_run = state, write_in_run
        for name, row in GATING.items():
            op, allowed = row[0], row[column]
            if allowed:
                await op(plc)
            else:
                assert await error_code(op(plc)) == "55H", f"{name} in {mode}"


@pytest.mark.parametrize(
    ("model", "m9050", "m9051", "allowed"),
    [
        (0x94, False, True, True),
        (0x94, True, True, False),
        (0x94, False, False, False),
        (0xA3, False, True, True),
        (0x92, False, True, False),
    ],
)
async def test_program_write_in_run_conditions(
    model: int, m9050: bool, m9051: bool, allowed: bool
) -> None:
    """(*) of §7.1: in RUN only A3/A3N/A3A/A3U/A4U, M9050 OFF, M9051 ON."""
    async with await sim_e71.start() as s, client(s.url) as plc:
        module_of(s.memory).model_code = model
        s.memory.write_bits("M", 9050, [m9050, m9051])
        for command in (0x0C, 0x20):
            if allowed:
                await plc.write_area(command, 0, [1])
            else:
                assert await error_code(plc.write_area(command, 0, [1])) == "55H"


async def test_cpu_type_restrictions() -> None:
    """§7.1: sub programs and microcomputer SUB only on A3-class CPUs, extended comments only on
    AnA/AnU ([R] refused with 58H)."""
    async with await sim_e71.start(MelsecMemory(CpuGroup.V)) as s, client(s.url) as plc:
        assert await error_code(plc.read_area(0x0B, 0, 1)) == "58H"  # A2A: no sub program
        assert await error_code(plc.read_area(0x1F, 0, 1)) == "58H"
        assert await plc.read_area(0x39, 0, 1) == [0]
    async with await sim_e71.start(MelsecMemory(CpuGroup.IV)) as s, client(s.url) as plc:
        assert await error_code(plc.read_area(0x39, 0, 1)) == "58H"  # A3: not AnA/AnU
        assert await plc.read_area(0x0B, 0, 1) == [0]
        assert await plc.read_area(0x1F, 0, 1) == [0]


# -- PC number and undefined subheaders ---------------------------------------------------------


async def test_pc_number_of_a_network_station_gets_5bh_10h() -> None:
    async with await sim_e71.start() as s, client(s.url, pc=5) as plc:
        assert await error_code(plc.cpu_model()) == "5BH/10H"
        assert await error_code(plc.read_ext_file(1, 0, 1)) == "5BH/10H"
        assert await plc.read_random_buffer(0, 1) == [0]  # no PC number in 61H


@pytest.mark.parametrize(
    ("code", "request_", "answer"),
    [
        ("binary", bytes.fromhex("30 FF 0A 00"), bytes.fromhex("B0 50")),
        ("binary", bytes.fromhex("65 FF 0A 00"), bytes.fromhex("E5 50")),
        ("ascii", b"22FF000A", b"A250"),
    ],
)
async def test_undefined_subheaders_get_sub_or_80h_50h(
    code: str, request_: bytes, answer: bytes
) -> None:
    async with await sim_e71.start(code=code) as s:  # type: ignore[arg-type]
        reader, writer = await asyncio.open_connection(s.host, s.port)
        writer.write(request_)
        assert await reader.readexactly(len(answer)) == answer
        writer.write(b"15FF000A" if code == "ascii" else bytes.fromhex("15 FF 0A 00"))
        expected = b"95009400" if code == "ascii" else bytes.fromhex("95 00 94 00")
        assert await reader.readexactly(len(expected)) == expected  # connection kept
        writer.close()


async def test_remote_stop_closes_connections_unless_enabled() -> None:
    """§1.3: without "communication in STOP" (buffer word 496) a STOP closes the connections;
    the client reconnects on its next request."""
    s = await sim_e71.start()
    assert isinstance(s, sim_e71.E71TcpSimulator)
    async with s, client(s.url) as plc:
        module = module_of(s.memory)
        await plc.remote_stop()
        assert len(s.connections) == 1  # enabled (the simulator's default): kept
        await plc.remote_run()
        module.comm_in_stop = False
        await plc.remote_stop()
        for _ in range(500):  # the E71 closes after its answer; wait until the client saw it
            if not s.connections and not plc.transport.is_open:
                break
            await asyncio.sleep(0.01)
        assert not s.connections and not plc.transport.is_open
        assert await plc.read_random_buffer(0, 1) == [0]  # reconnected
        assert plc.stats.connects == 2


async def test_fixed_buffer_telegram_on_the_mc_connection(sim: Sim) -> None:
    """A with-procedure connection also carries 60H (§8.1); the simulated PLC program takes the
    data at once (or answers the end code its handler returns)."""
    module = module_of(sim.memory)
    async with client(sim.url) as plc:
        await plc.send_fixed_buffer([1, 2, 3])
        assert module.fixed_buffer_received == [(1, 2, 3)]
        module.fixed_buffer_handler = lambda words: 0x52 if len(words) > 2 else 0
        assert await error_code(plc.send_fixed_buffer([1, 2, 3])) == "52H"
        await plc.send_fixed_buffer([4])
        assert (await plc.cpu_model())[0] == 0x94  # the connection is still in step
