"""Typed async clients, one module per protocol, all sharing one ``Client`` base."""

from plcstack.clients.base import Client, ClientStats, RequestClient

__all__ = ["Client", "ClientStats", "RequestClient"]
