"""asyncio transports: bytes in and out, deadlines and reconnects; no protocol knowledge."""

from plcstack.transports.backoff import Backoff
from plcstack.transports.base import Transport
from plcstack.transports.tcp import TcpTransport
from plcstack.transports.udp import UdpTransport

__all__ = ["Backoff", "TcpTransport", "Transport", "UdpTransport"]
