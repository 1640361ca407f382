"""aiomqtt's socket-write registration, made safe against a socket closed before it runs.

paho asks for a writer from the thread that connects; the loop registers it later. A connect
that fails closes the socket first. Reproduced here without timing: the registration is asked
for, the socket closed, and only then does the loop run. aiomqtt's own client logs "Bad file
descriptor" as an unhandled loop exception (which fails any test here); the sink's does not,
and registers nothing.
"""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path

import pytest

aiomqtt = pytest.importorskip("aiomqtt")

from plcstack.north.mqtt_client import guarded_client  # noqa: E402


async def _register_then_close(client: object) -> list[dict[str, object]]:
    loop = asyncio.get_running_loop()
    errors: list[dict[str, object]] = []
    previous = loop.get_exception_handler()
    loop.set_exception_handler(lambda _, context: errors.append(context))
    a, b = socket.socketpair()
    try:
        paho = client._client  # type: ignore[attr-defined]
        # as paho does in its connecting thread: ask for a writer, then the connect fails and
        # the socket is closed, all before the loop gets to run the registration
        fileno = a.fileno()
        paho.on_socket_register_write(paho, None, a)
        a.close()
        for _ in range(3):
            await asyncio.sleep(0)
        registered = loop._selector.get_map().get(fileno)  # type: ignore[attr-defined]
        assert registered is None or registered.data[1] is None, "a writer on a closed socket"
    finally:
        loop.set_exception_handler(previous)
        b.close()
    return errors


async def test_a_registration_for_a_closed_socket_is_dropped() -> None:
    client = guarded_client(aiomqtt)("127.0.0.1", 1)
    assert await _register_then_close(client) == []


async def test_aiomqtts_own_client_logs_the_bad_descriptor() -> None:
    """What the guard is for: without it the loop reports an unhandled OSError."""
    errors = await _register_then_close(aiomqtt.Client("127.0.0.1", 1))
    assert errors and isinstance(errors[0].get("exception"), OSError), errors


def test_every_mqtt_connection_of_the_product_uses_the_guarded_client() -> None:
    """The sink and the scale-out presence both meet resets (the presence's when a worker loses
    its broker); a new ``aiomqtt.Client(`` anywhere else would bring the race back."""
    root = Path(__file__).resolve().parents[1] / "plcstack"
    builders = [
        f"{path.relative_to(root)}:{n}"
        for path in sorted(root.rglob("*.py"))
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if "aiomqtt.Client(" in line
    ]
    assert builders == [], builders
    users = {
        path.relative_to(root).as_posix()
        for path in root.rglob("*.py")
        if "guarded_client(aiomqtt)(" in path.read_text(encoding="utf-8")
    }
    assert users == {"north/mqtt.py", "scale/presence.py"}, users
