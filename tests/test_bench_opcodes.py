"""The bytecode counter behind the fleet case's ``--opcodes`` (plcstack/bench/opcodes.py).

It is the deterministic profile that found issue 16's gap; its counts must be exact.
"""

from __future__ import annotations

import dis
import json
from pathlib import Path

from plcstack.bench.opcodes import OpcodeCounter, compare, main


def _straight(a: int) -> int:
    b = a + 1
    return b * 2


def _loop(n: int) -> int:
    total = 0
    for i in range(n):
        total += i
    return total


def _counted(fn: object, *args: int, times: int = 1) -> int:
    counter = OpcodeCounter()
    counter.enable()
    try:
        for _ in range(times):
            fn(*args)  # type: ignore[operator]
    finally:
        counter.disable()
    return counter.counts[(Path(__file__).name, fn.__name__)]  # type: ignore[attr-defined]


def test_a_straight_function_counts_each_of_its_instructions_once_per_call() -> None:
    # all but the RESUME at entry, which runs before the call event sets up opcode tracing
    instructions = [i for i in dis.get_instructions(_straight) if i.opname != "CACHE"]
    assert instructions[0].opname == "RESUME"
    assert _counted(_straight, 1) == len(instructions) - 1
    assert _counted(_straight, 1, times=7) == 7 * (len(instructions) - 1)


def test_a_loop_counts_what_runs() -> None:
    # every extra turn of the loop runs the same instructions: counts grow linearly
    c0, c1, c5 = (_counted(_loop, n) for n in (0, 1, 5))
    assert c1 > c0 and c5 - c1 == 4 * (c1 - c0)


def test_dump_and_compare_per_request(tmp_path: Path, capsys: object) -> None:
    counter = OpcodeCounter()
    counter.counts[("a.py", "f")] = 300
    counter.counts[("b.py", "g")] = 100
    counter.dump(tmp_path / "one.json", requests=100)
    (tmp_path / "two.json").write_text(
        json.dumps({"requests": 10, "functions": [["a.py", "f", 50], ["c.py", "h", 200]]})
    )
    table = compare([tmp_path / "one.json", tmp_path / "two.json"]).splitlines()
    assert table[1].split() == ["4", "25", "all"]  # (300 + 100) / 100 and (50 + 200) / 10
    assert table[2].split() == ["0.0", "20.0", "c.py", "h"]  # ordered by the last column
    assert table[3].split() == ["3.0", "5.0", "a.py", "f"]
    assert table[4].split() == ["1.0", "0.0", "b.py", "g"]
    assert main([str(tmp_path / "one.json")]) == 0


def test_fleet_opcodes_counts_the_measured_window(tmp_path: Path) -> None:
    import os
    import subprocess
    import sys

    from plcstack.bench.cases.fanout import PACKAGE_PARENT

    out = tmp_path / "poll.json"
    env = dict(os.environ, PYTHONPATH=str(PACKAGE_PARENT))
    cmd = [sys.executable, "-m", "plcstack.bench.cases.fleet", "poll", "2"]
    cmd += ["--duration", "0.5", "--warmup", "0.3", "--opcodes", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads(out.read_text())
    assert data["requests"] > 0
    names = {(file, name) for file, name, _ in data["functions"]}
    # the callback scan path ran in the window, and the counting around it did not
    assert ("scanner.py", "_fire") in names and ("exchange.py", "start") in names
    assert ("engine.py", "_update_connection_stats") not in names
