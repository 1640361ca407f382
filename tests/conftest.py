"""Fixtures shared by every test module: real servers on loopback (see tests/servers.py)."""

from tests.servers import influxd, mosquitto

__all__ = ["influxd", "mosquitto"]
