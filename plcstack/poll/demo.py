"""The demo plant: in-process simulators of every protocol built so far, each running a small
PLC program (a counter, a sine, a float temperature, a running light), and a poll config for them.

Protocols are found through :data:`PROTOCOLS`: an entry whose simulator or client module is not
part of this installation yet is skipped with a note, and picked up as soon as the module exists,
so the demo grows with the stack without being edited.
"""

from __future__ import annotations

import asyncio
import importlib
import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.values import BOOL, FLOAT32, INT16, KG, RAW, UINT16, Endian

__all__ = ["PROTOCOLS", "DemoPlant", "DemoProtocol", "available_protocols", "start_plant"]

#: how often the PLC programs update their memory (seconds)
PROGRAM_TICK = 0.1


def _sine(t: float, amplitude: float, period: float) -> float:
    return amplitude * math.sin(2 * math.pi * t / period)


def _float_words_low_first(value: float) -> list[int]:
    """An IEEE float as MELSEC keeps it (D2 low word, D3 high word)."""
    return [int(p) for p in FLOAT32.encode(value, 16, Endian.LITTLE)]


def _kg_words(value: float) -> list[int]:
    """An S5 KG real as the CPU keeps it (exponent in the high byte of the first word)."""
    return [int(p) for p in KG.encode(value, 16, Endian.BIG)]


# -- PLC programs: memory, tick number, seconds since start --------------------------------------
def melsec_memory() -> Any:
    # imported by name: the module lands with the E71 protocol and may be absent here
    return importlib.import_module("plcstack.sim.melsec_memory").MelsecMemory()


