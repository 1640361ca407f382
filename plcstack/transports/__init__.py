"""asyncio transports: bytes in and out, deadlines and reconnects; no protocol knowledge."""

from plcstack.transports.backoff import Backoff
from plcstack.transports.base import Transport
from plcstack.transports.tcp import TcpTransport
from plcstack.transports.udp import UdpTransport

__all__ = ["Backoff", "TcpTransport", "Transport", "UdpTransport", "ip_transport"]


def ip_transport(host: str | None, port: int | None, kind: str) -> Transport:
    """TCP or UDP (``kind``, as ``PlcUrl.transport`` names it) to ``host:port``."""
    if host is None or port is None:
        raise ValueError("an IP transport needs a host and a port")
    if kind == "udp":
        return UdpTransport(host, port)
    if kind == "tcp":
        return TcpTransport(host, port)
    raise ValueError(f"not an IP transport: {kind!r}")
