"""plcstack: an asyncio protocol stack for legacy PLCs.

async with plcstack.connect("e71+tcp://10.0.0.5:5000") as plc:
    words = await plc.read("D100", 10)
"""

from plcstack.errors import (
    AddressError,
    ConnectFailed,
    ConnectionLost,
    LocalProtocolError,
    PlcError,
    PlcErrorResponse,
    PlcTimeout,
    RemoteProtocolError,
)
from plcstack.url import PlcUrl, connect, parse_url

__version__ = "0.1.0"

__all__ = [
    "AddressError",
    "ConnectFailed",
    "ConnectionLost",
    "LocalProtocolError",
    "PlcError",
    "PlcErrorResponse",
    "PlcTimeout",
    "PlcUrl",
    "RemoteProtocolError",
    "__version__",
    "connect",
    "parse_url",
]
