"""The MQTT sink under load: 1000 PLCs x 10 tags at 1 Hz into a real mosquitto.

Setup: a mosquitto on a free loopback port (started here; Debian package ``mosquitto``), one
:class:`~plcstack.north.mqtt.MqttSink` (JSON layout, QoS 1, store-and-forward on disk) fed through
the :class:`~plcstack.north.pipeline.North` path (metrics, report-by-exception, fan-out) with
fake samples: each "scan" is one PLC's 10 tags (ints, floats, bools). No PLC I/O: what is
measured is what the north side adds.

Measured:

* **paced**: ``--plcs`` x ``--tags`` at 1 Hz for ``--seconds``: every second each PLC hands over one
  scan (spread over the second). Reported: samples/s delivered (acknowledged by the broker),
  the backlog at the end (0 = it keeps up), CPU of this process per sample (``process_time`` of
  the run minus that of generating the same samples without a sink, divided by samples), and
  mosquitto's CPU from /proc;
* **flat out**: ``--burst`` samples submitted at once, time until the broker acknowledged the
  last: the ceiling of one sink (one connection, ``inflight`` 64 messages in flight).

    python -m benchmarks.mqtt_sink [--plcs 1000] [--tags 10] [--seconds 10] [--burst 100000]
    python -m benchmarks.mqtt_sink --rbe        # with report-by-exception (deadband 0.5)
    python -m benchmarks.mqtt_sink --broker-nodelay   # mosquitto with set_tcp_nodelay true
"""

