"""Typed async clients, one module per protocol, all sharing one ``Client`` base, and
:func:`connect`, which picks the client for a URL."""

from plcstack.clients.as511 import AS511Client
from plcstack.clients.base import Client, ClientStats
from plcstack.clients.connect import SCHEMES, connect
from plcstack.clients.e71 import E71Client
from plcstack.clients.exchange import RequestClient
from plcstack.clients.fetchwrite import FetchWriteClient
from plcstack.clients.s5lan import S5LanClient

__all__ = [
    "SCHEMES",
    "AS511Client",
    "Client",
    "ClientStats",
    "E71Client",
    "FetchWriteClient",
    "RequestClient",
    "S5LanClient",
    "connect",
]
