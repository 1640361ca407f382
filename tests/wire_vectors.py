"""The golden vectors of both protocol specs as captures: what the dissector tests read.

Every vector of specs/melsec-e71.md §12 (binary and ASCII, TCP and UDP) and of
specs/siemens-s5.md (A.10 S5-LAN-LINK, B.11 AS511, C.10 FETCH/WRITE raw and in the MK header),
written with the same recording code the capture file uses, plus one answer for every end
code, abnormal code and Err value the codecs know (the goldens hold only some of them).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from plcstack.codecs.e71_buffers import FIXED_BUFFER_END_CODES
from plcstack.codecs.e71_end_codes import ABNORMAL_CODES, END_CODES
from plcstack.codecs.fetchwrite import ERROR_MEANINGS
from plcstack.codecs.s5lan import ERR_MEANINGS
from plcstack.transports.tap import Endpoints
from plcstack.wire.recording import Recording

#: microseconds of the first packet (2023-11-14 22:13:20 UTC); one millisecond apart
START = 1_700_000_000_000_000

#: §12: (number, case, [(binary request, binary answer, ASCII request, ASCII answer), ...])
E71_VECTORS: list[tuple[int, str, list[tuple[str, str, str, str]]]] = [
    (
        1,
        "00H bit read M100, 8 points",
        [
            (
                "00 FF 0A 00 64 00 00 00 20 4D 08 00",
                "80 00 10 10 01 10",
                "00FF000A4D20000000640800",
                "800010100110",
            )
        ],
    ),
    (
        2,
        "00H bit read M100, 12 points",
        [
            (
                "00 FF 0A 00 64 00 00 00 20 4D 0C 00",
                "80 00 10 10 10 10 10 10",
                "00FF000A4D20000000640C00",
                "8000101010101010",
            )
        ],
    ),
    (
        3,
        "00H odd count M100, 3 points",
        [
            (
                "00 FF 0A 00 64 00 00 00 20 4D 03 00",
                "80 00 10 10",
                "00FF000A4D20000000640300",
                "80001010",
            )
        ],
    ),
    (
        4,
        "01H word read Y40, 2 words",
        [
            (
                "01 FF 0A 00 40 00 00 00 20 59 02 00",
                "81 00 9D 82 3E 55",
                "01FF000A5920000000400200",
                "8100829D553E",
            )
        ],
    ),
    (
        5,
        "01H word read D100-D102",
        [
            (
                "01 FF 0A 00 64 00 00 00 20 44 03 00",
                "81 00 34 12 76 98 09 01",
                "01FF000A4420000000640300",
                "8100123498760109",
            )
        ],
    ),
    (
        6,
        "02H bit write M50-M61",
        [
            (
                "02 FF 0A 00 32 00 00 00 20 4D 0C 00 01 11 01 00 00 01",
                "82 00",
                "02FF000A4D20000000320C00011101000001",
                "8200",
            )
        ],
    ),
    (
        7,
        "02H odd count M50-M52",
        [
            (
                "02 FF 0A 00 32 00 00 00 20 4D 03 00 10 10",
                "82 00",
                "02FF000A4D200000003203001010",
                "8200",
            )
        ],
    ),
    (
        8,
        "03H word write D100-D102",
        [
            (
                "03 FF 0A 00 64 00 00 00 20 44 03 00 34 12 76 98 09 01",
                "83 00",
                "03FF000A4420000000640300123498760109",
                "8300",
            )
        ],
    ),
    (
        9,
        "04H bit test X94 M60 B26",
        [
            (
                "04 FF 0A 00 03 00 94 00 00 00 20 58 01 3C 00 00 00 20 4D 00 26 00 00 00 20 42 01",
                "84 00",
                "04FF000A0300582000000094014D200000003C0042200000002601",
                "8400",
            )
        ],
    ),
    (
        10,
        "05H word test Y80 W26 CN18",
        [
            (
                "05 FF 0A 00 03 00 80 00 00 00 20 59 29 7B 26 00 00 00 20 57 34 12 "
                "12 00 00 00 4E 43 50 00",
                "85 00",
                "05FF000A03005920000000807B295720000000261234434E000000120050",
                "8500",
            )
        ],
    ),
    (
        11,
        "06H register, 08H monitor",
        [
            (
                "06 FF 0A 00 03 00 46 00 00 00 20 59 0C 00 00 00 20 4D 2C 00 00 00 20 42",
                "86 00",
                "06FF000A03005920000000464D200000000C42200000002C",
                "8600",
            ),
            ("08 FF 0A 00", "88 00 10 10", "08FF000A", "88001010"),
        ],
    ),
    (
        12,
        "07H register, 09H monitor",
        [
            (
                "07 FF 0A 00 03 00 50 00 00 00 20 59 26 00 00 00 20 44 1E 00 00 00 20 57",
                "87 00",
                "07FF000A030059200000005044200000002657200000001E",
                "8700",
            ),
            ("09 FF 0A 00", "89 00 6D E5 34 12 78 56", "09FF000A", "8900E56D12345678"),
        ],
    ),
    (13, "15H CPU model", [("15 FF 0A 00", "95 00 A3 00", "15FF000A", "9500A300")]),
    (14, "12H parameter analysis", [("12 FF 0A 00", "92 00", "12FF000A", "9200")]),
    (
        15,
        "13H/14H remote RUN/STOP",
        [
            ("13 FF 0A 00", "93 00", "13FF000A", "9300"),
            ("14 FF 0A 00", "94 00", "14FF000A", "9400"),
        ],
    ),
    (
        16,
        "16H loopback",
        [("16 FF 0A 00 03 12 34 AB", "96 00 03 12 34 AB", "16FF000A031234AB", "9600031234AB")],
    ),
    (
        17,
        "0EH special module read",
        [
            (
                "0E FF 0A 00 F0 07 00 04 13 00",
                "8E 00 09 18 20 34",
                "0EFF000A0007F0041300",
                "8E0009182034",
            )
        ],
    ),
    (
        18,
        "0FH special module write",
        [
            (
                "0F FF 0A 00 50 07 00 04 13 00 01 23 45 67",
                "8F 00",
                "0FFF000A00075004130001234567",
                "8F00",
            )
        ],
    ),
    (
        19,
        "17H ext file register read",
        [
            (
                "17 FF 0A 00 46 00 00 00 20 52 02 00 03 00",
                "97 00 34 12 65 87 3F 01",
                "17FF000A00025220000000460300",
                "970012348765013F",
            )
        ],
    ),
    (
        20,
        "19H ext file register test",
        [
            (
                "19 FF 0A 00 02 00 1A 00 00 00 20 52 02 00 34 12 13 00 00 00 20 52 03 00 09 01",
                "99 00",
                "19FF000A0200000252200000001A123400035220000000130109",
                "9900",
            )
        ],
    ),
    (
        21,
        "3BH direct read R70",
        [
            (
                "3B FF 0A 00 46 00 00 00 20 52 04 00",
                "BB 00 34 12 65 87 3F 01 20 00",
                "3BFF000A5220000000460400",
                "BB0012348765013F0020",
            )
        ],
    ),
    (
        22,
        "5BH abnormal: PC number",
        [
            (
                "01 05 0A 00 64 00 00 00 20 44 01 00",
                "81 5B 10 00",
                "0105000A4420000000640100",
                "815B1000",
            )
        ],
    ),
    (
        23,
        "58H head not multiple of 16",
        [("01 FF 0A 00 05 00 00 00 20 4D 01 00", "81 58", "01FF000A4D20000000050100", "8158")],
    ),
    (
        24,
        "56H unknown device code",
        [("01 FF 0A 00 00 00 00 00 20 5A 01 00", "81 56", "01FF000A5A20000000000100", "8156")],
    ),
    (25, "50H undefined subheader", [("65 FF 0A 00", "E5 50", "65FF000A", "E550")]),
    (
        26,
        "RAB write then read",
        [
            ("62 00 00 00 03 00 34 12 78 56 BC 9A", "E2 00", "620000000003123456789ABC", "E200"),
            ("61 00 00 00 03 00", "E1 00 34 12 78 56 BC 9A", "610000000003", "E100123456789ABC"),
        ],
    ),
    (
        27,
        "RAB 51H/52H",
        [
            ("61 00 00 18 01 00", "E1 51", "610018000001", "E151"),
            ("61 00 FF 17 02 00", "E1 52", "610017FF0002", "E152"),
        ],
    ),
    (
        28,
        "fixed buffer with procedure",
        [("60 00 03 00 01 00 02 00 03 00", "E0 00", "60000003000100020003", "E000")],
    ),
]

A10_DATA = " ".join(f"{i:02X} 10" for i in range(20))

#: (case, request, response) of A.10
S5LAN = [
    (
        "A.10-1 read DB10 DW5 x20",
        "35 00 00 00 1A 52 57 44 0A 00 05 00 14 00 00 00 00 00 11 22 33 44 00 00 00 00",
        "35 00 00 00 1A 52 57 44 0A 00 05 00 14 00 00 00 68 00 11 22 33 44 00 00 00 00 " + A10_DATA,
    ),
    (
        "A.10-2 write MB100 x4",
        "35 00 00 00 1A 57 42 4D 00 00 64 00 04 00 00 00 00 00 00 00 00 00 00 00 00 00 DE AD BE EF",
        "35 00 00 00 1A 57 42 4D 00 00 64 00 04 00 00 00 68 00 00 00 00 00 00 00 00 00",
    ),
    (
        "A.10-3 Err 2",
        "35 00 00 00 1A 52 57 44 63 00 00 00 01 00 00 00 00 00 00 00 00 00 00 00 00 00",
        "35 00 00 00 1A 52 57 44 63 00 00 00 01 00 02 00 68 00 00 00 00 00 00 00 00 00",
    ),
]

C10_DATA = " ".join(f"10 {i:02X}" for i in range(20))
#: (case, request, response) of C.10, raw FETCH/WRITE
FETCHWRITE = [
    (
        "C.10-1 FETCH DB10 DW5 x20",
        "53 35 10 01 03 05 03 08 01 0A 00 05 00 14 FF 02",
        "53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00 " + C10_DATA,
    ),
    (
        "C.10-2 WRITE MB100 x4",
        "53 35 10 01 03 03 03 08 02 00 00 64 00 04 FF 02 DE AD BE EF",
        "53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00",
    ),
    (
        "C.10-3 FETCH DB99 error 02",
        "53 35 10 01 03 05 03 08 01 63 00 00 00 01 FF 02",
        "53 35 10 01 03 06 0F 03 02 FF 07 00 00 00 00 00",
    ),
]
#: C.10-5: the telegrams on each side, in order: (from the PC?, bytes)
MK = [
    (True, "4D 4B 10 00 00 00 00 00 53 35 10 01 03 05 03 08 01 0A 00 05 00 14 FF 02"),
    (False, "4D 4B 38 00 00 00 00 00 53 35 10 01 03 06 0F 03 00 FF 07 00 00 00 00 00 " + C10_DATA),
    (True, "4D 4B 14 00 00 00 01 00 53 35 10 01 03 03 03 08 02 00 00 64 00 04 FF 02 DE AD BE EF"),
    (False, "4D 4B 10 00 00 00 01 00 53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00"),
    (True, "4D 4B 00 00 00 00 02 00"),
]
#: C.10-6: WRITE DB10 DW0 x300 split over two telegrams (the PC's counter at 1)
_SPLIT_HEAD = "53 35 10 01 03 03 03 08 01 0A 00 00 01 2C FF 02"
_SPLIT_DATA = bytes((i * 7) & 0xFF for i in range(600))


def mk_split() -> list[tuple[bool, bytes]]:
    message = bytes.fromhex(_SPLIT_HEAD) + _SPLIT_DATA
    first = bytes.fromhex("4D 4B 00 02 01 00 01 00") + message[:512]
    second = bytes.fromhex("4D 4B 68 00 00 00 02 00") + message[512:]
    ack = bytes.fromhex("4D 4B 10 00 00 00 01 00 53 35 10 01 03 04 0F 03 00 FF 07 00 00 00 00 00")
    return [(True, first), (True, second), (False, ack)]


#: AS511 transactions of B.11: (case, [(from the PG?, hex), ...]) step by step
def _steps_1_to_7(fn: str) -> list[tuple[bool, str]]:
    return [
        (True, "02"),
        (False, "10 06"),
        (True, fn),
        (False, "02"),
        (True, "10 06"),
        (False, "16 10 03"),
        (True, "10 06"),
    ]


_END = [(False, "02"), (True, "10 06"), (False, "12 10 03"), (True, "10 06")]
AS511 = [
    (
        "B.11.1 B_INFO DB5",
        [
            *_steps_1_to_7("1A"),
            (True, "01 05 10 04"),
            (False, "10 06"),
            (False, "02"),
            (True, "10 06"),
            (False, "00 4A 10 10 70 70 41 05 00 00 00 00 00 15 10 03"),
            (True, "10 06"),
            *_END,
        ],
    ),
    (
        "B.11.2 DB_READ DB5 DW0-DW3",
        [
            *_steps_1_to_7("04"),
            (True, "4A 10 10 4A 17 10 04"),
            (False, "10 06"),
            (False, "02"),
            (True, "10 06"),
            (False, "00 00 00 00 00 12 34 00 10 10 AB CD 10 10 10 10 10 03"),
            (True, "10 06"),
            *_END,
        ],
    ),
    (
        "B.11.3 DB_WRITE DB5 DW2-DW3",
        [*_steps_1_to_7("03"), (True, "4A 14 01 02 10 10 03 10 04"), (False, "10 06"), *_END],
    ),
    (
        "B.11.4 system parameters",
        [
            *_steps_1_to_7("18"),
            (True, "10 04"),
            (False, "10 06"),
            (False, "02"),
            (True, "10 06"),
            (
                False,
                "00 00 00 00 00 EF 00 EF 80 EE 00 ED 00 EC 00 EA 00 00 00 7F FF 00 00 02 00 02 00 "
                "02 00 02 00 02 00 02 00 02 00 00 00 00 00 00 05 00 00 00 00 00 00 00 00 10 03",
            ),
            (True, "10 06"),
            *_END,
        ],
    ),
    (
        "B.11.4 read MB0-MB3",
        [
            *_steps_1_to_7("04"),
            (True, "EE 00 EE 03 10 04"),
            (False, "10 06"),
            (False, "02"),
            (True, "10 06"),
            (False, "00 00 00 00 00 01 02 03 04 10 03"),
            (True, "10 06"),
            *_END,
        ],
    ),
    ("B.11.4 stop", [*_steps_1_to_7("03"), (True, "EA 0C 88 04 10 04"), (False, "10 06"), *_END]),
    ("B.11.4 B_INFO missing DB7", [*_steps_1_to_7("1A"), (True, "01 07 10 04"), (False, "10 15")]),
]


# -- every code the codecs know, answered once ------------------------------------------------


def e71_code_exchanges() -> list[tuple[str, str, str, str]]:
    """E71 exchanges as the §12 ones (binary request and answer, ASCII request and answer):
    vector 5's read answered with each end code (5BH once per abnormal code), and a fixed
    buffer telegram answered with each fixed-buffer end code."""
    read = ("01 FF 0A 00 64 00 00 00 20 44 03 00", "01FF000A4420000000640300")
    fixed = ("60 00 01 00 34 12", "600000011234")
    out = [(read[0], f"81 {c:02X}", read[1], f"81{c:02X}") for c in END_CODES if c not in (0, 0x5B)]
    out += [(read[0], f"81 5B {a:02X} 00", read[1], f"815B{a:02X}00") for a in ABNORMAL_CODES]
    out += [(fixed[0], f"E0 {c:02X}", fixed[1], f"E0{c:02X}") for c in FIXED_BUFFER_END_CODES]
    return out


def s5lan_err_exchanges() -> list[tuple[str, str]]:
    """A.10-3's request answered with every Err value the module documents, and one it
    does not (-1)."""
    request = S5LAN[2][1]
    head = "35 00 00 00 1A 52 57 44 63 00 00 00 01 00"
    pairs = []
    for err in [*ERR_MEANINGS, -1]:
        if err == 0:
            continue
        value = (err & 0xFFFF).to_bytes(2, "little").hex(" ")
        pairs.append((request, f"{head} {value} 68 00 00 00 00 00 00 00 00 00"))
    return pairs


def fetchwrite_error_exchanges() -> list[tuple[str, str]]:
    """C.10-3's FETCH answered with every error field value of C.6.4."""
    request = FETCHWRITE[2][1]
    return [
        (request, f"53 35 10 01 03 06 0F 03 {code:02X} FF 07 00 00 00 00 00")
        for code in ERROR_MEANINGS
        if code
    ]


