"""``plcstack demo``: simulators of every protocol, polled concurrently, shown as a live table.

On a terminal the table is redrawn in place (ANSI escapes, no curses); when stdout is not a
terminal every sample is printed as one plain line. Runs until Ctrl-C unless ``--duration`` is
given; the poller's statistics go to stderr at the end. Exit 0, or 130 after Ctrl-C.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import re
import shlex
import shutil
import sys
import time
from importlib import resources
from pathlib import Path
from typing import Any, TextIO

from plcstack.cli import UsageError, plain_text, print_error
from plcstack.cli.signals import Signals, StopEvent
from plcstack.poll.demo import DemoPlant, start_plant
from plcstack.poll.engine import Poller, Quality, Sample, format_stats

#: seconds between redraws of the live table
REDRAW = 0.25


def register(subparsers: Any) -> None:
    demo = subparsers.add_parser(
        "demo",
        help="simulate PLCs of every protocol and poll them all (live table)",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    demo.add_argument(
        "--plcs",
        type=int,
        default=None,
        help="number of simulated PLCs, spread over the protocols (default: one per protocol)",
    )
    demo.add_argument(
        "--duration", type=float, default=None, help="stop after SECONDS (default: until Ctrl-C)"
    )
    demo.add_argument(
        "--interval", type=float, default=0.25, help="scan interval in seconds (default 0.25)"
    )
    demo.add_argument(
        "--write-config",
        metavar="FILE",
        default=None,
        help="write the example poll config (PLCs at the simulators' default ports) to FILE "
        "('-' for stdout) and exit; then: plcstack sim e71 & plcstack sim s5lan & "
        "plcstack poll FILE",
    )
    demo.add_argument(
        "--base-port",
        type=int,
        default=None,
        metavar="N",
        help="with --write-config: the E71 simulator at port N, S5-LAN at N+1, OPC UA at N+2 "
        "instead of 5000, 5010, 4840; the config's comments show the matching sim commands",
    )
    demo.set_defaults(func=run_demo)


#: the example configuration shipped in the package (package data)
EXAMPLE_CONFIG = "plant.toml"


#: the ports the shipped example uses: the simulators' and the OPC UA server's defaults
EXAMPLE_PORTS: dict[str, int] = {"e71": 5000, "s5lan": 5010, "opcua": 4840}


def example_ports(base_port: int | None) -> dict[str, int]:
    """The example's ports: the defaults, or ``base_port``, +1, +2 (E71, S5-LAN, OPC UA), so
    the config and the simulators started for it move together (a second copy beside the
    first, a test on free ports, a machine where 5000 is taken)."""
    if base_port is None:
        return dict(EXAMPLE_PORTS)
    if not 1 <= base_port <= 65533:
        raise UsageError(f"--base-port {base_port}: must be 1..65533 (three ports from N on)")
    return {name: base_port + k for k, name in enumerate(EXAMPLE_PORTS)}


def example_config(base_port: int | None = None) -> str:
    """The text of the shipped example poll configuration, its ports moved to ``base_port``."""
    text = (resources.files("plcstack.examples") / EXAMPLE_CONFIG).read_text(encoding="utf-8")
    if base_port is None:
        return text
    ports = example_ports(base_port)
    for name, default in EXAMPLE_PORTS.items():
        text = text.replace(f"127.0.0.1:{default}", f"127.0.0.1:{ports[name]}")
        if name != "opcua":  # the comment's sim commands start the simulators on the new ports
            text = text.replace(
                f"plcstack sim {name} ", f"plcstack sim {name} --port {ports[name]} "
            )
    return text.replace(
        "plcstack demo --write-config plant.toml",
        f"plcstack demo --write-config plant.toml --base-port {base_port}",
    )


def sim_commands(base_port: int | None) -> str:
    """The shell line that starts the example's simulators where its config points."""
    if base_port is None:
        return "plcstack sim e71 & plcstack sim s5lan &"
    ports = example_ports(base_port)
    return f"plcstack sim e71 --port {ports['e71']} & plcstack sim s5lan --port {ports['s5lan']} &"


