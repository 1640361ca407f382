"""Fixtures shared by every test module: real servers on loopback (see tests/servers.py)."""

from tests.servers import influxd, mosquitto, nats_server

__all__ = ["influxd", "mosquitto", "nats_server"]
