"""The flight recorder: a PLC's last N frames in memory, as a pcapng file when asked, and
written once per hour at most when the PLC goes offline."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

import plcstack
from plcstack.sim import e71 as e71_sim
from plcstack.transports.tap import Endpoints
from plcstack.wire.packets import parse_ip
from plcstack.wire.pcapng import read_capture
from plcstack.wire.ring import FlightRecorder, FrameRing
from plcstack.wire.streams import conversations, exchanges
from tests.wire_helpers import tshark_fields


async def test_a_ring_keeps_the_last_frames_and_reads_clean_in_tshark(tmp_path: Path) -> None:
    sim = await e71_sim.start()
    ring = FrameRing(8)
    try:
        plc = plcstack.connect(sim.url)
        plc.transport.record_to(ring)
        async with plc:
            for n in range(10):
                await plc.write("D100", [n])
                assert await plc.read("D100", 1) == [n]
    finally:
        await sim.aclose()
    assert len(ring) == 8  # 40 frames went by; the last 8 are kept
    path = tmp_path / "ring.pcapng"
    path.write_bytes(ring.pcapng())
    (conversation,) = conversations(path.read_bytes())
    # the last four exchanges: write 8, read 8, write 9, read 9
    assert [e.request[0] for e in exchanges(conversation)] == [0x03, 0x01, 0x03, 0x01]
    assert exchanges(conversation)[-1].answers == (bytes.fromhex("8100 0900"),)
    # the connection began before the ring: its handshake says so; its close is there
    flagged = tshark_fields(path, ["tcp.analysis.flags"], display_filter="tcp.analysis.flags")
    assert flagged == []
    comments = tshark_fields(path, ["frame.comment"], display_filter="frame.comment")
    assert comments == [
        ["handshake synthesised: the connection was open before this capture began"]
    ]
    flags = [parse_ip(p.data) for p in read_capture(path.read_bytes())]
    assert [p.flags & 0x03 for p in flags if p is not None][-3:] == [0x01, 0x01, 0x00]


def test_a_ring_holds_at_least_one_frame() -> None:
    with pytest.raises(ValueError):
        FrameRing(0)


async def test_an_offline_plc_is_written_at_most_once_per_hour(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    now = [1000.0]
    recorder = FlightRecorder(size=16, directory=tmp_path / "traces", clock=lambda: now[0])
    sim = await e71_sim.start()
    try:
        plc = plcstack.connect(sim.url)
        plc.transport.record_to(recorder.ring("press"))
        async with plc:
            await plc.read("D0", 1)
    finally:
        await sim.aclose()
    assert recorder.offline("oven") is None  # no ring, nothing to write
    first = recorder.offline("press")
    assert first is not None and first.parent == tmp_path / "traces"
    assert first.read_bytes() == recorder.capture("press")
    now[0] += 3599
    assert recorder.offline("press") is None  # flapping: not again within the hour
    now[0] += 2
    with caplog.at_level(logging.WARNING):
        again = recorder.offline("press")
    assert again is not None
    said = [r.getMessage() for r in caplog.records if "went offline" in r.getMessage()]
    assert len(said) == 2  # once per capture written, none for the one skipped
    assert said[-1] == (
        f"press went offline: its last 2 frames are in {again} (open it in Wireshark; "
        "at most one such file per PLC per 60 minutes)"
    )


def test_a_capture_that_cannot_be_written_is_logged_not_raised(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    recorder = FlightRecorder(directory=blocked / "traces")
    ring = recorder.ring("press")
    ring.connection(Endpoints("tcp", ("127.0.0.1", 1), ("127.0.0.1", 2), "local")).sent(b"x")
    assert recorder.offline("press") is None
    assert any("could not be written" in r.getMessage() for r in caplog.records)
