"""Count the Python bytecodes a stretch of code executes, per function: a deterministic profile.

On a shared two-core machine the fleet's CPU per request moves by 15 % between runs minutes
apart, and cProfile, which charges every call alike, showed the poller at call-count parity with
the raw floor while perf still put 11 us per request more in the interpreter. What
separated them was the number of bytecodes executed: every bytecode is counted here, the same
number on every run, so two trees can be compared without a quiet machine.

``python -m plcstack.bench.cases.fleet poll 100 --opcodes poll.json`` counts the measured window;
``python -m plcstack.bench.opcodes floor.json poll.json`` shows bytecodes per request side by side.
Tracing slows the process by an order of magnitude: use a small N (100), whose schedule it can
still keep, or per-request counts of the event loop's own code change with the load.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any

__all__ = ["OpcodeCounter", "compare", "main"]


class OpcodeCounter:
    """``enable()`` ... ``disable()``: bytecodes executed per ``(file, function)`` in between.

    Uses ``sys.settrace`` with opcode events, so it sees this thread only (asyncio runs there),
    and a coroutine resumed while enabled is counted from its resumption on. The ``RESUME`` a
    frame starts with is not counted (it runs before the call event turns opcode events on).
    """

    def __init__(self) -> None:
        self.counts: collections.Counter[tuple[str, str]] = collections.Counter()

    def _global(self, frame: FrameType, event: str, arg: Any) -> Any:
        frame.f_trace_opcodes = True
        frame.f_trace_lines = False
        return self._local

    def _local(self, frame: FrameType, event: str, arg: Any) -> Any:
        if event == "opcode":
            code = frame.f_code
            self.counts[(Path(code.co_filename).name, code.co_name)] += 1
        return self._local

    def enable(self) -> None:
        sys.settrace(self._global)

    def disable(self) -> None:
        sys.settrace(None)

    def dump(self, path: str | Path, requests: int) -> None:
        """Write the counts and the number of requests they cover (JSON)."""
        rows = [[file, name, n] for (file, name), n in self.counts.most_common()]
        Path(path).write_text(json.dumps({"requests": requests, "functions": rows}))


def _per_request(path: str | Path) -> dict[tuple[str, str], float]:
    data = json.loads(Path(path).read_text())
    requests = max(1, int(data["requests"]))
    return {(file, name): n / requests for file, name, n in data["functions"]}


def compare(paths: Sequence[str | Path], top: int = 30) -> str:
    """A table of bytecodes per request: one column per file, rows by the last column's cost."""
    tables = [_per_request(p) for p in paths]
    keys = sorted(set().union(*tables), key=lambda k: -tables[-1].get(k, 0.0))
    lines = [
        "  ".join(f"{Path(p).stem[:9]:>9}" for p in paths) + "  function",
        "  ".join(f"{sum(t.values()):9.0f}" for t in tables) + "  all",
    ]
    for key in keys[:top]:
        lines.append("  ".join(f"{t.get(key, 0.0):9.1f}" for t in tables) + f"  {key[0]} {key[1]}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m plcstack.bench.opcodes")
    parser.add_argument("files", nargs="+", help="counts written by the fleet case's --opcodes")
    parser.add_argument("--top", type=int, default=30, help="functions to list (default 30)")
    args = parser.parse_args(argv)
    print(compare(args.files, args.top))
    return 0


if __name__ == "__main__":
    sys.exit(main())
