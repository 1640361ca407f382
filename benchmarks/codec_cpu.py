"""Codec cost per operation in process CPU time, stack and floor batches interleaved (issue 16).

    python -m benchmarks.codec_cpu [e71|as511|all] [REPEATS] [NUMBER]

The ops are those of the ``codec/*`` rows of ``plcstack bench``; each repeat times one batch of
each op in turn (``time.process_time``), so load drift hits all alike; prints median and min.
Run it under ``taskset -c 0`` with before/after trees on ``PYTHONPATH`` alternately.
"""

from __future__ import annotations

import gc
import statistics
import sys
import time
from collections.abc import Callable

from plcstack.bench.cases.codecs import as511_codec, e71_codec


def batch(fn: Callable[[], object], number: int) -> float:
    started = time.process_time()
    for _ in range(number):
        fn()
    return (time.process_time() - started) / number * 1e6


def main(argv: list[str]) -> None:
    which = argv[0] if argv else "all"
    repeats = int(argv[1]) if len(argv) > 1 else 15
    for name, factory, number in (("e71", e71_codec, 5000), ("as511", as511_codec, 1000)):
        if which not in (name, "all"):
            continue
        if len(argv) > 2:
            number = int(argv[2]) // (5 if name == "as511" else 1)
        ops = factory()
        fns = {"read64": ops.stack_read, "write64": ops.stack_write, "floor read": ops.floor_read}
        results: dict[str, list[float]] = {k: [] for k in fns}
        for fn in fns.values():
            batch(fn, 100)
        gc.collect()
        for _ in range(repeats):
            for key, fn in fns.items():
                results[key].append(batch(fn, number))
        for key, values in results.items():
            print(f"{name} {key} median {statistics.median(values):.2f} us  min {min(values):.2f}")


if __name__ == "__main__":
    main(sys.argv[1:])
