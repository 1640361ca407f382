"""A serial transport that is closed right after a write lets that write reach the line."""

from __future__ import annotations

import os
import tty

from plcstack.transports.serial import SerialTransport


async def test_the_last_write_reaches_the_line_before_the_port_is_let_go() -> None:
    """pyserial-asyncio sends from a writer callback; ``aclose`` waits for the buffer to go
    out. Before, a PG's closing DLE ACK was still buffered when ``aclose`` returned: the far
    end never got it, and a far end that went away next made asyncio log a fatal write error."""
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        line = SerialTransport(os.ttyname(slave), parity="N")
        await line.open(1.0)
        line.write(b"\x10\x06")
        await line.aclose()
        os.set_blocking(master, False)
        assert os.read(master, 16) == b"\x10\x06"
    finally:
        os.close(master)
        os.close(slave)
