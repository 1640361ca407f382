"""The pcapng capture: what the tap records, read back by our reader and by the real tshark.

The file is checked against the format by Wireshark itself (capinfos, tshark with every
checksum check on and TCP analysis), against the bytes the clients really exchanged (tshark's
"follow stream" of each connection), and against what the pcapng draft says the blocks hold.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

import plcstack
from plcstack.sim import as511 as as511_sim
from plcstack.sim import e71 as e71_sim
from plcstack.sim import fetchwrite as fw_sim
from plcstack.sim import s5lan as s5lan_sim
from plcstack.transports.tap import Endpoints, capturing
from plcstack.transports.tcp import TcpTransport, _TcpProtocol
from plcstack.wire.capture import FLUSH_DELAY, PcapngCapture, parse_size
from plcstack.wire.packets import (
    IpAddress,
    checksum,
    ip_address,
    parse_ip,
    tcp_packet,
    udp_packet,
)
from plcstack.wire.pcapng import (
    LINKTYPE_RAW,
    LINKTYPE_WIRESHARK_UPPER_PDU,
    enhanced_packet,
    read_capture,
    section_header,
)
from plcstack.wire.recording import Recording
from tests.wire_helpers import capinfos, tshark, tshark_fields

# -- the blocks, as the draft lays them out ---------------------------------------------------


def test_section_header_is_the_drafts_layout() -> None:
    block = section_header("plcstack")
    block_type, total, magic, major, minor, length = struct.unpack_from("<IIIHHq", block)
    assert (block_type, magic, major, minor, length) == (0x0A0D0D0A, 0x1A2B3C4D, 1, 0, -1)
    assert total == len(block) and total % 4 == 0
    assert struct.unpack_from("<I", block, total - 4)[0] == total


def test_enhanced_packet_pads_and_repeats_its_length() -> None:
    block = enhanced_packet(0, (5 << 32) | 7, b"abcde", direction=2, comment="x")
    block_type, total, iface, high, low, captured, original = struct.unpack_from("<7I", block)
    assert (block_type, iface, high, low, captured, original) == (6, 0, 5, 7, 5, 5)
    assert total == len(block) and total % 4 == 0
    assert block[28:33] == b"abcde" and block[33:36] == b"\x00\x00\x00"
    # epb_flags (code 2, length 4) = outbound, then the comment, then opt_endofopt
    assert struct.unpack_from("<HHI", block, 36) == (2, 4, 2)
    assert struct.unpack_from("<I", block, total - 4)[0] == total


def test_checksum_is_rfc_1071s_example() -> None:
    # RFC 1071 section 3: the words 0001 f203 f4f5 f6f7 sum to ddf2; the checksum is its
    # complement
    assert checksum(bytes.fromhex("0001f203f4f5f6f7")) == 0xFFFF - 0xDDF2
    assert checksum(bytes.fromhex("0001f203f4f5f6")) == checksum(bytes.fromhex("0001f203f4f5f600"))


def test_packets_parse_back() -> None:
    src, dst = plcstack_ip("10.0.0.1"), plcstack_ip("10.0.0.2")
    tcp = parse_ip(tcp_packet(src, dst, 1234, 5000, 7, 9, 0x18, b"hello"))
    assert tcp is not None and (tcp.sport, tcp.dport, tcp.seq, tcp.ack, tcp.payload) == (
        1234,
        5000,
        7,
        9,
        b"hello",
    )
    v6 = parse_ip(udp_packet(plcstack_ip("::1"), plcstack_ip("::2"), 1, 2, b"x"))
    assert v6 is not None and v6.payload == b"x" and v6.src.version == 6
    assert parse_ip(b"\x45") is None and parse_ip(b"") is None


def plcstack_ip(text: str) -> IpAddress:
    return ip_address(text)


def test_size_limits_parse() -> None:
    assert parse_size("100M") == 100 * 1024 * 1024
    assert parse_size("512k") == 512 * 1024
    assert parse_size("8192") == 8192
    for bad in ("1k", "lots", ""):
        with pytest.raises(ValueError):
            parse_size(bad)


# -- real traffic, recorded and read by tshark ------------------------------------------------


@contextlib.contextmanager
def recorded(path: Path, limit: int = 100 * 1024 * 1024) -> Iterator[PcapngCapture]:
    capture = PcapngCapture(path, limit=limit).open()
    try:
        with capturing(capture):
            yield capture
    finally:
        capture.close()


async def _client_traffic(path: Path) -> None:
    """One capture of every transport the clients use (simulators started outside the
    capture, so only the client side is recorded); returns what each exchanged."""
    e71 = await e71_sim.start()
    e71u = await e71_sim.start(transport="udp")
    lan = await s5lan_sim.start()
    mk = await fw_sim.start(mk=True)
    try:
        with recorded(path):
            async with plcstack.connect(e71.url) as plc:
                await plc.write("D100", [0x1234, 0x9876, 0x0109])
                assert await plc.read("D100", 3) == [0x1234, 0x9876, 0x0109]
            async with plcstack.connect(e71u.url) as plc:
                await plc.read("D0", 2)
            async with plcstack.connect(lan.url) as plc:
                await plc.read("DB10.DW5", 20)
            async with plcstack.connect(mk.url) as plc:
                await plc.read("DB10.DW0", 250)  # an answer over two MK telegrams
    finally:
        for sim in (e71, e71u, lan, mk):
            await sim.aclose()


async def test_a_capture_of_every_transport_reads_clean_in_tshark(tmp_path: Path) -> None:
    path = tmp_path / "clients.pcapng"
    await _client_traffic(path)
    info = capinfos(path)
    assert "pcapng" in info and "Raw IP" in info
    checks = [
        "-o",
        "ip.check_checksum:TRUE",
        "-o",
        "tcp.check_checksum:TRUE",
        "-o",
        "udp.check_checksum:TRUE",
    ]
    # one tshark run: checksums, TCP analysis, handshakes and closes, directions
    fields = ["frame.number", "ip.checksum.status", "tcp.checksum.status", "udp.checksum.status",
              "tcp.analysis.flags", "tcp.stream", "tcp.flags.syn", "tcp.flags.fin",
              "frame.packet_flags_direction"]  # fmt: skip
    rows = [
        dict(zip(fields, row, strict=True)) for row in tshark_fields(path, fields, options=checks)
    ]
    assert rows
    for row in rows:
        statuses = {row[f] for f in fields[1:4] if row[f]}
        assert statuses == {"1"}, f"frame {row['frame.number']}: checksum status {statuses}"
    # TCP analysis finds nothing wrong: no lost segment, no retransmission, no unseen ACK
    flagged = [row["frame.number"] for row in rows if row["tcp.analysis.flags"]]
    assert flagged == [], f"TCP analysis flagged frames: {flagged}"
    # every TCP connection has its handshake and its close
    by_stream: dict[str, set[str]] = {}
    for row in rows:
        if row["tcp.stream"]:
            flags = by_stream.setdefault(row["tcp.stream"], set())
            flags |= {"syn"} if row["tcp.flags.syn"] in ("1", "True") else set()
            flags |= {"fin"} if row["tcp.flags.fin"] in ("1", "True") else set()
    assert len(by_stream) == 3, by_stream
    assert all(flags == {"syn", "fin"} for flags in by_stream.values()), by_stream
    # every packet says its direction
    directions = {row["frame.packet_flags_direction"] for row in rows}
    assert directions <= {"1", "2", "0x00000001", "0x00000002"} and len(directions) == 2


class ListTap:
    """A tap that keeps what it is told, as (event, value) pairs."""

    def __init__(self) -> None:
        self.events: list[tuple[str, object]] = []

    def connection(self, endpoints: Endpoints) -> ListTap:
        self.events.append(("open", endpoints.kind))
        return self

    def sent(self, data: bytes) -> None:
        self.events.append(("sent", data))

    def received(self, data: bytes) -> None:
        self.events.append(("received", data))

    def ended(self, by_peer: bool) -> None:
        self.events.append(("ended", by_peer))

    def joined(self, event: str) -> bytes:
        return b"".join(v for e, v in self.events if e == event and isinstance(v, bytes))


async def test_the_followed_stream_is_the_bytes_exchanged(tmp_path: Path) -> None:
    """tshark's "follow TCP stream" gives back exactly what went over the socket (seen by a
    second tap on the same transport: both record, as with --pcap and the flight recorder)."""
    path = tmp_path / "e71.pcapng"
    sim = await e71_sim.start()
    own = ListTap()
    try:
        with recorded(path):
            plc = plcstack.connect(sim.url)
            plc.transport.record_to(own)
            async with plc:
                await plc.read("D100", 3)
                await plc.write("D100", [1, 2, 3])
    finally:
        await sim.aclose()
    out = tshark(["-r", str(path), "-q", "-z", "follow,tcp,raw,0"]).splitlines()
    data = [line for line in out[out.index("Node 1: " + f"127.0.0.1:{sim.port}") + 1 :] if line]
    sent = "".join(line for line in data if not line.startswith(("\t", "=")))
    received = "".join(line.strip() for line in data if line.startswith("\t"))
    assert bytes.fromhex(sent) == own.joined("sent")
    assert bytes.fromhex(received) == own.joined("received")
    assert own.joined("sent").startswith(bytes.fromhex("01ff"))  # a 01H batch read


async def test_a_simulator_started_in_the_block_is_recorded_from_its_side(
    tmp_path: Path,
) -> None:
    path = tmp_path / "sim.pcapng"
    capture = PcapngCapture(path).open()
    try:
        with capturing(capture):
            sim = await e71_sim.start()
        try:
            # the client is outside the block: only the simulator's side is recorded
            async with plcstack.connect(sim.url) as plc:
                await plc.read("D0", 1)
        finally:
            await sim.aclose()
    finally:
        capture.close()
    rows = tshark_fields(
        path,
        [
            "tcp.srcport",
            "tcp.dstport",
            "tcp.flags.syn",
            "tcp.flags.ack",
            "frame.packet_flags_direction",
        ],
    )
    # the SYN comes from the client (the far end): towards the simulator's port, inbound
    syn = rows[0]
    assert syn[1] == str(sim.port) and syn[2] in ("1", "True") and syn[3] in ("0", "False")
    assert syn[4] in ("1", "0x00000001")


async def test_stream_and_datagram_simulators_are_recorded_from_their_side(
    tmp_path: Path,
) -> None:
    """The asyncio-streams simulators (S5-LAN) and a UDP one (E71) work as before when
    tapped, and their side of the traffic is in the file."""
    path = tmp_path / "sims.pcapng"
    capture = PcapngCapture(path).open()
    try:
        with capturing(capture):
            lan = await s5lan_sim.start()
            udp = await e71_sim.start(transport="udp")
        try:
            async with plcstack.connect(lan.url) as plc:
                await plc.write("DB10.DW5", [0x1000])
                assert await plc.read("DB10.DW5", 1) == [0x1000]
            async with plcstack.connect(udp.url) as plc:
                assert await plc.read("D0", 2) == [0, 0]
        finally:
            await lan.aclose()
            await udp.aclose()
    finally:
        capture.close()
    rows = tshark_fields(path, ["tcp.srcport", "udp.srcport", "tcp.len", "udp.length"])
    tcp_data = [row for row in rows if row[0] and row[2] not in ("", "0")]
    assert [row[0] == str(lan.port) for row in tcp_data] == [False, True, False, True]
    udp_rows = [row for row in rows if row[1]]
    assert [row[1] == str(udp.port) for row in udp_rows] == [False, True]


async def test_an_as511_line_is_an_exported_pdu_with_its_direction(tmp_path: Path) -> None:
    path = tmp_path / "as511.pcapng"
    sim = await as511_sim.start_pty()
    try:
        with recorded(path):
            async with plcstack.connect(sim.url) as plc:
                await plc.read("DB1.DW0", 2)
    finally:
        await sim.aclose()
    packets = list(read_capture(path.read_bytes()))
    assert {p.linktype for p in packets} == {LINKTYPE_WIRESHARK_UPPER_PDU}
    assert {p.interface for p in packets} == {sim.path}
    rows = tshark_fields(
        path, ["exported_pdu.prot_name", "frame.p2p_dir", "exported_pdu.exported_pdu"]
    )
    assert {row[0] for row in rows} == {"as511"}
    # the PG starts every transaction with STX (02), sent; the PLC answers DLE ACK, received
    assert rows[0][1:] == ["0", "02"]
    assert rows[1][1] == "1" and rows[1][2].startswith("1006")


async def test_a_capture_is_flushed_as_it_goes(tmp_path: Path) -> None:
    path = tmp_path / "live.pcapng"
    sim = await e71_sim.start()
    try:
        with recorded(path) as capture:
            async with plcstack.connect(sim.url) as plc:
                await plc.read("D0", 1)
                assert len(list(read_capture(path.read_bytes()))) < 5  # still buffered
                # the flush is a timer FLUSH_DELAY after the first unflushed block: one that
                # comes due later on the same loop runs after it
                await asyncio.sleep(2 * FLUSH_DELAY)
                # read while the capture is still open: the request and its answer are there
                packets = list(read_capture(path.read_bytes()))
                assert len(packets) == 5  # handshake (3), request, answer
                assert capture.packets == 2
    finally:
        await sim.aclose()


async def test_at_its_limit_the_capture_rotates_and_both_parts_read(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "rot.pcapng"
    sim = await e71_sim.start()
    try:
        with recorded(path, limit=8192) as capture:
            async with plcstack.connect(sim.url) as plc:
                for _ in range(100):
                    await plc.read("D0", 64)
    finally:
        await sim.aclose()
    older = tmp_path / "rot.pcapng.1"
    assert capture.rotations >= 2 and older.exists()
    assert path.stat().st_size <= 8192 and older.stat().st_size <= 8192
    warnings = [r for r in caplog.records if "reached its limit" in r.getMessage()]
    assert [r.levelname for r in warnings][:1] == ["WARNING"]
    assert {r.levelname for r in warnings[1:]} <= {"INFO"}
    for part in (path, older):
        # each part opens on its own (the connection's handshake synthesised again) and
        # reads clean
        rows = tshark_fields(part, ["tcp.flags.syn", "tcp.analysis.flags"])
        assert any(syn in ("1", "True") for syn, _ in rows), f"{part.name} has no handshake"
        flagged = [flags for _, flags in rows if flags]
        assert flagged == [], f"{part.name}: {flagged}"


def _mount_tmpfs(where: Path, size: str) -> None:
    proc = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        pytest.fail(f"cannot mount a tmpfs (the full-disk test runs as root): {proc.stderr}")


async def test_a_full_disk_stops_the_capture_not_the_polling(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    disk = tmp_path / "disk"
    disk.mkdir()
    _mount_tmpfs(disk, "64k")
    try:
        sim = await e71_sim.start()
        try:
            with recorded(disk / "full.pcapng") as capture:
                async with plcstack.connect(sim.url) as plc:
                    for _ in range(300):
                        assert await plc.read("D0", 64) == [0] * 64
                        await asyncio.sleep(0)
        finally:
            await sim.aclose()
        assert capture.failure is not None and "No space left" in capture.failure
        assert capture.lost > 0
        errors = [
            r for r in caplog.records if r.levelname == "ERROR" and "capture" in r.getMessage()
        ]
        assert len(errors) == 1, "a failed capture is said once"
    finally:
        await asyncio.to_thread(subprocess.run, ["umount", str(disk)], check=False)


async def test_without_a_tap_the_connection_is_the_plain_one() -> None:
    """Zero cost when off: the plain protocol class and the asyncio transport's own write."""
    sim = await e71_sim.start()
    try:
        transport = TcpTransport(sim.host, sim.port)
        await transport.open(1.0)
        try:
            assert type(transport._protocol) is _TcpProtocol
            assert transport._send == transport._transport.write  # type: ignore[union-attr]
        finally:
            await transport.aclose()
    finally:
        await sim.aclose()