def write_config(target: str, out: TextIO, base_port: int | None = None) -> int:
    text = example_config(base_port)
    if target == "-":
        out.write(text)
        return 0
    # the comment's commands name the file they are in, so they run as written after a copy
    text = text.replace(f" {EXAMPLE_CONFIG}", f" {shlex.quote(target)}")
    path = Path(target)
    if path.exists():
        raise UsageError(f"--write-config {target}: the file exists; not overwritten")
    try:
        path.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise UsageError(f"--write-config {target}: {exc.strerror or exc}") from None
    print(f"wrote {target}; run: {sim_commands(base_port)} plcstack poll {target}", file=sys.stderr)
    return 0


def _format_value(value: Any) -> str:
    if isinstance(value, list):
        if value and all(isinstance(v, bool) for v in value):
            return "".join("#" if v else "." for v in value)
        return " ".join(_format_value(v) for v in value)
    if isinstance(value, bool):
        return "ON" if value else "off"
    if isinstance(value, float):
        return f"{value:.3f}"
    return str(value)


def _display(tag: str, value: Any) -> str:
    if tag == "light" and isinstance(value, int) and not isinstance(value, bool):
        value = [bool(value >> i & 1) for i in range(8)]  # an S5 flag byte, bit 0 first
    return _format_value(value)


def plain_line(sample: Sample) -> str:
    stamp = time.strftime("%H:%M:%S", time.localtime(sample.source_time))
    millis = int(sample.source_time * 1000) % 1000
    text = _display(sample.tag, sample.value) if sample.quality is Quality.GOOD else sample.error
    return f"{stamp}.{millis:03d} {sample.plc} {sample.tag} {sample.quality.value} {text}"


