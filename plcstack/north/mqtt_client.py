"""The aiomqtt client every MQTT connection of plcstack uses: the north side's sink and the
scale-out workers' presence.

aiomqtt's own ``Client`` has one race this one closes (see :func:`guarded_client`); a test checks
that no other module builds an ``aiomqtt.Client`` of its own.
"""

from __future__ import annotations

import functools
from typing import Any

__all__ = ["guarded_client"]


@functools.cache  # one class per aiomqtt module, not one per session
def guarded_client(aiomqtt: Any) -> Any:
    """``aiomqtt.Client`` whose socket-write registration survives a socket closed first.

    paho asks for a writer when it has bytes to send (from the thread that connects, or the
    loop); aiomqtt then schedules ``loop.add_writer(fd)`` with the descriptor read at that
    moment. A connect that fails (a broker that requires a client certificate closes at once)
    or a connection the broker resets closes the socket before the loop runs it: asyncio logs
    "Bad file descriptor", or, if a PLC connection got the same descriptor number meanwhile,
    the writer lands on that socket. Here the loop checks, when it runs, that the socket still
    has that descriptor.
    """

    class GuardedClient(aiomqtt.Client):  # type: ignore[misc]
        def _on_socket_register_write(self, client: Any, userdata: Any, sock: Any) -> None:
            fileno = sock.fileno()
            loop = self._loop

            def callback() -> None:
                # as aiomqtt's: a failed write means the connection broke
                try:
                    client.loop_write()
                except Exception as exc:
                    if not self._disconnected.done():
                        self._disconnected.set_exception(exc)

            def register() -> None:
                if fileno >= 0 and sock.fileno() == fileno:  # closed: -1
                    loop.add_writer(fileno, callback)

            loop.call_soon_threadsafe(register)

    return GuardedClient
