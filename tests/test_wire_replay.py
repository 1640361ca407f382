"""Replay of a capture: conversations read back, the in-order matcher, and the end to end
promise: a capture of ``plcstack poll`` against the simulators, replayed by ``plcstack sim
replay``, gives the same samples when polled again."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import struct
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

import plcstack
from plcstack.errors import PlcError
from plcstack.sim import as511 as as511_sim
from plcstack.sim import e71 as e71_sim
from plcstack.sim import s5lan as s5lan_sim
from plcstack.transports.tap import capturing
from plcstack.wire import replay
from plcstack.wire.capture import PcapngCapture
from plcstack.wire.packets import ACK, PSH, ip_address, tcp_packet, udp_packet
from plcstack.wire.pcapng import LINKTYPE_ETHERNET
from plcstack.wire.script import Script
from plcstack.wire.streams import Exchange, conversations, exchanges
from tests.cli_helpers import cli_in_process

ROOT = Path(__file__).resolve().parent.parent


# -- conversations read back --------------------------------------------------------------------


def _classic_pcap(frames: list[bytes]) -> bytes:
    """A libpcap file of Ethernet frames, as tcpdump writes one."""
    out = struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, LINKTYPE_ETHERNET)
    for i, frame in enumerate(frames):
        out += struct.pack("<IIII", 1_700_000_000 + i, 0, len(frame), len(frame)) + frame
    return out


def _ethernet(packet: bytes) -> bytes:
    return b"\x02" * 6 + b"\x04" * 6 + b"\x08\x00" + packet


def test_tcp_is_reassembled_in_order_with_retransmissions_taken_once() -> None:
    """A field capture: a retransmitted segment, one that arrives early, no handshake."""
    pc, plc = ip_address("10.0.0.1"), ip_address("10.0.0.5")

    def seg(to_plc: bool, seq: int, ack: int, data: bytes) -> bytes:
        src, dst, sport, dport = (pc, plc, 40000, 5000) if to_plc else (plc, pc, 5000, 40000)
        return _ethernet(tcp_packet(src, dst, sport, dport, seq, ack, PSH | ACK, data))

    frames = [
        seg(True, 100, 900, b"REQ1"),
        seg(True, 100, 900, b"REQ1"),  # retransmission
        seg(False, 904, 104, b"B"),  # early: comes before "A" in the capture
        seg(False, 900, 104, b"ANS"),
        seg(False, 903, 104, b"A"),
        seg(True, 104, 905, b"REQ2"),
        seg(False, 905, 108, b"ANS2"),
    ]
    (conversation,) = conversations(_classic_pcap(frames))
    assert (conversation.kind, conversation.client, conversation.server) == (
        "tcp",
        "10.0.0.1:40000",
        "10.0.0.5:5000",
    )
    assert [(e.request, e.answers) for e in exchanges(conversation)] == [
        (b"REQ1", (b"ANSAB",)),
        (b"REQ2", (b"ANS2",)),
    ]


def test_udp_keeps_datagrams_and_the_client_is_who_spoke_first() -> None:
    pc, plc = ip_address("10.0.0.1"), ip_address("10.0.0.5")
    frames = [
        _ethernet(udp_packet(pc, plc, 40001, 5000, b"Q1")),
        _ethernet(udp_packet(plc, pc, 5000, 40001, b"A1")),
        _ethernet(udp_packet(plc, pc, 5000, 40001, b"A2")),
        _ethernet(udp_packet(pc, plc, 40001, 5000, b"Q2")),
    ]
    (conversation,) = conversations(_classic_pcap(frames))
    assert conversation.server == "10.0.0.5:5000"
    assert [(e.request, e.answers) for e in exchanges(conversation)] == [
        (b"Q1", (b"A1", b"A2")),
        (b"Q2", ()),
    ]


# -- the matcher ------------------------------------------------------------------------------


def _script(*pairs: tuple[bytes, bytes], repeat: bool = True) -> Script:
    return Script("x", [Exchange(q, (a,), 0.0, i) for i, (q, a) in enumerate(pairs)], repeat=repeat)


def test_requests_take_their_answers_in_order_and_start_again() -> None:
    script = _script((b"R", b"1"), (b"W", b"ok"), (b"R", b"2"))
    answers = [script.match(q).exchange for q in (b"R", b"R", b"W", b"R")]
    assert [a.answers[0] for a in answers if a is not None] == [b"1", b"2", b"ok", b"1"]
    assert script.rounds == 2


def test_a_request_in_pieces_waits_for_its_rest() -> None:
    """The AS511 dialogue: DLE ACK and the parameter frame may come in two reads."""
    script = _script((b"\x10\x06\x01\x05\x10\x04", b"\x10\x06\x02"), (b"\x10\x06", b"data"))
    assert script.match(b"\x10\x06").kind == "wait"
    match = script.match(b"\x10\x06\x01\x05\x10\x04")
    assert match.kind == "answer" and match.exchange is not None
    assert match.exchange.answers == (b"\x10\x06\x02",)
    assert script.match(b"\x10\x06").kind == "answer"


def test_counted_fields_match_any_value_and_the_user_code_is_echoed() -> None:
    """S5-LAN's UserCode (the client's request number, echoed by the module) and the MK
    header's SeqNo are no part of what is asked."""
    head = bytes.fromhex("35 00 00 00 1A 52 57 44 0A 00 05 00 01 00 00 00 00 00")
    tail = bytes(4)
    recorded_q = head + b"\x01\x00\x00\x00" + tail
    recorded_a = head[:16] + b"\x68\x00" + b"\x01\x00\x00\x00" + tail + b"\x34\x12"
    script = _script((recorded_q, recorded_a))
    asked = head + b"\x07\x00\x00\x00" + tail
    match = script.match(asked)
    assert match.kind == "answer"
    assert match.answers == (recorded_a[:18] + b"\x07\x00\x00\x00" + recorded_a[22:],)
    # a second round: the recorded request again, with the next number the client counts
    again = script.match(head + b"\x08\x00\x00\x00" + tail)
    assert again.kind == "answer" and script.rounds == 2
    assert again.answers == (recorded_a[:18] + b"\x08\x00\x00\x00" + recorded_a[22:],)
    mk = _script((bytes.fromhex("4D4B 0200 0000 0000 5335"), b"ok"))
    assert mk.match(bytes.fromhex("4D4B 0200 0000 0500 5335")).kind == "answer"
    assert mk.match(bytes.fromhex("4D4B 0200 0000 0600 5336")).kind == "mismatch"


