"""Sans-IO codecs: pure byte <-> event translation, one module per wire protocol.

No module here does I/O, reads a clock or sleeps; time comes in as a ``now`` argument where a
protocol needs deadlines (AS511). Both roles (client and PLC) live in the same module so the client
and the simulator share one encoder/decoder. Every protocol module has a ``ClientConnection`` and a
``ServerConnection`` with ``send(event) -> bytes``, ``receive_data`` and ``next_event``; events
derive from :class:`Event`; see ``_common`` for the ERROR state.
"""

from plcstack.codecs._common import NEED_DATA, ErrorState, Event, NeedData, ReceiveBuffer

__all__ = ["NEED_DATA", "ErrorState", "Event", "NeedData", "ReceiveBuffer"]
