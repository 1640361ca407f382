"""E71-only commands: ``plcstack info|run|stop|loopback URL``, the random access buffer
(``plcstack rab-read|rab-write``) and the EXPERIMENTAL program/parameter/comment area transfer
(``plcstack e71-area read|write``, the bodies passed on as opaque bytes) with a progress bar."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, TextIO

from plcstack.clients import connect
from plcstack.clients.e71 import E71Client
from plcstack.errors import AddressError

#: area name -> (read command, write command, unit)
AREAS: dict[str, tuple[int, int, str]] = {
    "parameters": (0x10, 0x11, "bytes"),
    "main-program": (0x0A, 0x0C, "steps"),
    "sub-program": (0x0B, 0x0D, "steps"),
    "comments": (0x1C, 0x1D, "bytes"),
    "ext-comments": (0x39, 0x3A, "bytes"),
    "micro-main": (0x1E, 0x20, "bytes"),
    "micro-sub": (0x1F, 0x21, "bytes"),
}


def _int(text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer (123, 0x7B)") from None


def register(subparsers: Any) -> None:
    def url_parser(name: str, help_: str) -> argparse.ArgumentParser:
        p: argparse.ArgumentParser = subparsers.add_parser(name, help=help_)
        p.add_argument("url", help="E71 URL, e.g. e71+tcp://10.0.0.5:5000?code=ascii")
        p.add_argument("--timeout", type=float, default=None, help="request deadline in seconds")
        return p

    p = url_parser("info", "E71: CPU model (15H) and operating state (D9015)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run_info)
    url_parser("run", "E71: remote RUN (13H)").set_defaults(func=run_run)
    url_parser("stop", "E71: remote STOP (14H)").set_defaults(func=run_stop)
    p = url_parser("loopback", "E71: loopback test (16H)")
    p.add_argument("data", nargs="?", default=None, help="hex bytes to echo (default 00 01 .. 1F)")
    p.set_defaults(func=run_loopback)

    p = url_parser("rab-read", "E71: read the random access buffer (61H)")
    p.add_argument("address", type=_int, help="internal word address 0-6143")
    p.add_argument("count", nargs="?", type=_int, default=1, help="words (default 1)")
    p.add_argument("--json", action="store_true", help='print {"address": ..., "values": [...]}')
    p.set_defaults(func=run_rab_read)
    p = url_parser("rab-write", "E71: write the random access buffer (62H)")
    p.add_argument("address", type=_int, help="internal word address 0-6143")
    p.add_argument("values", nargs="+", type=_int, help="words (123, -5, 0x1F)")
    p.set_defaults(func=run_rab_write)

    p = subparsers.add_parser(
        "e71-area",
        help="E71: EXPERIMENTAL read/write of parameters, programs, comments (bodies are opaque)",
    )
    sub = p.add_subparsers(dest="direction", required=True, metavar="read|write")
    r = sub.add_parser("read", help="read an area to a file (or hex to stdout)")
    w = sub.add_parser("write", help="write a file into an area")
    for q in (r, w):
        q.add_argument("url", help="E71 URL")
        q.add_argument("area", choices=list(AREAS), help="the area: " + ", ".join(AREAS))
        q.add_argument("start", type=_int, help="start address (step / byte)")
        q.add_argument("--chunk", type=_int, default=256, help="units per request (1-256)")
        q.add_argument("--progress", action="store_true", help="progress bar even when not a tty")
        q.add_argument("--timeout", type=float, default=None, help="request deadline in seconds")
    r.add_argument("length", type=_int, help="steps (programs) or bytes to read")
    r.add_argument("--out", type=Path, default=None, help="file to write (steps: 2 bytes LE)")
    w.add_argument("file", type=Path, help="file to send (steps: 2 bytes LE each)")
    r.set_defaults(func=run_area_read)
    w.set_defaults(func=run_area_write)


def _client(args: argparse.Namespace) -> E71Client:
    options = {"timeout": args.timeout} if args.timeout is not None else {}
    plc = connect(args.url, **options)
    if not isinstance(plc, E71Client):
        raise AddressError(f"{args.url}: this command needs an e71+tcp:// or e71+udp:// URL")
    return plc


async def run_info(args: argparse.Namespace) -> int:
    async with _client(args) as plc:
        status = await plc.cpu_status()
    if args.json:
        print(
            json.dumps(
                {
                    "model_code": status.model_code,
                    "model": status.model,
                    "state": status.state,
                    "status_word": status.status_word,
                }
            )
        )
    else:
        print(f"model: {status.model_code:02X}H ({status.model})")
        print(f"state: {status.state} (D9015 = {status.status_word:04X}H)")
    return 0


async def run_run(args: argparse.Namespace) -> int:
    async with _client(args) as plc:
        await plc.remote_run()
    print("remote RUN accepted")
    return 0


async def run_stop(args: argparse.Namespace) -> int:
    async with _client(args) as plc:
        await plc.remote_stop()
    print("remote STOP accepted")
    return 0


async def run_loopback(args: argparse.Namespace) -> int:
    if args.data is None:
        data = bytes(range(32))
    else:
        try:
            data = bytes.fromhex(args.data)
        except ValueError:
            raise AddressError(f"loopback data {args.data!r} is not hex bytes") from None
    async with _client(args) as plc:
        started = time.perf_counter()
        await plc.loopback(data)
        elapsed = time.perf_counter() - started
    print(f"loopback: {len(data)} bytes echoed in {elapsed * 1000:.1f} ms")
    return 0


async def run_rab_read(args: argparse.Namespace) -> int:
    async with _client(args) as plc:
        values = await plc.read_random_buffer(args.address, args.count)
    if args.json:
        print(json.dumps({"address": args.address, "values": values}))
    else:
        print(f"RAB {args.address}: " + " ".join(str(v) for v in values))
    return 0


async def run_rab_write(args: argparse.Namespace) -> int:
    async with _client(args) as plc:
        await plc.write_random_buffer(args.address, args.values)
    print(f"RAB {args.address}: wrote {len(args.values)} word(s)")
    return 0


class ProgressBar:
    """``[#####.....]  512/3072 bytes`` redrawn in place on ``stream`` (stderr)."""

    def __init__(self, unit: str, stream: TextIO, enabled: bool, width: int = 30) -> None:
        self.unit = unit
        self.stream = stream
        self.enabled = enabled
        self.width = width

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        filled = self.width * done // max(total, 1)
        bar = "#" * filled + "." * (self.width - filled)
        self.stream.write(f"\r[{bar}] {done}/{total} {self.unit}")
        if done >= total:
            self.stream.write("\n")
        self.stream.flush()


async def run_area_read(args: argparse.Namespace) -> int:
    read_cmd, _, unit = AREAS[args.area]
    bar = ProgressBar(unit, sys.stderr, args.progress or sys.stderr.isatty())
    async with _client(args) as plc:
        values = await plc.read_area(
            read_cmd, args.start, args.length, chunk=args.chunk, progress=bar
        )
    raw = b"".join(v.to_bytes(2, "little") for v in values) if unit == "steps" else bytes(values)
    if args.out is None:
        print(raw.hex())
    else:
        args.out.write_bytes(raw)
        print(f"{args.area}: {len(values)} {unit} written to {args.out}")
    return 0


async def run_area_write(args: argparse.Namespace) -> int:
    _, write_cmd, unit = AREAS[args.area]
    raw = args.file.read_bytes()
    if unit == "steps":
        if len(raw) % 2:
            raise AddressError(f"{args.file}: program files hold 2 bytes per step")
        values = [int.from_bytes(raw[i : i + 2], "little") for i in range(0, len(raw), 2)]
    else:
        values = list(raw)
    if not values:
        raise AddressError(f"{args.file} is empty")
    bar = ProgressBar(unit, sys.stderr, args.progress or sys.stderr.isatty())
    async with _client(args) as plc:
        await plc.write_area(write_cmd, args.start, values, chunk=args.chunk, progress=bar)
    print(f"{args.area}: wrote {len(values)} {unit}")
    return 0
