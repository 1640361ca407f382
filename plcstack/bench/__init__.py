"""The plcstack benchmark suite (``plcstack bench``), shipped in the package.

"Fast" must be a measured ratio, not a claim. Every stack number here is paired with a *floor*:
the same exchange done by the thinnest hand-written asyncio code (pre-built request bytes, read the
known reply length), against the same simulator, on the same event loop, in the same run.

Modules (all ``plcstack.bench.*``):

* ``runner``    -- repeat a case, min/median/max of ops/s, p50/p99 latency, result rows
* ``frames``    -- request/reply bytes built from the spec rules (checked against the spec's
  golden vectors in ``tests/test_bench.py``)
* ``floor``     -- the raw asyncio clients (TCP, UDP, scripted dialogue)
* ``cases``     -- the protocol variants (``protocols``), codec adapters (``codecs``), one
  connection (``conn``), fan-out in child processes (``fanout``), the poller (``pollbench``),
  the 10 Hz fleet against responders in another process (``fleet``) and the optional peers
* ``suite``     -- which cases run in ``--quick``/full/``--smoke`` and on which loops
* ``report``    -- the stdout table, the JSON file and the PNG chart
* ``png``       -- a dependency-free PNG line chart (zlib + struct)
* ``profiling`` -- cProfile of the client side (``python -m plcstack.bench.profiling``)
* ``pollcost``  -- the poller's own CPU per request without sockets (``-m plcstack.bench.pollcost``)

Usage, decisions and the JSON schema: ``benchmarks/README.md`` in the repository; numbers:
``benchmarks/RESULTS.md``. The package ships in the wheel so that ``plcstack bench`` works from
any install; the repository's ``benchmarks/`` keeps standalone developer scripts that need extra
services.
"""
