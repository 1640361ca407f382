"""Fixtures shared by every test module: real servers on loopback (see tests/servers.py), and
the rule that no test may leave an unhandled exception in an event loop.

asyncio reports an exception nobody handled (a callback that raised, a task whose exception was
never retrieved, a transport error) through the loop's exception handler, which logs it on the
``asyncio`` logger at ERROR. Such a line in a test run is either a bug or a test that does not
clean up (a server cancelled mid-connection, a reader left registered); hundreds of them hid
real ones. So any such record during a test fails that test, with the records in the message.
A test that provokes one on purpose says so with ``@pytest.mark.loop_errors_expected`` (or
collects them itself with ``tests.robust_helpers.record_loop_errors``).

The garbage collection after each test is what makes a failed task in a reference cycle report
itself inside the test that made it. A full collection walks every tracked object, and after the
imports (asyncua, hypothesis, pytest's own items) that is over 100,000 objects: about 0.1 s of
CPU per test, most of the whole suite's CPU time. So the objects alive at the start of a module
are frozen (``gc.freeze()``: moved to a generation the collector does not walk), and the collection
after each test walks only what was made since.

What was frozen while alive and died later is found only by a full collection (the heap
unfrozen, collected, frozen again): above all the values of fixtures wider than a test (module,
class, session), which die when their scope ends. So the first test of a module collects fully
when such a fixture was torn down since the last full collection, so that what it held is freed
and still reports (at worst in the first test of the next module), and at least every
``FULL_COLLECTION_EVERY`` modules for anything else (a test that kept an object past its end),
and after the last test of the process. A full collection at every module start cost about
0.15 s each, a sixth of the suite's CPU.
"""

from __future__ import annotations

import gc
import logging
import os
import sys
import tempfile
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, settings

from tests.servers import influxd, mosquitto, nats_server

__all__ = ["influxd", "mosquitto", "nats_server"]

# tests/test_loop_error_rule.py runs a small pytest session to prove the rule below
pytest_plugins = ["pytester"]

# Hypothesis by default fails an example that takes over 200 ms (deadline) and a test whose data
# generation is slow (too_slow): wall-clock limits, which a loaded 2-core machine (three workers,
# simulators, servers) breaks at random. How much each test tries stays its own max_examples.
settings.register_profile("plcstack", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("plcstack")


def pytest_configure(config: pytest.Config) -> None:
    """With ``PYTHONDONTWRITEBYTECODE`` set (as on our shared development machine), every
    ``python -m plcstack`` a CLI test starts, and every xdist worker, compiled the whole package
    from source again: about half of each subprocess's start-up. Keep the wish behind the
    variable (no ``__pycache__`` in the source tree) but cache the bytecode in a directory under
    the temporary directory instead, for this process and everything it starts (the workers and
    the test subprocesses inherit the environment)."""
    if not os.environ.get("PYTHONDONTWRITEBYTECODE") or os.environ.get("PYTHONPYCACHEPREFIX"):
        return
    prefix = os.path.join(tempfile.gettempdir(), f"plcstack-pycache-{os.getuid()}")
    del os.environ["PYTHONDONTWRITEBYTECODE"]
    os.environ["PYTHONPYCACHEPREFIX"] = prefix
    sys.dont_write_bytecode = False
    sys.pycache_prefix = prefix


class _LoopErrors(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


#: the most module starts between two full collections (see the module docstring)
FULL_COLLECTION_EVERY = 8


class _Heap:
    """Where the garbage collection of the tests stands (see the module docstring)."""

    #: the module whose first test last froze the heap
    module = ""
    #: module starts since the last full collection
    starts = 0
    #: a fixture wider than a test was torn down since the last full collection
    wide_fixture_ended = True
    #: the test being torn down is the last of this process
    last_test = False


def _collect_garbage(module: str) -> None:
    """Collect what the test left in reference cycles, walking only objects made since the heap
    was last frozen; when a new module starts, freeze what is left, after a full collection if
    one is due; after the last test, a full collection, so nothing frozen goes unreported."""
    if module == _Heap.module and not _Heap.last_test:
        gc.collect()
        return
    if module != _Heap.module:
        _Heap.module = module
        _Heap.starts += 1
    if _Heap.wide_fixture_ended or _Heap.starts >= FULL_COLLECTION_EVERY or _Heap.last_test:
        _Heap.wide_fixture_ended, _Heap.starts = False, 0
        gc.unfreeze()
    gc.collect()
    gc.freeze()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_teardown(nextitem: pytest.Item | None) -> None:
    """Before the test's fixtures end: whether it is the last one (see _collect_garbage)."""
    _Heap.last_test = nextitem is None


def pytest_fixture_post_finalizer(fixturedef: pytest.FixtureDef[object]) -> None:
    """A fixture wider than a test ended: its value may lie frozen among the garbage."""
    if fixturedef.scope != "function":
        _Heap.wide_fixture_ended = True


@pytest.fixture(autouse=True)
def _no_unhandled_loop_errors(request: pytest.FixtureRequest) -> Iterator[None]:
    handler = _LoopErrors()
    log = logging.getLogger("asyncio")
    log.addHandler(handler)
    try:
        yield
        # "Task exception was never retrieved" is reported only when the task is collected
        _collect_garbage(request.node.nodeid.split("::", 1)[0])
    finally:
        log.removeHandler(handler)
    if handler.records and request.node.get_closest_marker("loop_errors_expected") is None:
        shown = "\n".join(
            f"  {r.getMessage().splitlines()[0]}"
            + (f" ({type(r.exc_info[1]).__name__}: {r.exc_info[1]})" if r.exc_info else "")
            for r in handler.records[:5]
        )
        pytest.fail(
            f"the event loop logged {len(handler.records)} unhandled exception(s):\n{shown}",
            pytrace=False,
        )