def melsec_program(mem: Any, tick: int, t: float) -> None:
    sine = round(_sine(t, 1000, 10.0))
    mem.write_words("D", 0, [tick & 0xFFFF, sine & 0xFFFF])
    mem.write_words("D", 2, _float_words_low_first(20.0 + _sine(t, 5.0, 30.0)))
    light = (tick // 5) % 8
    mem.write_bits("M", 0, [i == light for i in range(8)])


MELSEC_TAGS = (
    TagConfig("counter", "D0", UINT16),
    TagConfig("sine", "D1", INT16),
    TagConfig("temp", "D2", FLOAT32),
    TagConfig("light", "M0", BOOL, 8),
)


def s5_memory() -> Any:
    from plcstack.sim.s5memory import S5Memory

    return S5Memory(default_dbs={10: 16})


def s5_program(mem: Any, tick: int, t: float) -> None:
    from plcstack.sim.s5memory import Area

    sine = round(_sine(t, 1000, 10.0))
    words = [tick & 0xFFFF, sine & 0xFFFF, *_kg_words(20.0 + _sine(t, 5.0, 30.0))]
    mem.write_db_words(10, 0, words)
    light = (tick // 5) % 8
    mem.write_area(Area.FLAGS, 0, bytes([1 << light]))


S5_TAGS = (
    TagConfig("counter", "DB10.DW0", UINT16),
    TagConfig("sine", "DB10.DW1", INT16),
    TagConfig("temp", "DB10.DW2", KG),
    TagConfig("light", "MB0", RAW),
)


@dataclass(frozen=True)
class DemoProtocol:
    """One protocol variant of the demo: how to start its simulator and what to poll."""

    label: str
    sim_module: str
    client_module: str
    start_options: dict[str, Any]
    memory: Callable[[], Any]
    program: Callable[[Any, int, float], None]
    tags: tuple[TagConfig, ...]
    #: name of the sim module's start function (a pty variant may have its own)
    start_function: str = "start"
    #: memory modules the program needs besides the sim module
    needs: tuple[str, ...] = ()


def _e71(transport: str, code: str) -> DemoProtocol:
    """One E71 variant: the four differ only in transport and code."""
    return DemoProtocol(
        f"e71-{transport}-{'bin' if code == 'binary' else code}",
        "plcstack.sim.e71",
        "plcstack.clients.e71",
        {"transport": transport, "code": code},
        melsec_memory,
        melsec_program,
        MELSEC_TAGS,
        needs=("plcstack.sim.melsec_memory",),
    )


PROTOCOLS: tuple[DemoProtocol, ...] = (
    *(_e71(transport, code) for transport in ("tcp", "udp") for code in ("binary", "ascii")),
    DemoProtocol(
        "s5lan", "plcstack.sim.s5lan", "plcstack.clients.s5lan", {}, s5_memory, s5_program, S5_TAGS
    ),
    DemoProtocol(
        "fetchwrite-mk",
        "plcstack.sim.fetchwrite",
        "plcstack.clients.fetchwrite",
        {"mk": True},
        s5_memory,
        s5_program,
        S5_TAGS,
    ),
    DemoProtocol(
        "as511-pty",
        "plcstack.sim.as511",
        "plcstack.clients.as511",
        {},
        s5_memory,
        s5_program,
        S5_TAGS,
        start_function="start_pty",
    ),
)


def _importable(name: str) -> str | None:
    """None if the module imports, else why not (a module not built yet is the normal case)."""
    try:
        importlib.import_module(name)
    except ModuleNotFoundError as exc:
        if exc.name == name:
            return f"{name} is not part of this installation yet"
        return f"{name} cannot be imported: {exc}"
    except Exception as exc:  # a broken module must not stop the demo of the others
        return f"{name} cannot be imported: {type(exc).__name__}: {exc}"
    return None


def available_protocols(
    protocols: tuple[DemoProtocol, ...] = PROTOCOLS,
) -> tuple[list[DemoProtocol], list[str]]:
    """The protocol variants whose modules exist, and a note for each one skipped."""
    found: list[DemoProtocol] = []
    notes: list[str] = []
    for proto in protocols:
        reason = None
        for module in (proto.sim_module, proto.client_module, *proto.needs):
            reason = _importable(module)
            if reason is not None:
                break
        if reason is None:
            sim = importlib.import_module(proto.sim_module)
            starter = getattr(sim, proto.start_function, None)
            if starter is None:
                reason = f"{proto.sim_module} has no {proto.start_function}()"
            else:
                unknown = _unsupported_options(starter, proto.start_options)
                if unknown:
                    reason = f"{proto.sim_module}.{proto.start_function}() takes no {unknown}"
        if reason is None:
            found.append(proto)
        else:
            notes.append(f"{proto.label}: skipped ({reason})")
    return found, notes


def _unsupported_options(starter: Callable[..., Any], options: dict[str, Any]) -> str | None:
    try:
        params = inspect.signature(starter).parameters
    except (TypeError, ValueError):
        return None
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return None
    missing = [k for k in options if k not in params]
    return ", ".join(missing) if missing else None


@dataclass
class DemoPlc:
    name: str
    protocol: DemoProtocol
    sim: Any
    memory: Any


@dataclass
class DemoPlant:
    """Running simulators and their programs; ``config`` polls all of them."""

    plcs: list[DemoPlc]
    notes: list[str]
    interval: float
    #: what runs beside the simulators (the PLC programs); ``aclose`` cancels and awaits it
    tasks: list[asyncio.Task[None]] = field(default_factory=list)

    @property
    def config(self) -> PollConfig:
        return PollConfig(
            tuple(
                PlcConfig(p.name, p.sim.url, p.protocol.tags, timeout=1.0, connect_timeout=1.0)
                for p in self.plcs
            ),
            {"default": self.interval},
            concurrency=64,
        )

    async def aclose(self) -> None:
        for task in self.tasks:
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        await asyncio.gather(*(p.sim.aclose() for p in self.plcs), return_exceptions=True)


async def _run_program(plcs: list[DemoPlc]) -> None:
    """One task drives every PLC program, so 100 simulated PLCs cost one timer, not 100."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    tick = 0
    while True:
        t = loop.time() - start
        for plc in plcs:
            try:
                plc.protocol.program(plc.memory, tick, t)
            except Exception:  # a program bug in one simulator must not stop the others
                continue
        tick += 1
        await asyncio.sleep(max(0.0, start + tick * PROGRAM_TICK - loop.time()))


async def start_plant(plcs: int | None = None, *, interval: float = 0.25) -> DemoPlant:
    """Start ``plcs`` simulators spread round-robin over the available protocol variants
    (default: one of each), their programs, and return the plant."""
    protocols, notes = available_protocols()
    if not protocols:
        return DemoPlant([], notes, interval)
    total = len(protocols) if plcs is None else plcs
    started: list[DemoPlc] = []
    failed: set[str] = set()
    plant = DemoPlant(started, notes, interval)
    try:
        for i in range(total):
            proto = protocols[i % len(protocols)]
            if proto.label in failed:
                continue
            memory = proto.memory()
            proto.program(memory, 0, 0.0)
            module = importlib.import_module(proto.sim_module)
            try:
                sim = await getattr(module, proto.start_function)(memory, **proto.start_options)
            except Exception as exc:
                failed.add(proto.label)
                notes.append(f"{proto.label}: skipped (simulator did not start: {exc})")
                continue
            number = i // len(protocols) + 1
            started.append(DemoPlc(f"{proto.label}-{number}", proto, sim, memory))
    except BaseException:
        await plant.aclose()
        raise
    plant.tasks.append(asyncio.create_task(_run_program(started), name="demo PLC programs"))
    return plant