from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from plcstack.north.config import NorthConfig
from plcstack.north.mqtt import MqttSettings
from plcstack.north.pipeline import North
from plcstack.north.rbe import PASS_ALL, ReportPolicy
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Sample, Scan


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def start_mosquitto(workdir: Path, nodelay: bool = False) -> tuple[subprocess.Popen[bytes], int]:
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    conf = workdir / "mosquitto.conf"
    user = ["user root"] if os.geteuid() == 0 else []
    nodelay_line = ["set_tcp_nodelay true"] if nodelay else []
    lines = [f"listener {port} 127.0.0.1", "allow_anonymous true", *nodelay_line, *user]
    conf.write_text("\n".join(lines) + "\n")
    proc = subprocess.Popen(
        [binary, "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return proc, port
        except OSError:
            time.sleep(0.05)
    proc.kill()
    raise SystemExit(f"mosquitto ({binary}) did not start on 127.0.0.1:{port}")


def idle_poller(plcs: int, tags: int) -> Poller:
    """A Poller of the benchmark's PLCs, never started (the samples come from the benchmark):
    what the runtime reads of it is its configuration, its PLCs and tags, its statistics."""
    tag_configs = tuple(TagConfig(f"t{j}", f"D{j}") for j in range(tags))
    plc_configs = tuple(
        PlcConfig(f"plc{i:04d}", "e71+tcp://127.0.0.1:1", tag_configs) for i in range(plcs)
    )
    return Poller(PollConfig(plc_configs))


def scan(plc: str, tags: int, t: float, k: int) -> list[Scan]:
    """One PLC's scan: a third ints, a third floats, a third bools, values that move."""
    out = []
    for j in range(tags):
        kind = j % 3
        value: Any = k + j if kind == 0 else (k * 0.1 + j if kind == 1 else (k + j) % 2 == 0)
        out.append(Sample(plc, f"t{j}", value, Quality.GOOD, t, t + 0.002, None))
    return [Scan(plc, "default", t, t + 0.002, tuple(out))]


async def drive(north: North, plcs: list[str], tags: int, seconds: int) -> int:
    """Hand over one scan per PLC per second, spread over the second; returns samples reported."""
    step = 1.0 / len(plcs)
    reported = 0
    for second in range(seconds):
        start = time.perf_counter()
        for k, name in enumerate(plcs):
            passed = north.deliver(scan(name, tags, time.time(), second * 7 + k))
            reported += sum(len(s.samples) for s in passed)
            delay = start + (k + 1) * step - time.perf_counter()
            if delay > 0.002 or k % 50 == 49:
                await asyncio.sleep(max(0.0, delay))
    return reported


async def paced(args: argparse.Namespace, port: int, broker_pid: int, workdir: Path) -> None:
    poller = idle_poller(args.plcs, args.tags)
    report: Any = ReportPolicy(deadband=0.5) if args.rbe else PASS_ALL
    # baseline: the same pacing, samples, metrics and RBE, without the sink
    async with North(poller, NorthConfig(report=report)) as bare:
        cpu0 = time.process_time()
        await drive(bare, poller.plcs, args.tags, args.seconds)
        baseline = time.process_time() - cpu0

    settings = MqttSettings(
        host="127.0.0.1", port=port, client_id="bench", buffer_path=str(workdir / "q.sqlite")
    )
    async with North(poller, NorthConfig(mqtt=settings, report=report)) as north:
        assert north.mqtt is not None
        await north.mqtt.wait_connected(10)
        cpu0, broker0, wall0 = time.process_time(), cpu_seconds(broker_pid), time.perf_counter()
        reported = await drive(north, poller.plcs, args.tags, args.seconds)
        backlog_end = len(north.mqtt.buffer)
        await north.mqtt.wait_drained(60)
        wall = time.perf_counter() - wall0
        cpu = time.process_time() - cpu0
        broker = cpu_seconds(broker_pid) - broker0
        stats = north.mqtt.stats
    samples = args.seconds * args.plcs * args.tags
    sink_cpu = cpu - baseline
    print(
        f"paced {args.plcs} PLCs x {args.tags} tags at 1 Hz for {args.seconds} s"
        f" (rbe {'on' if args.rbe else 'off'}):\n"
        f"  samples {samples} ({samples / wall:,.0f}/s over {wall:.1f} s), reported {reported},"
        f" messages sent {stats.sent}, backlog when pacing ended {backlog_end}\n"
        f"  this process CPU {cpu:.2f} s ({100 * cpu / wall:.0f} % of a core);"
        f" the same run without the sink {baseline:.2f} s\n"
        f"  sink CPU per sample {1e6 * sink_cpu / samples:.1f} us"
        f" (per message {1e6 * sink_cpu / max(1, stats.sent):.0f} us);"
        f" mosquitto CPU {broker:.2f} s ({100 * broker / wall:.0f} % of a core)"
    )


async def burst(args: argparse.Namespace, port: int, workdir: Path) -> None:
    poller = idle_poller(args.plcs, args.tags)
    settings = MqttSettings(
        host="127.0.0.1", port=port, client_id="bench-burst", buffer_path=str(workdir / "b.sqlite")
    )
    north = North(poller, NorthConfig(mqtt=settings))
    async with north:
        assert north.mqtt is not None
        await north.mqtt.wait_connected(10)
        scans = max(1, args.burst // args.tags)
        batches = [
            scan(poller.plcs[k % args.plcs], args.tags, time.time(), k) for k in range(scans)
        ]
        wall0, cpu0 = time.perf_counter(), time.process_time()
        for b in batches:
            north.deliver(b)
        await north.mqtt.wait_drained(300)
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        spilled = north.mqtt.buffer.spilled
    n = scans * args.tags
    print(
        f"flat out: {n} samples in {scans} messages acknowledged in {wall:.2f} s:"
        f" {n / wall:,.0f} samples/s, {scans / wall:,.0f} messages/s;"
        f" CPU {1e6 * cpu / n:.1f} us per sample; spilled to disk {spilled} messages"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--plcs", type=int, default=1000)
    parser.add_argument("--tags", type=int, default=10)
    parser.add_argument("--seconds", type=int, default=10)
    parser.add_argument("--burst", type=int, default=100_000)
    parser.add_argument("--rbe", action="store_true")
    parser.add_argument(
        "--broker-nodelay",
        action="store_true",
        help="mosquitto with set_tcp_nodelay true (default: mosquitto's default, Nagle on)",
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="plcstack-mqtt-bench-") as d:
        workdir = Path(d)
        proc, port = start_mosquitto(workdir, args.broker_nodelay)
        try:
            asyncio.run(paced(args, port, proc.pid, workdir))
            if args.burst:
                asyncio.run(burst(args, port, workdir))
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(10)


if __name__ == "__main__":
    main()
