"""The Lua dissectors in the real tshark: every golden vector of both specs, field by field.

One capture holds every vector (E71 binary and ASCII over TCP and UDP, S5-LAN-LINK, FETCH/WRITE
raw and in the MK header, AS511 on a serial line and over TCP) plus an answer for every error
code the codecs know; tshark reads it once (two passes, so requests know their answers) and
each decoded field is compared with the spec. The dissectors' value tables are compared with
the codecs' (tshark -G values), and reassembly across TCP segments is checked on split PDUs.
"""

from __future__ import annotations

import random
from collections.abc import Iterator
from pathlib import Path

import pytest

from plcstack.codecs.as511_jobs import FUNCTION_NAMES
from plcstack.codecs.e71_buffers import FIXED_BUFFER_END_CODES
from plcstack.codecs.e71_command_events import CPU_MODELS
from plcstack.codecs.e71_devices import DEVICE_NAMES, Device
from plcstack.codecs.e71_end_codes import ABNORMAL_CODES, END_CODES
from plcstack.codecs.e71_framing import COMMAND_NAMES, REQUEST_RULES
from plcstack.codecs.s5lan import AREA_LETTERS, ERR_MEANINGS
from plcstack.wire.dissectors import PROTOCOLS, write_dissectors
from plcstack.wire.pcapng import read_capture
from tests.wire_helpers import run_tool, tshark_fields, tshark_value_tables
from tests.wire_vectors import (
    AS511,
    E71_VECTORS,
    MK,
    S5LAN,
    CaptureBuilder,
    golden_capture,
    hexbytes,
)