def test_a_request_not_recorded_is_a_mismatch_naming_the_nearest() -> None:
    script = _script((b"\x01\xff\x0a\x00\x64", b"x"), repeat=False)
    match = script.match(b"\x01\xff\x0a\x00\x65")
    assert match.kind == "mismatch" and match.differs_at == 4
    assert match.nearest == b"\x01\xff\x0a\x00\x64"
    assert script.match(b"\x01\xff\x0a\x00\x64").kind == "answer"
    assert script.match(b"\x01\xff\x0a\x00\x64").kind == "mismatch"  # --once: used up
    assert script.mismatches == 2


# -- end to end -------------------------------------------------------------------------------


def _config(path: Path, e71_url: str, lan_url: str) -> Path:
    path.write_text(
        f"""
[poll]
interval = 0.05
timeout = 0.5           # the recording's last request may be unanswered (the poll ended)

[[plc]]
name = "press"
url = "{e71_url}"
[plc.tags]
strokes = {{ address = "D100", type = "uint16" }}
alarm = {{ address = "M0", type = "bool" }}

[[plc]]
name = "oven"
url = "{lan_url}"
[plc.tags]
temperature = {{ address = "DB10.DW0", type = "int16" }}
""",
        encoding="utf-8",
    )
    return path


async def _poll(
    config: Path, *extra: str, enough: Callable[[list[dict[str, object]]], bool]
) -> list[dict[str, object]]:
    """``plcstack poll`` until its samples are ``enough``, then SIGTERM (exit 0): every sample
    it printed. A fixed --duration gave a loaded machine fewer scans than the checks need, and
    an idle one waited it out."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "plcstack", "poll", str(config), *extra,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=env,
    )  # fmt: skip
    samples: list[dict[str, object]] = []
    try:
        assert proc.stdout is not None
        async with asyncio.timeout(30):
            while not enough(samples):
                line = await proc.stdout.readline()
                assert line, f"poll ended after {len(samples)} samples"
                samples.append(json.loads(line))
        proc.terminate()
        out, err = await asyncio.wait_for(proc.communicate(), 30)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode == 0, err.decode()
    return samples + [json.loads(line) for line in out.decode().splitlines()]


def _each_tag_at_least(n: int) -> Callable[[list[dict[str, object]]], bool]:
    """Enough once each of the three tags of ``_config`` has ``n`` samples."""
    return lambda samples: (
        len(_series(samples)) == 3 and all(len(v) >= n for v in _series(samples).values())
    )


Series = dict[tuple[object, object], list[tuple[object, object]]]


def _series(samples: list[dict[str, object]]) -> Series:
    """(value, quality) of each sample, by (PLC, tag), in the order they came."""
    series: Series = {}
    for sample in samples:
        series.setdefault((sample["plc"], sample["tag"]), []).append(
            (sample["value"], sample["quality"])
        )
    return series


async def test_a_replayed_poll_gives_the_same_samples(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    e71 = await e71_sim.start()
    lan = await s5lan_sim.start()
    running = True

    async def change() -> None:
        # the plant moves on while it is recorded: every scan may see other values
        n = 0
        while running:
            n += 1
            e71.memory.write_words("D", 100, [n])
            e71.memory.write_bits("M", 0, [n % 3 == 0])
            lan.memory.write_db_words(10, 0, [(n * 7) & 0x7FFF])
            await asyncio.sleep(0.03)

    changer = asyncio.create_task(change())
    capture = tmp_path / "plant.pcapng"
    try:
        config = _config(tmp_path / "plant.toml", e71.url, lan.url)
        recorded = await _poll(
            config,
            "--pcap",
            str(capture),
            enough=lambda s: (
                _each_tag_at_least(5)(s)
                and len({v for v, _ in _series(s)[("press", "strokes")]}) > 3
            ),
        )
    finally:
        running = False
        await changer
        await e71.aclose()
        await lan.aclose()
    first = _series(recorded)
    assert len({v for v, _ in first[("press", "strokes")]}) > 3, "the values did change"

    sim = await replay.start(capture)
    try:
        assert len(sim.listening) == 2
        urls = {name.split(" ")[0]: where for name, where in sim.listening.items()}
        e71_port, lan_port = e71.url.rsplit(":", 1)[1], lan.url.rsplit(":", 1)[1]
        config = _config(
            tmp_path / "replay.toml",
            f"e71+tcp://{urls[f'127.0.0.1:{e71_port}']}",
            f"s5lan://{urls[f'127.0.0.1:{lan_port}']}",
        )
        # five of each, as many as the recording has at least: where the recording's requests
        # are used up the replay starts again from the first (the S5-LAN client numbers its
        # requests in UserCode: they are still the recorded ones)
        replayed = _series(await _poll(config, enough=_each_tag_at_least(5)))
        said = [r.getMessage() for r in caplog.records if r.name == "plcstack.wire.replay"]
        assert sim.mismatches == 0, said
    finally:
        await sim.aclose()
    assert set(replayed) == set(first)
    for key, values in first.items():
        again = replayed[key]
        n = min(len(values), len(again))
        assert n >= 5, f"{key}: {len(values)} recorded, {len(again)} replayed"
        assert again[:n] == values[:n], key


async def test_sim_replay_on_the_command_line(tmp_path: Path) -> None:
    """``plcstack sim replay FILE`` announces each server it replays, answers as recorded."""
    e71 = await e71_sim.start()
    e71.memory.write_words("D", 100, [1, 2, 3])
    capture = tmp_path / "read.pcapng"
    try:
        code, out, err = await cli_in_process("read", e71.url, "D100", "3", "--pcap", str(capture))
        assert (code, out) == (0, "D100: 1 2 3\n"), err
    finally:
        await e71.aclose()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "plcstack", "sim", "replay", str(capture),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, env=env,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode()
        assert line.startswith("listening on 127.0.0.1:") and " (TCP), replaying " in line
        assert line.rstrip().endswith(": 1 exchanges")
        where = line.split()[2]
        code, out, err = await cli_in_process("read", f"e71+tcp://{where}", "D100", "3")
        assert (code, out) == (0, "D100: 1 2 3\n"), err
        # a request the capture does not hold: no guess, the connection is closed
        code, out, err = await cli_in_process("read", f"e71+tcp://{where}", "D200", "3")
        assert code == 1 and "D200" in err
    finally:
        proc.send_signal(signal.SIGTERM)
        await asyncio.wait_for(proc.wait(), 15)
    assert proc.stderr is not None
    log = (await proc.stderr.read()).decode()
    assert log.count("is not in the capture") == 1, log  # said once, then counted
    assert "request(s) were not in the capture" in log


async def record_one_read(capture: Path) -> Path:
    """``capture``: a pcapng of one read of D0 from an E71 simulator (which is gone after)."""
    e71 = await e71_sim.start()
    try:
        with PcapngCapture(capture) as file, capturing(file):
            async with plcstack.connect(e71.url) as plc:
                await plc.read("D0", 1)
    finally:
        await e71.aclose()
    return capture


async def test_a_mismatch_is_said_once_per_burst(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    capture = await record_one_read(tmp_path / "one.pcapng")
    sim = await replay.start(capture, repeat=False)
    try:
        url = f"e71+tcp://{sim.url}"
        caplog.set_level(logging.DEBUG, "plcstack.wire.replay")
        for _ in range(3):
            async with plcstack.connect(url, timeout=1) as plc:
                with pytest.raises(PlcError):
                    await plc.read("D1", 1)
        assert sim.mismatches == 3
        warned = [r for r in caplog.records if r.levelname == "WARNING"]
        assert len(warned) == 1 and "differs at byte" in warned[0].getMessage()
    finally:
        await sim.aclose()


async def test_an_as511_line_replays_on_a_pseudo_terminal(tmp_path: Path) -> None:
    ag = await as511_sim.start_pty()
    ag.memory.write_db_words(1, 0, [0x1234, 0x0010])
    capture = tmp_path / "as511.pcapng"
    try:
        with PcapngCapture(capture) as file, capturing(file):
            async with plcstack.connect(ag.url) as pg:
                assert await pg.read("DB1.DW0", 2) == [0x1234, 0x0010]
    finally:
        await ag.aclose()
    sim = await replay.start(capture)
    try:
        (path,) = sim.listening.values()
        assert path.startswith("/dev/")
        async with plcstack.connect(f"as511://{path}") as pg:
            assert await pg.read("DB1.DW0", 2) == [0x1234, 0x0010]
        assert sim.mismatches == 0
    finally:
        await sim.aclose()


async def test_port_serves_the_one_server_and_refuses_a_choice_it_cannot_make(
    tmp_path: Path,
) -> None:
    e71 = await e71_sim.start()
    lan = await s5lan_sim.start()
    capture = tmp_path / "two.pcapng"
    try:
        with PcapngCapture(capture) as file, capturing(file):
            async with plcstack.connect(e71.url) as plc:
                await plc.read("D0", 1)
            async with plcstack.connect(lan.url) as plc:
                await plc.read("DB1.DW0", 1)
    finally:
        await e71.aclose()
        await lan.aclose()
    with pytest.raises(ValueError, match="--port serves one server; the capture has 2"):
        await replay.start(capture, port=0)
    sim = await replay.start(capture, port=0, servers=[e71.url.removeprefix("e71+tcp://")])
    try:
        assert list(sim.listening) == [f"{e71.url.removeprefix('e71+tcp://')} (TCP)"]
    finally:
        await sim.aclose()
