"""How a connection's far end is named in logs and in the write audit: ``host:port``.

Every server that takes writes from the network (the web console, the Modbus TCP server, the
OPC UA server, the gateway's S5-LAN and FETCH/WRITE servers) names its client with this one
function, so an auditor reads the same address for the same client whichever side it used.
"""

from __future__ import annotations

__all__ = ["peer_address"]


def peer_address(peername: object) -> str | None:
    """``host:port`` (``[v6]:port``) of a connection's peer; None when there is none to say.

    ``peername`` is what the socket says (``transport.get_extra_info("peername")``): a tuple
    ``(host, port, ...)``, a Unix socket's path (a name, or empty for an unnamed one), or None
    (no transport, or one already closed).
    """
    if isinstance(peername, tuple | list) and len(peername) >= 2:
        host, port = peername[0], peername[1]
        return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"
    if isinstance(peername, bytes):
        peername = peername.decode(errors="replace")
    if isinstance(peername, str) and peername:
        return peername
    return None
