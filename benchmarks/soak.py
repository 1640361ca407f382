"""Soak: can a gateway run unattended? Pollers with their MQTT sinks under repeated faults.

Setup (all on loopback, started here):

* ``--plcs`` simulated PLCs in this process, of every kind the poller speaks: E71 over TCP and
  UDP, S5-LAN, FETCH/WRITE and AS511 over TCP. Each TCP PLC sits behind a fault proxy of its
  own (an asyncio relay that can cut every connection or hold every byte), each UDP PLC behind a
  relay that loses every datagram while stalled.
* a real mosquitto (``tests/servers.py``), persistent, so queued QoS 1 messages survive its
  restarts;
* two measured child processes, each a ``plcstack poll CONFIG --format influx`` run (the CLI's
  own ``run_poll``, logging and sinks): one with ``[mqtt] mode = "json"`` over the first half of
  the PLCs, one with ``mode = "sparkplug"`` over the second half, both with store-and-forward on
  disk (the Sparkplug one with a small ``buffer_max``, so drops happen and must be counted).
  Influx lines go to a counter instead of stdout (the product writes them to stdout only).
  A sampler task inside each child writes one JSON line every ``--every`` seconds: RSS, open
  descriptors, asyncio tasks, the poller's queue and counters, the sink's queue and counters.
* a subscriber on ``#`` that counts what reaches the broker, per PLC.

Phases: ``--warmup`` seconds quiet, ``--faults`` seconds of faults (one every ``--gap``
seconds, chosen at random with ``--seed``: cut the connections of some PLCs, stall some for a
few seconds past the request timeout, restart some simulators, stop the broker for a while;
``--kinds`` adds ``hang``, the broker frozen with SIGSTOP), then ``--recovery`` seconds quiet.
Checks at the end:

* every PLC was read with good quality after the faults stopped, and the subscriber saw
  messages from every PLC after the faults stopped;
* each sink's accounting closes: submitted = sent + waiting + dropped (no silent loss);
* each state change was said once: per PLC, "offline" and "back online" alternate; per sink,
  the broker's loss is said once per distinct reason while it stays away (the documented rule:
  "connection lost", then "nothing listens there" while it is down) and "connected again" once;
* RSS, descriptors and tasks at the start of the fault phase, its middle and its end, and after
  recovery: growth that does not level off shows here.

    python -m benchmarks.soak                       # 100 PLCs at 2 Hz, about 4 minutes
    python -m benchmarks.soak --plcs 50 --faults 60 --recovery 30 --json soak.json

Needs mosquitto and the ``mqtt`` and ``sparkplug`` extras; run from the repository root.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import os
import random
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from plcstack.sim.melsec_memory import MelsecMemory
from plcstack.sim.s5memory import S5Memory

#: kinds of PLC, in the order they are handed out, with their tags
KINDS = ("e71+tcp", "e71+udp", "s5lan", "fetchwrite", "as511+tcp")
E71_TAGS = {"counter": "D0", "level": "D1", "temp": "D2", "alarms": "M0"}
S5_TAGS = {"counter": "DB10.DW0", "level": "DB10.DW2", "temp": "DB10.DW4", "flags": "MB0"}


# -- the fault proxy -------------------------------------------------------------------------------
class FaultProxy:
    """client -> proxy -> simulator, one per TCP PLC. ``cut()`` aborts every connection now;
    while ``stalled`` no byte moves in either direction (held, delivered after the stall)."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream = ("127.0.0.1", upstream_port)
        self.server: asyncio.Server | None = None
        self.port = 0
        self.stalled = asyncio.Event()  # set = flowing
        self.stalled.set()
        self._conns: set[tuple[asyncio.StreamWriter, asyncio.StreamWriter]] = set()
        self._tasks: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._accept, "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]

    def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.get_running_loop().create_task(self._handle(reader, writer))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            up_reader, up_writer = await asyncio.open_connection(*self.upstream)
        except OSError:
            writer.transport.abort()
            return
        pair = (writer, up_writer)
        self._conns.add(pair)

        async def pump(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
            with contextlib.suppress(ConnectionError, OSError):
                while data := await src.read(65536):
                    await self.stalled.wait()
                    if dst.is_closing():
                        return
                    dst.write(data)

        try:
            pumps = [asyncio.ensure_future(pump(reader, up_writer)),
                     asyncio.ensure_future(pump(up_reader, writer))]  # fmt: skip
            try:
                await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for p in pumps:
                    p.cancel()
                await asyncio.gather(*pumps, return_exceptions=True)
        finally:
            self._conns.discard(pair)
            writer.transport.abort()
            up_writer.transport.abort()

    def cut(self) -> int:
        """Abort every connection through this proxy (both sides); how many."""
        n = len(self._conns)
        for a, b in list(self._conns):
            a.transport.abort()
            b.transport.abort()
        return n

    async def aclose(self) -> None:
        self.stalled.set()
        if self.server is not None:
            self.server.close()
        self.cut()
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.server is not None:
            await self.server.wait_closed()


class UdpRelay:
    """client -> relay -> simulator for a UDP PLC: while ``stalled`` is clear every datagram is
    lost, both ways (UDP has no connection to cut)."""

    def __init__(self, upstream_port: int) -> None:
        self.upstream = ("127.0.0.1", upstream_port)
        self.port = 0
        self.stalled = asyncio.Event()  # set = flowing
        self.stalled.set()
        self._front: asyncio.DatagramTransport | None = None
        self._back: asyncio.DatagramTransport | None = None
        self._client: Any = None

    async def start(self) -> None:
        relay = self

        class Front(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: Any) -> None:
                relay._client = addr
                if relay.stalled.is_set() and relay._back is not None:
                    relay._back.sendto(data)

        class Back(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: Any) -> None:
                front, client = relay._front, relay._client
                if relay.stalled.is_set() and front is not None and client is not None:
                    front.sendto(data, client)

        loop = asyncio.get_running_loop()
        self._front, _ = await loop.create_datagram_endpoint(Front, local_addr=("127.0.0.1", 0))
        self._back, _ = await loop.create_datagram_endpoint(Back, remote_addr=self.upstream)
        self.port = self._front.get_extra_info("sockname")[1]

    def cut(self) -> int:
        return 0

    async def aclose(self) -> None:
        for transport in (self._front, self._back):
            if transport is not None:
                transport.close()


# -- the simulated plant ---------------------------------------------------------------------------
@dataclass
class Plc:
    name: str
    kind: str
    memory: Any
    sim: Any = None
    sim_port: int = 0
    proxy: FaultProxy | UdpRelay | None = None

    @property
    def url(self) -> str:
        assert self.proxy is not None
        return f"{self.kind}://127.0.0.1:{self.proxy.port}"

    @property
    def tags(self) -> dict[str, str]:
        return E71_TAGS if self.kind.startswith("e71") else S5_TAGS

    async def start_sim(self) -> None:
        """Start (or restart, on the same port) this PLC's simulator."""
        from plcstack.sim import as511, e71, fetchwrite, s5lan

        port = self.sim_port
        if self.kind == "e71+tcp":
            self.sim = await e71.start(self.memory, port=port)
        elif self.kind == "e71+udp":
            self.sim = await e71.start(self.memory, port=port, transport="udp")
        elif self.kind == "s5lan":
            self.sim = await s5lan.start(self.memory, port=port)
        elif self.kind == "fetchwrite":
            self.sim = await fetchwrite.start(self.memory, port=port)
        else:
            self.sim = await as511.start(self.memory, port=port)
        self.sim_port = self.sim.port

    async def stop_sim(self) -> None:
        if self.sim is not None:
            sim, self.sim = self.sim, None
            await sim.aclose()


def new_plc(i: int) -> Plc:
    kind = KINDS[i % len(KINDS)]
    memory: Any
    if kind.startswith("e71"):
        memory = MelsecMemory()
        memory.write_words("D", 0, [i, 100 + i, 20])
    else:
        memory = S5Memory(default_dbs={10: 16})
        memory.write_db_words(10, 0, [i, 100 + i, 20])
    return Plc(f"plc{i:03d}-{kind.split('+')[0]}", kind, memory)


def config_text(
    plcs: list[Plc], mqtt: str, mode: str, buffer: Path, interval: float, buffer_max: int
) -> str:
    lines = [
        "[poll]",
        f"interval = {interval}",
        "timeout = 1.0",
        "connect_timeout = 1.0",
        "backoff_max = 2.0",
        "",
        "[mqtt]",
        f'url = "{mqtt}"',
        f'mode = "{mode}"',
        f'client_id = "soak-{mode}"',
        f'buffer_path = "{buffer}"',
        "buffer_memory = 65536",
        f"buffer_max = {buffer_max}",
        "reconnect_max = 2.0",
        "keepalive = 5",
    ]
    if mode == "sparkplug":
        lines += ['group_id = "soak"']
    for plc in plcs:
        lines += ["", "[[plc]]", f'name = "{plc.name}"', f'url = "{plc.url}"', "", "[plc.tags]"]
        for tag, address in plc.tags.items():
            kind = "bool" if tag == "alarms" else ("uint8" if tag == "flags" else "uint16")
            lines.append(f'{tag} = {{ address = "{address}", type = "{kind}" }}')
    return "\n".join(lines) + "\n"


# -- the measured child ----------------------------------------------------------------------------
class _CountingOut(io.TextIOBase):
    """Stands for stdout: counts the Influx lines instead of printing them."""

    def __init__(self) -> None:
        self.lines = 0

    def write(self, text: str) -> int:
        self.lines += text.count("\n")
        return len(text)


def child(config: str, duration: float, every: float, out_path: str) -> int:
    """``plcstack poll CONFIG --format influx`` in this process, with a sampler beside it."""
    import plcstack.cli.poll as cli_poll
    from plcstack.cli import build_parser
    from plcstack.logs import configure
    from plcstack.north.pipeline import North

    captured: dict[str, Any] = {}

    class Captured(North):
        """The run's North, remembered for the sampler."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            captured["north"] = self

    setattr(cli_poll, "North", Captured)  # noqa: B010 - the CLI module's name, replaced
    counting = _CountingOut()
    args = build_parser().parse_args(
        ["poll", config, "--format", "influx", "--duration", str(duration)]
    )
    undo = configure("warning")

    started = time.monotonic()

    trace_at = float(os.environ.get("PLCSTACK_SOAK_TRACE", "0") or 0)
    first: list[tracemalloc.Snapshot] = []
    if trace_at:
        tracemalloc.start(8)

    async def sample(out: Any) -> None:
        while True:
            if trace_at and not first and time.monotonic() - started >= trace_at:
                first.append(tracemalloc.take_snapshot())
            north = captured.get("north")
            if north is not None:
                out.write(json.dumps(snapshot(north, started, counting.lines)) + "\n")
                out.flush()
            await asyncio.sleep(every)

    async def run(out: Any) -> int:
        sampler = asyncio.create_task(sample(out))
        try:
            return await cli_poll.run_poll(args, out=counting)  # type: ignore[arg-type]
        finally:
            sampler.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sampler
            north = captured.get("north")
            if north is not None:
                final = snapshot(north, started, counting.lines)
                final["final"] = True
                out.write(json.dumps(final) + "\n")
            if first:  # what grew between the end of the warm-up and the end, by line
                first.append(tracemalloc.take_snapshot())

    try:
        with open(out_path, "w") as out:
            code = asyncio.run(run(out))
        if len(first) == 2:
            grown = first[1].compare_to(first[0], "lineno")
            Path(out_path + ".trace").write_text("".join(f"{stat}\n" for stat in grown[:30]))
        return code
    finally:
        undo()


def rss_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return -1


def snapshot(north: Any, started: float, influx_lines: int) -> dict[str, Any]:
    poller = north.poller
    stats = poller.stats
    total: Counter[str] = Counter()
    for st in stats.values():
        for key in ("requests", "errors", "reconnects", "connect_failures", "drops", "scans"):
            total[key] += getattr(st, key)
    sink = north.mqtt
    s = sink.stats
    return {
        "t": round(time.monotonic() - started, 1),
        "rss_kib": rss_kib(),
        "fds": len(os.listdir("/proc/self/fd")),
        "tasks": len(asyncio.all_tasks()),
        "pending": poller.pending(),
        "poller_dropped": poller.dropped,
        "plc": dict(total),
        "sink": {
            "submitted": s.submitted,
            "sent": s.sent,
            "buffered": s.buffered,
            "replayed": s.replayed,
            "connects": s.connects,
            "disconnects": s.disconnects,
            "failures": s.failures,
            "waiting": len(sink.buffer),
            "on_disk": sink.buffer.on_disk,
            "dropped": sink.buffer.dropped,
            "connected": sink.connected,
        },
        "sink_errors": dict(north.supervisor.errors),
        "influx_lines": influx_lines,
    }


# -- the subscriber --------------------------------------------------------------------------------
class Seen:
    """Messages that reached the broker, per PLC name found in the topic, with the time."""

    def __init__(self, names: list[str]) -> None:
        self.names = set(names)
        self.last: dict[str, float] = {}
        self.count = 0

    def saw(self, topic: str) -> None:
        self.count += 1
        for level in topic.split("/"):
            if level in self.names:
                self.last[level] = time.monotonic()


async def subscribe(port: int, seen: Seen) -> None:
    import aiomqtt

    while True:
        try:
            async with aiomqtt.Client("127.0.0.1", port, identifier="soak-watch") as client:
                await client.subscribe("#", qos=0)
                async for message in client.messages:
                    seen.saw(str(message.topic))
        except aiomqtt.MqttError:
            await asyncio.sleep(0.5)


# -- the faults ------------------------------------------------------------------------------------
@dataclass
class Faults:
    plcs: list[Plc]
    broker: Any
    rng: random.Random
    kinds: tuple[str, ...] = ("cut", "cut", "stall", "restart", "restart", "broker")
    log: list[dict[str, Any]] = field(default_factory=list)
    tasks: set[asyncio.Task[None]] = field(default_factory=set)

    def _later(self, coro: Any) -> None:
        task = asyncio.create_task(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    def _some(self, kinds: tuple[str, ...] | None = None) -> list[Plc]:
        pool = [p for p in self.plcs if kinds is None or p.kind in kinds]
        return self.rng.sample(pool, max(1, len(pool) // 10))

    async def one(self, t: float) -> None:
        what = self.rng.choice(self.kinds)
        tcp = tuple(k for k in KINDS if k != "e71+udp")
        if what == "cut":
            chosen = self._some(tcp)
            cut = sum(p.proxy.cut() for p in chosen if p.proxy is not None)
            self.log.append({"t": t, "fault": "cut", "plcs": [p.name for p in chosen], "n": cut})
        elif what == "stall":
            chosen = self._some()
            hold = self.rng.uniform(2.0, 5.0)
            for p in chosen:
                assert p.proxy is not None
                p.proxy.stalled.clear()
            self._later(self._resume(chosen, hold))
            self.log.append({"t": t, "fault": "stall", "plcs": [p.name for p in chosen],
                             "seconds": round(hold, 1)})  # fmt: skip
        elif what == "restart":
            chosen = self._some()
            down = self.rng.uniform(1.0, 4.0)
            for p in chosen:
                await p.stop_sim()
            self._later(self._restart(chosen, down))
            self.log.append({"t": t, "fault": "restart", "plcs": [p.name for p in chosen],
                             "seconds": round(down, 1)})  # fmt: skip
        elif what == "hang":  # the broker process stopped (SIGSTOP): a host that hangs
            proc = self.broker._proc
            if proc is None:
                return
            hold = self.rng.uniform(8.0, 15.0)
            proc.send_signal(signal.SIGSTOP)
            self._later(self._broker_cont(proc, hold))
            self.log.append({"t": t, "fault": "hang", "seconds": round(hold, 1)})
        else:
            if not self.broker.running:
                return
            down = self.rng.uniform(3.0, 8.0)
            await asyncio.to_thread(self.broker.stop)
            self._later(self._broker_back(down))
            self.log.append({"t": t, "fault": "broker", "seconds": round(down, 1)})

    async def _resume(self, plcs: list[Plc], after: float) -> None:
        await asyncio.sleep(after)
        for p in plcs:
            assert p.proxy is not None
            p.proxy.stalled.set()

    async def _restart(self, plcs: list[Plc], after: float) -> None:
        await asyncio.sleep(after)
        for p in plcs:
            await p.start_sim()

    async def _broker_cont(self, proc: subprocess.Popen[bytes], after: float) -> None:
        await asyncio.sleep(after)
        proc.send_signal(signal.SIGCONT)

    async def _broker_back(self, after: float) -> None:
        await asyncio.sleep(after)
        await asyncio.to_thread(self.broker.start)

    async def settle(self) -> None:
        await asyncio.gather(*self.tasks)


# -- the logs --------------------------------------------------------------------------------------
OFFLINE = re.compile(r"PLC (\S+) is offline")
ONLINE = re.compile(r"PLC (\S+) is back online")
LOST = re.compile(r"MQTT broker \S+ .*retrying with backoff")
AGAIN = re.compile(r"connected to \S+ again")


def log_findings(text: str) -> dict[str, Any]:
    """Per PLC and per sink, whether each state change was said exactly once (alternating
    lines), and the other WARNING/ERROR lines by their shape (numbers and names masked)."""
    state: dict[str, bool] = {}
    repeats: list[str] = []
    offline = online = lost = again = 0
    broker_up = True
    reasons: set[str] = set()
    shapes: Counter[str] = Counter()
    for line in text.splitlines():
        if m := OFFLINE.search(line):
            offline += 1
            if state.get(m[1]) is False:
                repeats.append(line)
            state[m[1]] = False
        elif m := ONLINE.search(line):
            online += 1
            if state.get(m[1], True) is True:
                repeats.append(line)
            state[m[1]] = True
        elif LOST.search(line):
            lost += 1  # the loss, then each new reason while it stays away (docs/north.md)
            reason = line.split(": ", 2)[-1]
            if broker_up:
                reasons = set()
            elif reason in reasons:
                repeats.append(line)
            reasons.add(reason)
            broker_up = False
        elif AGAIN.search(line):
            again += 1
            if broker_up:
                repeats.append(line)
            broker_up = True
        elif " WARNING " in line or " ERROR " in line:
            shapes[re.sub(r"\d+(\.\d+)?", "N", line)[:160]] += 1
    return {
        "offline": offline,
        "online": online,
        "broker_lost": lost,
        "broker_again": again,
        "repeated": repeats[:20],
        "repeated_n": len(repeats),
        "still_offline": sorted(p for p, up in state.items() if not up),
        "other": shapes.most_common(15),
    }


# -- the run ---------------------------------------------------------------------------------------
def figures(samples: list[dict[str, Any]], t: float) -> dict[str, Any]:
    """The sample nearest to ``t`` seconds."""
    best = min(samples, key=lambda s: abs(s["t"] - t))
    return {k: best[k] for k in ("t", "rss_kib", "fds", "tasks", "pending")}


async def soak(args: argparse.Namespace) -> dict[str, Any]:
    from tests.servers import Mosquitto

    rng = random.Random(args.seed)
    plcs = [new_plc(i) for i in range(args.plcs)]
    for p in plcs:
        await p.start_sim()
        p.proxy = UdpRelay(p.sim_port) if p.kind == "e71+udp" else FaultProxy(p.sim_port)
        await p.proxy.start()
    broker = Mosquitto()
    await asyncio.to_thread(broker.start)
    workdir = Path(tempfile.mkdtemp(prefix="plcstack-soak-"))
    half = len(plcs) // 2
    total = args.warmup + args.faults + args.recovery
    children = []
    for mode, part, budget in (("json", plcs[:half], 64 << 20), ("sparkplug", plcs[half:], 4096)):
        config = workdir / f"{mode}.toml"
        config.write_text(
            config_text(part, broker.url, mode, workdir / f"{mode}.db", args.interval, budget)
        )
        children.append((mode, *spawn(workdir, mode, config, total, args.every)))
    seen = Seen([p.name for p in plcs])
    watcher = asyncio.create_task(subscribe(broker.port, seen))
    faults = Faults(plcs, broker, rng, kinds=tuple(args.kinds.split(",")))
    t0 = time.monotonic()
    progress(f"soak: {len(plcs)} PLCs, {args.interval} s, faults for {args.faults} s in {workdir}")
    try:
        await asyncio.sleep(args.warmup)
        end_faults = t0 + args.warmup + args.faults
        while time.monotonic() < end_faults:
            await faults.one(round(time.monotonic() - t0, 1))
            await asyncio.sleep(rng.uniform(0.5, 1.5) * args.gap)
        await faults.settle()
        if not broker.running:
            await asyncio.to_thread(broker.start)
        quiet = time.monotonic()
        progress(f"soak: {len(faults.log)} faults; recovering for {args.recovery} s")
        for _, proc, _ in children:
            await asyncio.to_thread(proc.wait)
        seen_after = sorted(p.name for p in plcs if seen.last.get(p.name, 0) > quiet + 5)
    finally:
        for _, proc, err in children:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=30)
            err.close()
        watcher.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await watcher
        for p in plcs:
            if p.proxy is not None:
                await p.proxy.aclose()
            await p.stop_sim()
        await asyncio.to_thread(broker.close)
    report: dict[str, Any] = {"faults": faults.log, "children": {}, "workdir": str(workdir)}
    report["warmup"] = args.warmup
    report["mqtt_seen_after_faults"] = len(seen_after)
    report["mqtt_missing_after_faults"] = sorted({p.name for p in plcs} - set(seen_after))
    for mode, proc, _ in children:
        samples = [json.loads(x) for x in (workdir / f"{mode}.jsonl").read_text().splitlines()]
        final = samples[-1]
        ticks = [s for s in samples if not s.get("final")]
        sink = final["sink"]
        w, f = args.warmup, args.faults
        report["children"][mode] = {
            "exit": proc.returncode,
            "curve": {
                "start": figures(ticks, w),
                "middle": figures(ticks, w + f / 2),
                "end_of_faults": figures(ticks, w + f),
                "after_recovery": figures(ticks, total - 2 * args.every),  # before the stop
                "peak_rss_kib": max(s["rss_kib"] for s in ticks),
                "peak_fds": max(s["fds"] for s in ticks),
                "peak_tasks": max(s["tasks"] for s in ticks),
            },
            "final": final,
            "unaccounted": sink["submitted"] - sink["sent"] - sink["waiting"] - sink["dropped"],
            "log": log_findings((workdir / f"{mode}.log").read_text(errors="replace")),
            "series": [
                (s["t"], s["rss_kib"], s["fds"], s["tasks"], s["sink"]["waiting"]) for s in ticks
            ],
        }
    return report


def spawn(
    workdir: Path, mode: str, config: Path, total: float, every: float
) -> tuple[subprocess.Popen[bytes], Any]:
    """One measured child, its log in ``workdir/MODE.log``, its samples in ``MODE.jsonl``."""
    err = open(workdir / f"{mode}.log", "wb")  # noqa: SIM115 - closed by the caller
    cmd = [sys.executable, "-m", "benchmarks.soak", "child", str(config), str(total),
           str(every), str(workdir / f"{mode}.jsonl")]  # fmt: skip
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err), err


def progress(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def verdicts(report: dict[str, Any]) -> list[str]:
    """What a user would call a defect, one line each (empty: the run was clean)."""
    out = []
    if report["mqtt_missing_after_faults"]:
        missing = report["mqtt_missing_after_faults"]
        out.append(f"no MQTT message after the faults from {len(missing)} PLCs: {missing[:5]}")
    for mode, c in report["children"].items():
        log = c["log"]
        if c["exit"] != 0:
            out.append(f"{mode}: exit {c['exit']}")
        if c["unaccounted"] != 0:
            out.append(f"{mode}: {c['unaccounted']} messages neither sent, waiting nor dropped")
        if log["repeated_n"]:
            out.append(f"{mode}: {log['repeated_n']} repeated state lines, e.g. {log['repeated']}")
        if log["still_offline"]:
            out.append(f"{mode}: still offline at the end: {log['still_offline']}")
        curve = c["curve"]
        mid, end = curve["middle"], curve["after_recovery"]
        # tasks and descriptors come and go with the MQTT window, outages and reconnects: a
        # leak moves their median, of the first and of the last third of the run
        series = [x for x in c["series"] if x[0] >= report.get("warmup", 0)] or c["series"]
        third = max(1, len(series) // 3)
        for what, i in (("descriptors", 2), ("tasks", 3)):
            first = statistics.median(x[i] for x in series[:third])
            last = statistics.median(x[i] for x in series[-third:])
            if last > first + 2:
                out.append(f"{mode}: the median number of {what} rose from {first} to {last}")
        if end["rss_kib"] > mid["rss_kib"] * 1.2 and end["rss_kib"] > curve["start"]["rss_kib"]:
            out.append(f"{mode}: RSS still growing: {mid['rss_kib']} -> {end['rss_kib']} KiB")
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["child"]:
        config, duration, every, out = argv[1:5]
        return child(config, float(duration), float(every), out)
    parser = argparse.ArgumentParser(prog="python -m benchmarks.soak", description=__doc__)
    parser.add_argument("--plcs", type=int, default=100)
    parser.add_argument("--interval", type=float, default=0.5, help="scan interval, seconds")
    parser.add_argument("--warmup", type=float, default=20.0)
    parser.add_argument("--faults", type=float, default=150.0)
    parser.add_argument("--recovery", type=float, default=40.0)
    parser.add_argument("--gap", type=float, default=5.0, help="mean seconds between faults")
    parser.add_argument("--every", type=float, default=3.0, help="seconds between samples")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--kinds",
        default="cut,cut,stall,restart,restart,broker",
        help="faults to draw from (repeat one to make it likelier); also: hang (the broker"
        " stopped with SIGSTOP for 8-15 s)",
    )
    parser.add_argument("--json", default=None, help="write the whole report here")
    parser.add_argument(
        "--trace",
        action="store_true",
        help="tracemalloc in the children: what grew from the end of the warm-up to the end,"
        " by source line, in WORKDIR/MODE.jsonl.trace (slower)",
    )
    args = parser.parse_args(argv)
    if args.trace:
        os.environ["PLCSTACK_SOAK_TRACE"] = str(args.warmup)
    report = asyncio.run(soak(args))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    for mode, c in report["children"].items():
        print(f"== {mode}: exit {c['exit']}")
        print("   curve:", json.dumps(c["curve"]))
        print("   final:", json.dumps(c["final"]))
        print("   log:", json.dumps({k: v for k, v in c["log"].items() if k != "other"}))
        for shape, n in c["log"]["other"]:
            print(f"   {n:6d} x {shape}")
    print(f"faults: {Counter(f['fault'] for f in report['faults'])}")
    print(f"MQTT: messages after the faults from {report['mqtt_seen_after_faults']} PLCs")
    problems = verdicts(report)
    for line in problems:
        print("DEFECT:", line)
    print("clean" if not problems else f"{len(problems)} defects")
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
