"""The rule of tests/conftest.py holds: a test whose event loop logged an unhandled exception
fails, also when the failed task is only freed by the garbage collector (a reference cycle), in
the first test of a module and in a later one (the conftest freezes the heap between them), and
when a module's fixture held it until its module ended or a module kept it past its test (frozen
while alive, freed after)."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
INNER_CONFTEST = (
    "from tests.conftest import (  # noqa: F401\n"
    "    _no_unhandled_loop_errors, pytest_fixture_post_finalizer, pytest_runtest_teardown\n"
    ")\n"
)

INNER_TESTS = """
import asyncio

import pytest


async def _fail() -> None:
    raise ValueError("nobody looks at me")


async def _leave_a_failed_task_in_a_cycle() -> None:
    task = asyncio.get_running_loop().create_task(_fail())
    await asyncio.sleep(0)
    await asyncio.sleep(0)
    holder = {"task": task}
    holder["self"] = holder  # only the cycle collector frees the task now
    del task, holder


def test_first_of_module() -> None:
    asyncio.run(_leave_a_failed_task_in_a_cycle())


def test_later_in_module() -> None:
    asyncio.run(_leave_a_failed_task_in_a_cycle())


def test_clean() -> None:
    asyncio.run(asyncio.sleep(0))


@pytest.mark.loop_errors_expected
def test_declared() -> None:
    asyncio.run(_leave_a_failed_task_in_a_cycle())
"""


# a module fixture's failed task in a cycle: alive when the heap is frozen, garbage at module end
WIDE_FIXTURE_TESTS = """
import asyncio
from collections.abc import Iterator

import pytest


async def _fail() -> None:
    raise ValueError("held by a module's fixture")


@pytest.fixture(scope="module")
def held() -> Iterator[dict[str, object]]:
    loop = asyncio.new_event_loop()
    task = loop.create_task(_fail())
    loop.run_until_complete(asyncio.sleep(0))
    loop.close()
    holder: dict[str, object] = {"task": task}
    holder["self"] = holder
    del task
    yield holder


def test_uses_it(held: dict[str, object]) -> None:
    assert "task" in held


def test_uses_it_again(held: dict[str, object]) -> None:
    assert "task" in held
"""

NEXT_MODULE_TESTS = "def test_next() -> None:\n    pass\n"

# a failed task in a cycle kept past its test by the module (frozen while alive), dropped by the
# last test of the session: found by the full collection after the last test
LAST_MODULE_TESTS = """
import asyncio

kept: list[dict[str, object]] = []


async def _fail() -> None:
    raise ValueError("kept past its test")


def test_keeps_one() -> None:
    loop = asyncio.new_event_loop()
    task = loop.create_task(_fail())
    loop.run_until_complete(asyncio.sleep(0))
    loop.close()
    holder: dict[str, object] = {"task": task}
    holder["self"] = holder
    kept.append(holder)


def test_drops_it() -> None:
    kept.clear()
"""


def test_a_failed_task_in_a_cycle_fails_its_own_test(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The small session runs in a process of its own: what it does on purpose (failed tasks
    in reference cycles, a full collection and a new freeze of the heap, records on the asyncio
    logger) is process-wide and must not reach the process running this suite. In-process, the
    garbage collector could free one of its failed tasks while pytest parsed source to report
    a failure; the task's logged traceback parses source too, and that nesting is a known
    Python 3.11 defect ("AST constructor recursion depth mismatch") that ended the whole worker.
    """
    pytester.makeconftest(INNER_CONFTEST)
    pytester.makeini(
        "[pytest]\nasyncio_default_fixture_loop_scope = function\n"
        "markers =\n    loop_errors_expected: on purpose\n"
    )
    pytester.makepyfile(
        test_one=INNER_TESTS,
        test_two=INNER_TESTS,
        test_wide=WIDE_FIXTURE_TESTS,
        test_x_next=NEXT_MODULE_TESTS,
        test_y_last=LAST_MODULE_TESTS,
    )
    monkeypatch.setenv("PYTHONPATH", str(ROOT))  # the inner conftest imports tests.conftest
    result = pytester.runpytest_subprocess("-p", "no:xdist", "-p", "no:cacheprovider", "-rE")
    # the rule fails a test at teardown, so pytest counts its call as passed and adds an error
    result.assert_outcomes(passed=13, errors=6)
    failed = sorted(line.split()[1] for line in result.outlines if line.startswith("ERROR test_"))
    assert failed == [
        f"{m}::{t}"
        for m in ("test_one.py", "test_two.py")
        for t in ("test_first_of_module", "test_later_in_module")
    ] + [
        "test_x_next.py::test_next",  # the module fixture's task: in the next module's first
        "test_y_last.py::test_drops_it",  # the task kept past its test: in the last test
    ]
    result.stdout.fnmatch_lines(
        [
            "the event loop logged 1 unhandled exception(s):",
            "  Task exception was never retrieved (ValueError: nobody looks at me)",
        ]
    )
    result.stdout.fnmatch_lines(
        ["  Task exception was never retrieved (ValueError: held by a module's fixture)"]
    )
    result.stdout.fnmatch_lines(
        ["  Task exception was never retrieved (ValueError: kept past its test)"]
    )
