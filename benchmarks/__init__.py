"""The plcstack benchmark suite (``plcstack bench``, issue 8).

"Fast" must be a measured ratio, not a claim. Every stack number here is paired with a *floor*:
the same exchange done by the thinnest hand-written asyncio code (pre-built request bytes, read the
known reply length), against the same in-process simulator, on the same event loop, in the same
run.

Modules:

* :mod:`benchmarks.runner`  -- repeat a case, min/median/max of ops/s, p50/p99 latency, result rows
* :mod:`benchmarks.frames`  -- request/reply bytes built from the spec rules (checked against the
  spec's golden vectors in ``tests/test_bench.py``)
* :mod:`benchmarks.floor`   -- the raw asyncio clients (TCP, UDP, scripted dialogue)
* :mod:`benchmarks.cases`   -- the protocol variants (``protocols``), codec adapters (``codecs``),
  one connection (``conn``), fan-out in child processes (``fanout``), the poller (``pollbench``)
  and the optional peers (``peers``)
* :mod:`benchmarks.suite`   -- which cases run in ``--quick``/full/``--smoke`` and on which loops
* :mod:`benchmarks.report`  -- the stdout table, the JSON file and the PNG chart
* :mod:`benchmarks.png`     -- a dependency-free PNG line chart (zlib + struct)
* :mod:`benchmarks.profiling` -- cProfile of the client side (``python -m benchmarks.profiling``)

Usage, decisions and the JSON schema: ``benchmarks/README.md``; numbers: ``RESULTS.md``.

The package lives beside ``plcstack/`` in the source tree and is not installed with the wheel:
``plcstack bench`` finds it relative to the repository (see ``plcstack/cli/bench.py``).
"""
