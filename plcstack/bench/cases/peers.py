"""Case 4: peers from PyPI, only when installed (never a dependency of plcstack).

``hslcommunication`` (the Python package, binary 1E ``MelsecA1ENet`` and ``SiemensFetchWriteNet``)
is what "a thread per PLC with a blocking library" looks like in practice: one blocking client per
PLC, each in its own OS thread, against the same simulators as the stack. Its licence limits it to
research use, so it is only ever an optional local peer; install it yourself to see its row.

Each client is connected once (``ConnectServer``) so the comparison is against long-lived
connections, as the stack and the floor use; HSL's default is a new TCP connection per request.
"""

from __future__ import annotations

import importlib
import struct
from collections.abc import Callable
from typing import Any

from plcstack.bench.cases import WORDS, ProtocolCase, Unavailable

__all__ = ["PEER_PROTOCOLS", "hsl_available", "hsl_reader"]

#: protocol cases a peer exists for
PEER_PROTOCOLS = ("e71+tcp", "fetchwrite")


def hsl_available() -> bool:
    try:
        importlib.import_module("HslCommunication")
    except ImportError:
        return False
    return True


def hsl_reader(case: ProtocolCase) -> Callable[[str, int], Callable[[], list[int]]]:
    """A factory: ``make(host, port)`` -> a blocking ``read()`` of the case's 64 words."""
    try:
        hsl: Any = importlib.import_module("HslCommunication")
    except ImportError:
        raise Unavailable("hslcommunication not installed (optional peer)") from None
    if case.key == "e71+tcp":
        cls, address, raw_bytes = hsl.MelsecA1ENet, "D0", False
    elif case.key == "fetchwrite":
        # HSL's "DB10.0" puts 0 in the start field: DW0 on a Siemens-style (word) server. Its
        # ReadUInt16 swaps the bytes of S5 words (1.2.0), so read bytes and unpack big-endian.
        cls, address, raw_bytes = hsl.SiemensFetchWriteNet, "DB10.0", True
    else:
        raise Unavailable(f"no hslcommunication client for {case.key}")

    def make(host: str, port: int) -> Callable[[], list[int]]:
        client = cls(host, port)
        connected = client.ConnectServer()
        if not connected.IsSuccess:
            raise RuntimeError(f"hslcommunication could not connect: {connected.Message}")

        def read() -> list[int]:
            if raw_bytes:
                result = client.Read(address, 2 * WORDS)
            else:
                result = client.ReadUInt16(address, WORDS)
            if not result.IsSuccess:
                raise RuntimeError(f"hslcommunication read failed: {result.Message}")
            if raw_bytes:
                return list(struct.unpack(f">{WORDS}H", bytes(result.Content)))
            return list(result.Content)

        return read

    return make
