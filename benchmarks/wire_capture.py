"""What recording costs on one connection: ``--pcap FILE`` and a flight recorder's ring.

    python -m benchmarks.wire_capture [--seconds 0.2] [--repeats 15]

One E71 TCP simulator (``plcstack sim e71``) in another process on the last CPU; this process
on CPU 0 with three clients to it, each on its own connection: ``plain`` (nothing recorded),
``pcap`` (a :class:`~plcstack.wire.capture.PcapngCapture` file in a temporary directory, as
``--pcap`` writes it: every packet encoded and written, one flush per loop pass) and ``ring``
(a :class:`~plcstack.wire.ring.FrameRing` of 64 frames, as ``[trace] ring = 64``). Each window
reads 64 words in a closed loop for ``--seconds``; the kinds alternate (ABBA) for ``--repeats``
rounds. Reported: the median process CPU per request of each kind (``time.process_time``:
this process only) and the median per-round ratio plain/recorded (1.0 = free).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import plcstack
from plcstack.bench.profiling import cpu_per_op
from plcstack.wire.capture import PcapngCapture
from plcstack.wire.ring import FrameRing


def _cpus() -> list[int]:
    return sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []


def _start_sim(cpu: int | None) -> tuple[subprocess.Popen[str], int]:
    def pin() -> None:
        if cpu is not None:
            os.sched_setaffinity(0, {cpu})

    proc = subprocess.Popen(
        [sys.executable, "-m", "plcstack", "sim", "e71", "--port", "0"],
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=pin,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    return proc, int(line.split()[2].rsplit(":", 1)[1])


async def run(seconds: float, repeats: int) -> dict[str, Any]:
    cpus = _cpus()
    sim, port = _start_sim(cpus[-1] if len(cpus) > 1 else None)
    if len(cpus) > 1:
        os.sched_setaffinity(0, {cpus[0]})
    url = f"e71+tcp://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as folder:
        capture = PcapngCapture(Path(folder) / "bench.pcapng").open()
        try:
            plain, pcap, ring = plcstack.connect(url), plcstack.connect(url), plcstack.connect(url)
            pcap.transport.record_to(capture)
            ring.transport.record_to(FrameRing(64))
            clients = {"plain": plain, "pcap": pcap, "ring": ring}
            for client in clients.values():
                await client.open()
            try:
                ops = {
                    kind: (lambda c=client: c.read("D0", 64)) for kind, client in clients.items()
                }
                for op in ops.values():  # warm-up
                    await cpu_per_op(op, seconds)
                cpu: dict[str, list[float]] = {kind: [] for kind in ops}
                for round_ in range(repeats):
                    order = list(ops) if round_ % 2 == 0 else list(reversed(ops))
                    for kind in order:
                        cpu[kind].append((await cpu_per_op(ops[kind], seconds))[0])
            finally:
                for client in clients.values():
                    await client.aclose()
        finally:
            capture.close()
            size = (Path(folder) / "bench.pcapng").stat().st_size
    sim.terminate()
    sim.wait(10)
    medians = {kind: statistics.median(values) for kind, values in cpu.items()}
    ratios = {
        kind: statistics.median(p / r for p, r in zip(cpu["plain"], cpu[kind], strict=True))
        for kind in ("pcap", "ring")
    }
    return {
        "cpu_us_per_request": {k: round(v, 1) for k, v in medians.items()},
        "ratio_plain_over": {k: round(v, 3) for k, v in ratios.items()},
        "extra_us_per_request": {
            k: round(medians[k] - medians["plain"], 1) for k in ("pcap", "ring")
        },
        "pcap_packets": capture.packets,
        "pcap_bytes": size,
        "repeats": repeats,
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=0.2)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    print(asyncio.run(run(args.seconds, args.repeats)))


if __name__ == "__main__":
    main()