async def test_record_to_records_one_transport() -> None:
    tap = ListTap()
    sim = await e71_sim.start()
    try:
        plc = plcstack.connect(sim.url)
        plc.transport.record_to(tap)
        async with plc:
            await plc.read("D100", 3)
    finally:
        await sim.aclose()
    assert tap.events[0] == ("open", "tcp")
    assert tap.events[1][0] == "sent" and tap.events[2][0] == "received"
    assert tap.events[-1] == ("ended", False)


def test_a_resumed_recording_starts_each_open_stream_again() -> None:
    rec = Recording()
    ep = Endpoints("tcp", ("127.0.0.1", 40000), ("127.0.0.1", 5000), "local")
    stream, _ = rec.open(ep, 0)
    rec.data(stream, True, b"abc", 1)
    blocks = rec.resume(2)
    packets = [p for p in read_capture(blocks) if p.linktype == LINKTYPE_RAW]
    syn = parse_ip(packets[0].data)
    assert syn is not None and syn.flags == 0x02 and syn.seq == stream.local_seq - 1


async def test_an_as511_line_recorded_at_the_plc_says_sent_for_the_programming_device(
    tmp_path: Path,
) -> None:
    """The pty simulator recorded from its side: each frame's exported-PDU direction still
    names the programming device as the sender of "sent" (so one dissector reads both ends'
    captures), while the packet flags (and Wireshark's frame.p2p_dir, taken from them) say
    inbound/outbound as the PLC saw them."""
    path = tmp_path / "ag.pcapng"
    capture = PcapngCapture(path).open()
    try:
        with capturing(capture):
            ag = await as511_sim.start_pty()
        try:
            async with plcstack.connect(ag.url) as pg:
                await pg.read("DB1.DW0", 1)
        finally:
            await ag.aclose()
    finally:
        capture.close()
    rows = tshark_fields(
        path, ["exported_pdu.p2p_dir", "frame.packet_flags_direction", "exported_pdu.exported_pdu"]
    )
    # the PG's STX: sent by the programming device, inbound at the PLC
    assert rows[0][0] == "0" and rows[0][1] in ("1", "0x00000001") and rows[0][2] == "02"
    # the PLC's DLE ACK: received by the programming device, outbound at the PLC
    assert rows[1][0] == "1" and rows[1][1] in ("2", "0x00000002")