@pytest.fixture(scope="module")
def plugins(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A private HOME whose personal Lua plugin folder holds the dissectors, as a user's
    Wireshark finds them after ``plcstack wireshark ~/.local/lib/wireshark/plugins``."""
    home = tmp_path_factory.mktemp("home")
    write_dissectors(home / ".local" / "lib" / "wireshark" / "plugins")
    yield home


@pytest.fixture(scope="module")
def golden(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("golden") / "golden.pcapng"
    path.write_bytes(golden_capture())
    return path


E71_FIELDS = [
    "frame.number",
    "tcp.stream",
    "udp.stream",
    "melsec1e.code",
    "melsec1e.command",
    "melsec1e.subheader",
    "melsec1e.pc",
    "melsec1e.timer",
    "melsec1e.device",
    "melsec1e.device_code",
    "melsec1e.head",
    "melsec1e.points",
    "melsec1e.block",
    "melsec1e.end_code",
    "melsec1e.fixed_end_code",
    "melsec1e.abnormal_code",
    "melsec1e.word",
    "melsec1e.bit",
    "melsec1e.state",
    "melsec1e.cpu_model",
    "melsec1e.address",
    "melsec1e.length",
    "melsec1e.module",
    "melsec1e.data",
    "melsec1e.request_in",
    "melsec1e.response_in",
    "_ws.col.Info",
]

#: what §12 says each request and answer holds (field -> value as tshark prints it); every
#: request also has pc 0xff (22: 0x05) and timer 10, every answer end code 0x00 unless said
E71_EXPECTED: list[tuple[dict[str, str], dict[str, str]]] = [
    # 1-3: 00H bit reads of M100
    (
        {
            "command": "0x00",
            "device": "M100",
            "device_code": "0x4d20",
            "head": "100",
            "points": "8",
        },
        {"subheader": "0x80", "bit": "1,0,1,0,0,1,1,0"},
    ),
    ({"device": "M100", "points": "12"}, {"bit": "1,0,1,0,1,0,1,0,1,0,1,0"}),
    ({"device": "M100", "points": "3"}, {"bit": "1,0,1"}),
    # 4, 5: 01H word reads
    (
        {"command": "0x01", "device": "Y40", "device_code": "0x5920", "head": "64", "points": "2"},
        {"subheader": "0x81", "word": "0x829d,0x553e"},
    ),
    (
        {"device": "D100", "device_code": "0x4420", "head": "100", "points": "3"},
        {"word": "0x1234,0x9876,0x0109"},
    ),
    # 6, 7: 02H bit writes of M50
    (
        {"command": "0x02", "device": "M50", "points": "12", "bit": "0,1,1,1,0,1,0,0,0,0,0,1"},
        {"subheader": "0x82", "end_code": "0x00"},
    ),
    ({"device": "M50", "points": "3", "bit": "1,0,1"}, {"subheader": "0x82"}),
    # 8: 03H word write
    (
        {"command": "0x03", "device": "D100", "points": "3", "word": "0x1234,0x9876,0x0109"},
        {"subheader": "0x83"},
    ),
    # 9: 04H bit test X94 ON, M60 OFF, B26 ON
    (
        {
            "command": "0x04",
            "points": "3",
            "device": "X94,M60,B26",
            "head": "148,60,38",
            "state": "0x01,0x00,0x01",
        },
        {"subheader": "0x84"},
    ),
    # 10: 05H word test Y80 = 7B29H, W26 = 1234H, CN18 = 0050H
    (
        {"command": "0x05", "device": "Y80,W26,CN18", "word": "0x7b29,0x1234,0x0050"},
        {"subheader": "0x85"},
    ),
    # 11: 06H register Y46, M12, B2C; 08H monitor Y46 ON, M12 OFF, B2C ON
    ({"command": "0x06", "points": "3", "device": "Y46,M12,B2C"}, {"subheader": "0x86"}),
    ({"command": "0x08"}, {"subheader": "0x88", "bit": "1,0,1"}),
    # 12: 07H register Y50, D38, W1E; 09H monitor E56DH, 1234H, 5678H
    ({"command": "0x07", "device": "Y50,D38,W1E"}, {"subheader": "0x87"}),
    ({"command": "0x09"}, {"subheader": "0x89", "word": "0xe56d,0x1234,0x5678"}),
    # 13: 15H CPU model A3N
    ({"command": "0x15"}, {"subheader": "0x95", "cpu_model": "0xa3"}),
    # 14, 15: 12H, 13H, 14H
    ({"command": "0x12"}, {"subheader": "0x92"}),
    ({"command": "0x13"}, {"subheader": "0x93"}),
    ({"command": "0x14"}, {"subheader": "0x94"}),
    # 16: 16H loopback 12 34 AB
    (
        {"command": "0x16", "length": "3", "data": "1234ab"},
        {"subheader": "0x96", "length": "3", "data": "1234ab"},
    ),
    # 17, 18: 0EH/0FH special module 13H
    (
        {"command": "0x0e", "address": "0x000007f0", "length": "4", "module": "0x13"},
        {"subheader": "0x8e", "data": "09182034"},
    ),
    (
        {"command": "0x0f", "address": "0x00000750", "module": "0x13", "data": "01234567"},
        {"subheader": "0x8f"},
    ),
    # 19: 17H ext. file register read: block 2, R70, 3 points
    (
        {"command": "0x17", "device": "R70", "head": "70", "block": "2", "points": "3"},
        {"subheader": "0x97", "word": "0x1234,0x8765,0x013f"},
    ),
    # 20: 19H: R26 of block 2 = 1234H, R19 of block 3 = 0109H
    (
        {
            "command": "0x19",
            "points": "2",
            "device": "R26,R19",
            "block": "2,3",
            "word": "0x1234,0x0109",
        },
        {"subheader": "0x99"},
    ),
    # 21: 3BH direct read R70, 4 points
    (
        {"command": "0x3b", "device": "R70", "points": "4"},
        {"subheader": "0xbb", "word": "0x1234,0x8765,0x013f,0x0020"},
    ),
    # 22-25: errors
    (
        {"command": "0x01", "pc": "0x05", "device": "D100", "points": "1"},
        {"end_code": "0x5b", "abnormal_code": "0x10"},
    ),
    ({"device": "M5", "points": "1"}, {"end_code": "0x58"}),
    ({"device_code": "0x5a20", "head": "0"}, {"end_code": "0x56"}),
    ({"command": "0x65"}, {"subheader": "0xe5", "end_code": "0x50"}),
    # 26: random access buffer write, then read
    (
        {"command": "0x62", "address": "0x00000000", "length": "3", "word": "0x1234,0x5678,0x9abc"},
        {"subheader": "0xe2", "end_code": "0x00"},
    ),
    (
        {"command": "0x61", "address": "0x00000000", "length": "3"},
        {"subheader": "0xe1", "word": "0x1234,0x5678,0x9abc"},
    ),
    # 27: 51H / 52H
    ({"command": "0x61", "address": "0x00001800", "length": "1"}, {"end_code": "0x51"}),
    ({"command": "0x61", "address": "0x000017ff", "length": "2"}, {"end_code": "0x52"}),
    # 28: fixed buffer with procedure, 3 words
    (
        {"command": "0x60", "length": "3", "word": "0x0001,0x0002,0x0003"},
        {"subheader": "0xe0", "fixed_end_code": "0x00"},
    ),
]


def _rows(fields: list[str], rows: list[list[str]]) -> list[dict[str, str]]:
    return [dict(zip(fields, row, strict=True)) for row in rows]


@pytest.fixture(scope="module")
def golden_rows(golden: Path, plugins: Path) -> list[dict[str, str]]:
    """Every dissected packet of the golden capture with the fields of every test: one
    tshark run (two passes, so requests know their answers) for all of them."""
    fields = list(
        dict.fromkeys(
            [*E71_FIELDS, *S5LAN_FIELDS, *H1_FIELDS, *AS511_FIELDS, "tcp.srcport", "tcp.dstport"]
        )
    )
    rows = tshark_fields(
        golden,
        fields,
        display_filter="melsec1e || s5lan || h1 || tanimk || as511",
        options=["-2"],
        home=plugins,
    )
    return _rows(fields, rows)


def _of(rows: list[dict[str, str]], field: str) -> list[dict[str, str]]:
    return [row for row in rows if row[field]]


@pytest.fixture(scope="module")
def e71_rows(golden_rows: list[dict[str, str]]) -> dict[str, list[dict[str, str]]]:
    """The E71 rows of each of the four conversations (TCP/UDP x binary/ASCII)."""
    by: dict[tuple[str, str], list[dict[str, str]]] = {}
    for row in _of(golden_rows, "melsec1e.code"):
        by.setdefault((row["tcp.stream"], row["udp.stream"]), []).append(row)
    conversations = list(by.values())
    assert len(conversations) == 4
    names = ["tcp binary", "tcp ascii", "udp binary", "udp ascii"]
    return dict(zip(names, conversations, strict=True))


def _check(row: dict[str, str], expected: dict[str, str], where: str) -> None:
    for name, value in expected.items():
        got = row[f"melsec1e.{name}"]
        assert got == value, f"{where}: melsec1e.{name} is {got!r}, the spec says {value!r}"


@pytest.mark.parametrize("conversation", ["tcp binary", "tcp ascii", "udp binary", "udp ascii"])
def test_every_e71_golden_vector_decodes_as_the_spec_says(
    e71_rows: dict[str, list[dict[str, str]]], conversation: str
) -> None:
    rows = e71_rows[conversation]
    code = "ASCII" if conversation.endswith("ascii") else "binary"
    for n, (request, answer) in enumerate(E71_EXPECTED):
        req, resp = rows[2 * n], rows[2 * n + 1]
        frames = f"frames {req['frame.number']}, {resp['frame.number']}"
        where = f"{conversation} exchange {n + 1} ({frames})"
        assert req["melsec1e.code"] == code and resp["melsec1e.code"] == code, where
        if request.get("command") not in ("0x60", "0x61", "0x62", "0x65"):
            assert req["melsec1e.pc"] == request.get("pc", "0xff"), where
            assert req["melsec1e.timer"] == "10", where
        _check(req, request, where + " request")
        _check(
            resp,
            {"end_code": "0x00", **answer} if "fixed_end_code" not in answer else answer,
            where + " answer",
        )
        # requests and answers find each other
        assert resp["melsec1e.request_in"] == req["frame.number"], where
        assert req["melsec1e.response_in"] == resp["frame.number"], where


@pytest.mark.parametrize("conversation", ["tcp binary", "tcp ascii", "udp binary", "udp ascii"])
def test_every_e71_end_and_abnormal_code_is_named(
    e71_rows: dict[str, list[dict[str, str]]], conversation: str
) -> None:
    answers = e71_rows[conversation][2 * len(E71_EXPECTED) + 1 :: 2]
    codes = [c for c in END_CODES if c not in (0x00, 0x5B)]
    expected = [(f"{c:#04x}", END_CODES[c], "") for c in codes]
    expected += [("0x5b", END_CODES[0x5B], ABNORMAL_CODES[a]) for a in ABNORMAL_CODES]
    fixed = [(f"{c:#04x}", FIXED_BUFFER_END_CODES[c], "") for c in FIXED_BUFFER_END_CODES]
    assert len(answers) == len(expected) + len(fixed)
    for row, (code, meaning, abnormal) in zip(answers, expected + fixed, strict=True):
        field = (
            "melsec1e.end_code"
            if row["melsec1e.subheader"] == "0x81"
            else "melsec1e.fixed_end_code"
        )
        assert row[field] == code
        if code != "0x00":
            assert meaning in row["_ws.col.Info"], row["_ws.col.Info"]
        if abnormal:
            assert abnormal in row["_ws.col.Info"]


S5LAN_FIELDS = [
    "frame.number",
    "s5lan.plc_type",
    "s5lan.header_length",
    "s5lan.cmd",
    "s5lan.data_type",
    "s5lan.area",
    "s5lan.db",
    "s5lan.start",
    "s5lan.count",
    "s5lan.err",
    "s5lan.version",
    "s5lan.user_code",
    "s5lan.address",
    "s5lan.data",
    "s5lan.word",
    "s5lan.request_in",
    "_ws.col.Info",
]


def test_the_s5lan_golden_vectors_decode_as_the_spec_says(
    golden_rows: list[dict[str, str]],
) -> None:
    rows = _of(golden_rows, "s5lan.plc_type")
    req1, resp1, req2, resp2, req3, resp3 = rows[:6]
    common = {"s5lan.plc_type": "0x35", "s5lan.header_length": "26"}
    # A.10-1: read DB10 from DW5, 20 words, UserCode 11 22 33 44; every word low byte first
    assert req1 | common == req1 and req1["s5lan.cmd"] == "0x52"
    assert (req1["s5lan.data_type"], req1["s5lan.area"], req1["s5lan.db"]) == ("0x57", "0x44", "10")
    assert (req1["s5lan.start"], req1["s5lan.count"], req1["s5lan.err"]) == ("5", "20", "0")
    assert (req1["s5lan.user_code"], req1["s5lan.address"]) == ("11223344", "DB10.DW5 x20")
    assert (resp1["s5lan.version"], resp1["s5lan.err"]) == ("104", "0")
    assert resp1["s5lan.word"] == ",".join(f"0x{0x1000 + i:04x}" for i in range(20))
    assert resp1["s5lan.request_in"] == req1["frame.number"]
    # A.10-2: write DE AD BE EF to MB100
    assert (req2["s5lan.cmd"], req2["s5lan.data_type"], req2["s5lan.area"]) == (
        "0x57",
        "0x42",
        "0x4d",
    )
    assert (req2["s5lan.start"], req2["s5lan.count"], req2["s5lan.data"]) == (
        "100",
        "4",
        "deadbeef",
    )
    assert (req2["s5lan.address"], resp2["s5lan.err"]) == ("MB100 x4", "0")
    # A.10-3: DB99 does not exist: Err 2
    assert (req3["s5lan.db"], resp3["s5lan.err"], resp3["s5lan.data"]) == ("99", "2", "")
    assert ERR_MEANINGS[2] in resp3["_ws.col.Info"]
    # every Err value the module documents, then an undocumented one
    errs = rows[6:][1::2]
    documented = [e for e in ERR_MEANINGS if e]
    assert [r["s5lan.err"] for r in errs] == [str(e) for e in documented] + ["-1"]
    for row, err in zip(errs, documented, strict=False):
        assert ERR_MEANINGS[err] in row["_ws.col.Info"]
    assert "unknown error -1" in errs[-1]["_ws.col.Info"]


H1_FIELDS = [
    "frame.number",
    "tcp.dstport",
    "tcp.srcport",
    "h1.opcode",
    "h1.org",
    "h1.dbnr",
    "h1.dwnr",
    "h1.dlen",
    "h1.resvalue",
    "tanimk.length",
    "tanimk.seq",
    "tanimk.more",
    "tanimk.life_ack",
    "tanimk.message_length",
    "tanimk.telegrams",
    "tanimk.request_in",
    "_ws.col.Info",
]


def test_fetchwrite_raw_and_in_the_mk_header_reach_the_sinec_h1_dissector(
    golden_rows: list[dict[str, str]],
) -> None:
    rows = [r for r in golden_rows if r["h1.opcode"] or r["tanimk.length"]]
    raw = [r for r in rows if "2000" in (r["tcp.dstport"], r["tcp.srcport"])]
    mk = [r for r in rows if "5030" in (r["tcp.dstport"], r["tcp.srcport"])]
    # C.10-1..3 raw: FETCH DB10 DW5 x20, WRITE MB100 x4, FETCH DB99 -> error 02
    assert [r["h1.opcode"] for r in raw[:6]] == ["0x05", "0x06", "0x03", "0x04", "0x05", "0x06"]
    assert (raw[0]["h1.org"], raw[0]["h1.dbnr"], raw[0]["h1.dwnr"], raw[0]["h1.dlen"]) == (
        "0x01",
        "10",
        "5",
        "20",
    )
    assert (raw[2]["h1.org"], raw[2]["h1.dwnr"], raw[2]["h1.dlen"]) == ("0x02", "100", "4")
    assert raw[5]["h1.resvalue"] == "2"
    assert [r["h1.resvalue"] for r in raw[7::2]] == [str(c) for c in (1, 2, 3, 4, 255)]
    # C.10-5 in the MK header: DataLen, SeqNo, the same H1 fields, the life data ack
    assert [r["tanimk.length"] for r in mk[:5]] == ["16", "56", "20", "16", "0"]
    assert [r["tanimk.seq"] for r in mk[:5]] == ["0", "0", "1", "1", "2"]
    assert [r["h1.opcode"] for r in mk[:4]] == ["0x05", "0x06", "0x03", "0x04"]
    assert mk[1]["tanimk.request_in"] == mk[0]["frame.number"]
    assert mk[4]["tanimk.life_ack"] == "1" and "life data ack" in mk[4]["_ws.col.Info"]
    # C.10-6: 616 bytes in two telegrams (more flag), reassembled and handed on
    first, second, ack = mk[5:8]
    assert (first["tanimk.length"], first["tanimk.more"], first["h1.opcode"]) == ("512", "1", "")
    assert (second["tanimk.length"], second["tanimk.more"]) == ("104", "0")
    assert (second["tanimk.message_length"], second["tanimk.telegrams"]) == ("616", "2")
    assert (second["h1.opcode"], second["h1.dbnr"], second["h1.dlen"]) == ("0x03", "10", "300")
    assert ack["h1.opcode"] == "0x04"


AS511_FIELDS = [
    "frame.number",
    "frame.interface_id",
    "as511.direction",
    "as511.step",
    "as511.function",
    "as511.nak",
    "as511.block_type",
    "as511.block_number",
    "as511.dw0_address",
    "as511.block_length",
    "as511.start_address",
    "as511.end_address",
    "as511.data",
    "as511.params",
    "as511.system_address",
    "as511.accept",
    "as511.terminate",
    "as511.request_in",
    "_ws.col.Info",
]


@pytest.mark.parametrize("transport", ["serial", "tcp"])
def test_the_as511_golden_dialogues_decode_step_by_step(
    golden_rows: list[dict[str, str]], transport: str
) -> None:
    rows = [
        r
        for r in _of(golden_rows, "as511.direction")
        if (r["frame.interface_id"] == "1") == (transport == "serial")
    ]
    # B.11.1: the 17 steps of B.4, one packet each, in order, directions alternating as B.4
    steps = [r["as511.step"] for r in rows[:17]]
    assert steps == [str(n) for n in range(1, 18)]
    from_pg = {1, 3, 5, 7, 8, 11, 13, 15, 17}
    assert [r["as511.direction"] for r in rows[:17]] == [
        "0" if n in from_pg else "1" for n in range(1, 18)
    ]
    assert rows[2]["as511.function"] == "0x1a" and FUNCTION_NAMES[0x1A] in rows[2]["_ws.col.Info"]
    assert (rows[7]["as511.block_type"], rows[7]["as511.block_number"]) == ("0x01", "5")
    assert (rows[11]["as511.dw0_address"], rows[11]["as511.block_length"]) == ("0x4a10", "21")
    assert (rows[5]["as511.accept"], rows[15]["as511.terminate"]) == ("0x16", "0x12")
    assert rows[16]["as511.request_in"] == rows[0]["frame.number"]
    # B.11.2: DB_READ 4A10H-4A17H; the data de-stuffed: 12 34 00 10 AB CD 10 10
    read = rows[17:34]
    assert (read[7]["as511.start_address"], read[7]["as511.end_address"]) == ("0x4a10", "0x4a17")
    assert read[11]["as511.data"] == "12340010abcd1010"
    # B.11.3: DB_WRITE at 4A14H of 01 02 10 03: no data frame, steps 1-9 then 14-17
    write = rows[34:47]
    assert [r["as511.step"] for r in write] == [str(n) for n in [*range(1, 10), 14, 15, 16, 17]]
    assert write[7]["as511.params"] == "4a1401021003"
    assert write[7]["as511.data"] == "01021003"
    # B.11.4: system parameters (PAE EF00H ... system data EA00H), MB0-3, stop, missing DB7
    system = rows[47:64]
    assert system[11]["as511.system_address"].split(",")[2:8] == [
        "0xef00",
        "0xef80",
        "0xee00",
        "0xed00",
        "0xec00",
        "0xea00",
    ]
    flags = rows[64:81]
    assert flags[11]["as511.data"] == "01020304"
    stop = rows[81:94]
    assert stop[7]["as511.params"] == "ea0c8804"
    missing = rows[94:]
    assert [r["as511.step"] for r in missing] == [str(n) for n in range(1, 10)]
    assert missing[-1]["as511.nak"] == "1"


def test_the_dissectors_tables_are_the_codecs(plugins: Path) -> None:
    """Every value table of every dissector, as tshark has registered it, against the codec
    table it was generated from: they cannot drift apart."""
    tables = tshark_value_tables(plugins, PROTOCOLS)
    assert tables["melsec1e.command"] == COMMAND_NAMES
    assert set(COMMAND_NAMES) == set(REQUEST_RULES)
    assert tables["melsec1e.end_code"] == END_CODES
    assert tables["melsec1e.fixed_end_code"] == FIXED_BUFFER_END_CODES
    assert tables["melsec1e.abnormal_code"] == ABNORMAL_CODES
    assert tables["melsec1e.cpu_model"] == CPU_MODELS
    assert tables["melsec1e.device_code"] == {
        d.code: f"{d.letters} ({DEVICE_NAMES[d]})" for d in Device
    }
    assert tables["s5lan.area"] == {ord(k): v for k, v in AREA_LETTERS.items()}
    assert {
        k - (1 << 16) if k > 0x7FFF else k: v for k, v in tables["s5lan.err"].items()
    } == ERR_MEANINGS
    assert tables["as511.function"] == FUNCTION_NAMES


def test_a_pdu_split_over_segments_is_reassembled(tmp_path: Path, plugins: Path) -> None:
    """A.10-1's answer in three segments (10, 30, 26 bytes), then two requests in one segment
    and their two answers in one: each PDU whole, each answer matched to its request."""
    _, request, answer = S5LAN[0]
    q, r = hexbytes(request), hexbytes(answer)
    q3, r3 = hexbytes(S5LAN[2][1]), hexbytes(S5LAN[2][2])
    build = CaptureBuilder()
    build.conversation(
        "tcp",
        5010,
        [
            (True, q),
            (False, r[:10]),
            (False, r[10:40]),
            (False, r[40:]),
            (True, q + q3),
            (False, r + r3),
        ],
    )
    path = tmp_path / "split.pcapng"
    path.write_bytes(build.bytes())
    fields = [
        "frame.number",
        "s5lan.count",
        "s5lan.err",
        "s5lan.request_in",
        "tcp.reassembled.length",
    ]
    rows = tshark_fields(path, fields, display_filter="s5lan", options=["-2"], home=plugins)
    assert [row[1:] for row in rows] == [
        ["20", "0", "", ""],
        ["20", "0", rows[0][0], "66"],
        ["20,1", "0,0", "", ""],
        ["20,1", "0,2", f"{rows[2][0]},{rows[2][0]}", ""],
    ]


def _fuzzed_capture(seed: int, rounds: int) -> bytes:
    """Golden frames cut short, with bytes changed, repeated, appended, or replaced by random
    bytes, on every dissector's port and on a serial line."""
    rng = random.Random(seed)
    seeds = [hexbytes(x) for _, q, r in S5LAN for x in (q, r)]
    seeds += [hexbytes(x) for _, x in MK]
    for _, _, exchanges in E71_VECTORS:
        for breq, bresp, areq, aresp in exchanges:
            seeds += [hexbytes(breq), hexbytes(bresp), areq.encode(), aresp.encode()]
    seeds += [hexbytes(x) for _, steps in AS511 for _, x in steps]

    def mutate(frame: bytes) -> bytes:
        kind = rng.randrange(5)
        if kind == 0:
            return frame[: rng.randrange(len(frame) + 1)]
        if kind == 1:
            return rng.randbytes(rng.randrange(1, 80))
        changed = bytearray(frame)
        for _ in range(rng.randrange(1, 4)):
            if changed:
                changed[rng.randrange(len(changed))] = rng.randrange(256)
        if kind == 3:
            changed += rng.randbytes(rng.randrange(1, 30))
        if kind == 4:
            changed *= rng.randrange(1, 4)
        return bytes(changed)

    build = CaptureBuilder()
    for kind, port in [
        ("tcp", 5000),
        ("udp", 5000),
        ("tcp", 5010),
        ("tcp", 5020),
        ("tcp", 5030),
        ("serial", 0),
    ]:
        for line in range(2):
            chunks = [(rng.random() < 0.5, mutate(rng.choice(seeds))) for _ in range(rounds)]
            build.conversation(kind, port, chunks, device=f"/dev/ttyS{line}")
    return build.bytes()


def test_fuzzed_frames_are_reported_malformed_never_a_crash_or_a_hang(
    tmp_path: Path, plugins: Path
) -> None:
    """Random and truncated frames on every dissector: tshark ends (bounded: 60 s), exits 0,
    flags malformed frames as expert info, and shows no Lua error."""
    path = tmp_path / "fuzz.pcapng"
    path.write_bytes(_fuzzed_capture(seed=40, rounds=80))
    proc = run_tool("tshark", ["-r", str(path), "-2", "-V"], home=plugins, timeout=60)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "Lua Error" not in out and "attempt to" not in out and ".lua:" not in out
    # malformed frames are expert errors of the malformed group; AS511 bytes out of place in
    # the dialogue are sequence warnings
    assert out.count("[Expert Info (Error/Malformed)") > 20
    assert out.count("not expected from the") > 20
    frames = len(list(read_capture(path.read_bytes())))
    assert out.count("\nFrame ") + out.startswith("Frame ") == frames  # every frame dissected


def test_as511_steps_merged_and_split_over_packets(tmp_path: Path, plugins: Path) -> None:
    """As a serial device server delivers it: consecutive steps of one side in one packet
    (DLE ACK + STX, DLE ACK + the parameter frame), and the data frame cut in two between
    the DLE of a doubled 10h and its second byte: the same 17 steps, the frame whole."""
    _, steps = AS511[1]  # B.11.2: DB_READ of DB5 DW0..DW3, a data frame with doubled DLEs
    merged: list[tuple[bool, bytes]] = []
    for from_pg, text in steps:
        data = hexbytes(text)
        if merged and merged[-1][0] == from_pg:
            merged[-1] = (from_pg, merged[-1][1] + data)
        else:
            merged.append((from_pg, data))
    chunks: list[tuple[bool, bytes]] = []
    for from_pg, data in merged:
        cut = data.find(b"\x10\x10")  # inside the data frame: 00 10 | 10 AB ...
        if not from_pg and len(data) > 8 and cut > 0:
            chunks += [(from_pg, data[: cut + 1]), (from_pg, data[cut + 1 :])]
        else:
            chunks.append((from_pg, data))
    build = CaptureBuilder()
    build.conversation("tcp", 5020, chunks)
    path = tmp_path / "as511-merged.pcapng"
    path.write_bytes(build.bytes())
    rows = tshark_fields(
        path, ["as511.step", "as511.data", "_ws.expert.message"], display_filter="as511",
        home=plugins,
    )  # fmt: skip
    steps_seen = [step for row in rows for step in row[0].split(",") if step]
    # the data frame's two parts are both step 12 (the first "continues")
    assert steps_seen == [*map(str, range(1, 13)), "12", *map(str, range(13, 18))]
    assert [row[1] for row in rows if row[1]] == ["12340010abcd1010"]
    assert not any("not expected" in row[2] for row in rows), rows