# -- captures -------------------------------------------------------------------------------


class CaptureBuilder:
    """A pcapng file built packet by packet, as the capture tap would record it."""

    def __init__(self) -> None:
        self.recording = Recording()
        self.blocks = bytearray(self.recording.header())
        self.micros = START
        self._port = 40000

    def conversation(
        self,
        kind: str,
        server_port: int,
        chunks: Iterable[tuple[bool, bytes]],
        *,
        device: str = "",
    ) -> None:
        """One connection (TCP), pair of ends (UDP) or line (serial, ``device``): each chunk
        ``(from the client, bytes)`` one packet, a millisecond after the one before."""
        self._port += 1
        if kind == "serial":
            endpoints = Endpoints("serial", ("", 0), ("", 0), "local", device)
        else:
            endpoints = Endpoints(
                kind,  # type: ignore[arg-type]
                ("127.0.0.1", self._port),
                ("127.0.0.1", server_port),
                "local",
            )
        stream, blocks = self.recording.open(endpoints, self.micros)
        self.blocks += blocks
        for from_client, data in chunks:
            self.micros += 1000
            self.blocks += self.recording.data(stream, from_client, data, self.micros)
        self.blocks += self.recording.end(stream, False, self.micros)

    def bytes(self) -> bytes:
        return bytes(self.blocks)