async def run_demo(args: argparse.Namespace, out: TextIO | None = None) -> int:
    out = out if out is not None else sys.stdout
    base_port = getattr(args, "base_port", None)
    if getattr(args, "write_config", None) is not None:
        return write_config(args.write_config, out, base_port)
    if base_port is not None:
        raise UsageError("--base-port moves the ports of --write-config; give both")
    if args.plcs is not None and args.plcs < 1:
        print_error("demo: --plcs must be at least 1")
        return 2
    for name in ("duration", "interval"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            print_error(f"demo: --{name} must be greater than 0")
            return 2
    plant = await start_plant(args.plcs, interval=args.interval)
    try:
        for note in plant.notes:
            print(f"note: {note}", file=sys.stderr)
        if not plant.plcs:
            print_error("demo: no simulator is available")
            return 1
        poller = Poller(plant.config)
        stop = StopEvent()
        live = out.isatty() and os.environ.get("TERM") != "dumb"
        with Signals(stop):
            async with poller:
                show = _live_table(poller, plant, out) if live else _plain(poller, out, stop)
                shower = asyncio.create_task(show)
                stopper = asyncio.create_task(stop.wait())
                await asyncio.wait(
                    {shower, stopper}, timeout=args.duration, return_when=asyncio.FIRST_COMPLETED
                )
                shower.cancel()
                stopper.cancel()
                await asyncio.gather(shower, stopper, return_exceptions=True)
        if live:
            out.write("\n")
        with contextlib.suppress(BrokenPipeError, ValueError):
            out.flush()
        print(format_stats(poller.stats, dropped_total=poller.dropped), file=sys.stderr)
        return stop.exit_code()
    finally:
        await plant.aclose()


async def _plain(poller: Poller, out: TextIO, stop: asyncio.Event) -> None:
    try:
        async for sample in poller:
            out.write(plain_line(sample) + "\n")
            if not poller.pending():
                out.flush()
    except BrokenPipeError:
        stop.set()


async def _live_table(poller: Poller, plant: DemoPlant, out: TextIO) -> None:
    latest: dict[tuple[str, str], Sample] = {}
    started = time.monotonic()

    async def consume() -> None:
        async for sample in poller:
            latest[sample.plc, sample.tag] = sample

    consumer = asyncio.create_task(consume())
    out.write("\x1b[?25l\x1b[2J")  # hide the cursor, clear once
    try:
        while True:
            table = render_table(
                poller, plant, latest, time.monotonic() - started, _terminal_size(out)
            )
            out.write("\x1b[H" + table)
            out.write("\x1b[J")
            out.flush()
            await asyncio.sleep(REDRAW)
    finally:
        consumer.cancel()
        await asyncio.gather(consumer, return_exceptions=True)
        out.write("\x1b[?25h")  # cursor back


def _terminal_size(out: TextIO) -> tuple[int, int]:
    try:
        size = os.get_terminal_size(out.fileno())
    except (OSError, ValueError):
        size = shutil.get_terminal_size()
    return (size.columns or 80, size.lines or 24)


_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def clip(line: str, width: int) -> str:
    """Cut ``line`` to ``width`` visible characters, keeping (not counting) ANSI sequences."""
    out: list[str] = []
    visible = 0
    pos = 0
    for match in _ANSI.finditer(line):
        text = line[pos : match.start()]
        take = text[: max(0, width - visible)]
        out.append(take)
        visible += len(take)
        out.append(match.group())
        pos = match.end()
    out.append(line[pos:][: max(0, width - visible)])
    return "".join(out)


def render_table(
    poller: Poller,
    plant: DemoPlant,
    latest: dict[tuple[str, str], Sample],
    uptime: float,
    size: tuple[int, int] = (200, 1000),
) -> str:
    """The live table as text with ANSI colours; one row per PLC, one column per tag.

    ``size`` is the terminal's (columns, lines): rows that do not fit are summarised in one
    line, and long lines are cut, so the redraw in place never scrolls.
    """
    columns, rows = size
    green, red, dim, bold, reset = "\x1b[32m", "\x1b[31m", "\x1b[2m", "\x1b[1m", "\x1b[0m"
    stats = poller.stats
    lines = [
        f"{bold}plcstack demo{reset}  {len(plant.plcs)} simulated PLCs, scan every "
        f"{plant.interval:g} s, up {uptime:5.1f} s   {dim}Ctrl-C to stop{reset}",
        "",
    ]
    header = f"{'PLC':<18} {'counter':>8} {'sine':>6} {'temp':>8} {'light':>9}"
    header += f"  {'req':>6} {'err':>4} {'recon':>5} {'p50 ms':>7} {'p99 ms':>7}"
    lines.append(bold + header + reset)
    footer: list[str] = []
    errors = [s for s in latest.values() if s.quality is Quality.BAD and s.error is not None]
    if errors:
        footer.append("")
        footer.append(red + str(errors[-1].error) + reset)
    footer.extend(dim + note + reset for note in plant.notes)
    room = max(1, rows - len(lines) - len(footer) - 1)
    shown = plant.plcs if len(plant.plcs) <= room else plant.plcs[: room - 1]
    for plc in shown:
        cells = []
        widths = (8, 6, 8, 9)
        for tag, width in zip(plc.protocol.tags, widths, strict=False):
            sample = latest.get((plc.name, tag.name))
            if sample is None:
                cells.append(dim + "...".rjust(width) + reset)
            elif sample.quality is Quality.GOOD:
                text = _display(tag.name, sample.value)
                cells.append(green + text.rjust(width)[-width:] + reset)
            else:
                cells.append(red + "BAD".rjust(width) + reset)
        st = stats[plc.name]
        p50, p99 = st.percentile(50), st.percentile(99)
        tail = (
            f"  {st.requests:>6} {st.errors:>4} {st.reconnects:>5} "
            f"{'-' if p50 is None else f'{p50 * 1000:.2f}':>7} "
            f"{'-' if p99 is None else f'{p99 * 1000:.2f}':>7}"
        )
        lines.append(f"{plc.name:<18} " + " ".join(cells) + tail)
    if len(shown) < len(plant.plcs):
        hidden = plant.plcs[len(shown) :]
        bad = sum(
            1
            for p in hidden
            for t in p.protocol.tags
            if (s := latest.get((p.name, t.name))) is not None and s.quality is Quality.BAD
        )
        lines.append(dim + f"... and {len(hidden)} more PLCs ({bad} bad values among them)" + reset)
    lines.extend(footer)
    return "".join(clip(line, columns - 1) + "\x1b[K\n" for line in lines)
