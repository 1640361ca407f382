"""E71 end codes (spec §10) and the abnormal codes that follow end code 5BH (§4.3).

One table for the codec's :class:`~plcstack.codecs.e71.ErrorResponse`, the client's error
messages and :mod:`plcstack.diagnose`.
"""

from __future__ import annotations

from typing import Final

__all__ = ["ABNORMAL_CODES", "END_CODES", "GARBAGE_END_CODES"]

END_CODES: Final[dict[int, str]] = {
    0x00: "normal completion",
    0x50: "subheader/command not one of the defined formats",
    0x51: "random access buffer start address outside 0-6143",
    0x52: "random access buffer start address + word count outside 0-6143, or too many words "
    "for one message; fixed buffer data count wrong",
    0x54: "ASCII data from the partner could not be converted (non-hex characters)",
    0x55: "write to the CPU refused: CPU in RUN and write during RUN not enabled (or a "
    "parameter/program write while in RUN; a plcstack gateway refuses so a write outside its "
    "writable list)",
    0x56: "wrong device specification (unknown device code)",
    0x57: "number of points exceeds the per-request limit or the device range, command length "
    "wrong, write data count does not match, or monitor without prior registration",
    0x58: "head device number out of range, word device with a bit-unit command, or bit device "
    "head not a multiple of 16 in a word-unit command",
    0x59: "extended file register access on an A1(N) CPU",
    0x5B: "E71 and CPU cannot communicate / the CPU cannot process the request",
    0x60: "exchange between E71 and CPU exceeded the ACPU monitoring timer (a plcstack gateway "
    "answers so when the PLC behind it did not answer, or the request waited too long)",
}

ABNORMAL_CODES: Final[dict[int, str]] = {
    0x10: "wrong PC number (no PLC with this number)",
    0x11: "mode error (E71 and CPU could not exchange data)",
    0x12: "special function module specification error",
    0x13: "program step number error",
    0x18: "remote RUN/STOP not possible (mode already changed remotely by another station)",
    0x20: "link error (the CPU given by the PC number cannot be accessed)",
    0x21: "special function module bus error",
}

#: end codes of bytes that are no E71 request at all (an undefined subheader or command, ASCII
#: that is not hex): what a client that speaks another protocol or sends noise gets, never a
#: request a working client sends and the PLC refuses (those have the other codes)
GARBAGE_END_CODES: Final = frozenset({0x50, 0x54})