def hexbytes(text: str) -> bytes:
    return bytes.fromhex(text)


def e71_chunks(code: str) -> list[tuple[bool, bytes]]:
    """Every §12 exchange in order, then the code answers (binary or ASCII)."""
    chunks: list[tuple[bool, bytes]] = []
    for _, _, exchanges in E71_VECTORS:
        for breq, bresp, areq, aresp in exchanges:
            if code == "binary":
                chunks += [(True, hexbytes(breq)), (False, hexbytes(bresp))]
            else:
                chunks += [(True, areq.encode()), (False, aresp.encode())]
    for breq, bresp, areq, aresp in e71_code_exchanges():
        if code == "binary":
            chunks += [(True, hexbytes(breq)), (False, hexbytes(bresp))]
        else:
            chunks += [(True, areq.encode()), (False, aresp.encode())]
    return chunks


def _pairs(pairs: Sequence[tuple[str, str]]) -> list[tuple[bool, bytes]]:
    return [chunk for q, r in pairs for chunk in ((True, hexbytes(q)), (False, hexbytes(r)))]


def golden_capture() -> bytes:
    """Every golden vector of both specs in one file, on the dissectors' default ports."""
    build = CaptureBuilder()
    for kind in ("tcp", "udp"):
        for code in ("binary", "ascii"):
            build.conversation(kind, 5000, e71_chunks(code))
    build.conversation("tcp", 5010, _pairs([(q, r) for _, q, r in S5LAN]))
    build.conversation("tcp", 5010, _pairs(s5lan_err_exchanges()))
    build.conversation("tcp", 2000, _pairs([(q, r) for _, q, r in FETCHWRITE]))
    build.conversation("tcp", 2000, _pairs(fetchwrite_error_exchanges()))
    build.conversation("tcp", 5030, [(pc, hexbytes(x)) for pc, x in MK])
    build.conversation("tcp", 5030, mk_split())
    steps = [(pg, hexbytes(x)) for _, transaction in AS511 for pg, x in transaction]
    build.conversation("serial", 0, steps, device="/dev/ttyS0")
    build.conversation("tcp", 5020, steps)
    return build.bytes()
