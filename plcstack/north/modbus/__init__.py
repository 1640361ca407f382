"""A Modbus TCP server in front of the poller (``plcstack serve modbus``; docs/modbus.md).

- :mod:`~plcstack.north.modbus.config` - ``[modbus]`` and the register map (overlaps refused);
- :mod:`~plcstack.north.modbus.registers` - how each tag type becomes registers;
- :mod:`~plcstack.north.modbus.frames` - the Modbus TCP frames, Sans-IO;
- :mod:`~plcstack.north.modbus.service` - what a request is answered with (reads, writes);
- :mod:`~plcstack.north.modbus.server` - the asyncio server, its clients and metrics.

No third-party dependency: see frames.py for why pymodbus's server is not used.
"""

from plcstack.north.modbus.config import ModbusSettings, build_map, parse_modbus
from plcstack.north.modbus.server import ModbusCollector, ModbusServer

__all__ = ["ModbusCollector", "ModbusServer", "ModbusSettings", "build_map", "parse_modbus"]
