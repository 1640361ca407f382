"""Fixtures shared by every test module: real servers on loopback (see tests/servers.py), and
the rule that no test may leave an unhandled exception in an event loop.

asyncio reports an exception nobody handled (a callback that raised, a task whose exception was
never retrieved, a transport error) through the loop's exception handler, which logs it on the
``asyncio`` logger at ERROR. Such a line in a test run is either a bug or a test that does not
clean up (a server cancelled mid-connection, a reader left registered); hundreds of them hid
real ones. So any such record during a test fails that test, with the records in the message.
A test that provokes one on purpose says so with ``@pytest.mark.loop_errors_expected`` (or
collects them itself with ``tests.robust_helpers.record_loop_errors``).
"""

from __future__ import annotations

import gc
import logging
from collections.abc import Iterator

import pytest

from tests.servers import influxd, mosquitto, nats_server

__all__ = ["influxd", "mosquitto", "nats_server"]


class _LoopErrors(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.fixture(autouse=True)
def _no_unhandled_loop_errors(request: pytest.FixtureRequest) -> Iterator[None]:
    handler = _LoopErrors()
    log = logging.getLogger("asyncio")
    log.addHandler(handler)
    try:
        yield
        # "Task exception was never retrieved" is reported only when the task is collected
        gc.collect()
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
