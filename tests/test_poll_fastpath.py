"""Scripted replies and failures through the poller: the samples and counters they must give.

A merged request of two tags and a tag that is its request's whole reply each play one scripted
sequence (good replies, a timeout, a client bug, a lost connection, a refused merged request, a
short reply); what comes out is checked against the script, sample by sample.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import astuple

import pytest

from plcstack import values as vt
from plcstack.clients.base import Client
from plcstack.errors import ConnectionLost, PlcErrorResponse, PlcTimeout
from plcstack.poll.config import PlcConfig, PollConfig, TagConfig
from plcstack.poll.engine import Poller
from plcstack.poll.samples import Quality, Sample
from tests.poll_fakes import FakeClient

Outcome = list[int] | Callable[[], Exception]

#: one entry per read call: the words read, or a factory of the exception the read raises
SCRIPT: list[Outcome] = [
    [1, 2],
    lambda: PlcTimeout("no answer within 0.5 s"),
    [3, 4],
    lambda: KeyError("client bug"),
    lambda: ConnectionLost("connection reset by peer"),
    [5, 6],
    # the merged request is refused: from the next scan on each tag is read on its own
    lambda: PlcErrorResponse(0x57, "points beyond the device range"),
    [7],
    [8],
]
#: samples the script yields: 7 scans of the merged request, then one of two single reads
EXPECTED_SAMPLES = 16


TWO_TAGS = (
    TagConfig("a", "D0", vt.RAW, 1, "default"),
    TagConfig("b", "D1", vt.RAW, 1, "default"),
)


async def _run(
    *,
    tags: tuple[TagConfig, ...] = TWO_TAGS,
    script_of: list[Outcome] = SCRIPT,
    expected: int = EXPECTED_SAMPLES,
) -> tuple[list[tuple[object, ...]], dict[str, int], int]:
    fake = FakeClient("fake://p")
    script = list(script_of)
    block = asyncio.Event()  # never set: after the script every read waits, counters freeze
    waiting = asyncio.Event()  # set once a read is waiting on ``block``

    async def scripted(address: str, count: int = 1) -> list[int] | list[bool]:
        if not script:
            waiting.set()
            await block.wait()
        outcome = script.pop(0)
        await asyncio.sleep(0)
        if callable(outcome):
            raise outcome()
        return list(outcome)

    fake.read = scripted  # type: ignore[method-assign]

    def factory(plc: PlcConfig) -> Client:
        return fake

    config = PollConfig((PlcConfig("p", "e71+tcp://127.0.0.1:1", tags),), {"default": 0.001})
    poller = Poller(config, client_factory=factory)
    samples: list[Sample] = []
    async with asyncio.timeout(10):
        async with poller:
            async for sample in poller:
                samples.append(sample)
                if len(samples) == expected:
                    break
            await waiting.wait()  # the scan after the script has begun, and stays open
            st = poller.stats["p"]
            counters = {
                "requests": st.requests,
                "errors": st.errors,
                "scans": st.scans,
                "samples": st.samples,
                "bad_samples": st.bad_samples,
                "latencies": len(st.latencies),
            }
            requests = len(poller.plan("p", "default").requests)
    for s in samples:
        assert s.source_time <= s.receive_time
    # times differ from run to run; everything else must not
    return [(*astuple(s)[:4], s.error) for s in samples], counters, requests


async def test_script_gives_the_expected_samples() -> None:
    samples, counters, requests = await _run()
    values = [(tag, value) for _, tag, value, quality, _ in samples if quality is Quality.GOOD]
    assert [value for _, value in values] == [1, 2, 3, 4, 5, 6, 7, 8]
    assert [tag for tag, _ in values] == ["a", "b"] * 4
    errors = [str(error) for *_, error in samples if error is not None]
    assert len(errors) == 8 and all(e.startswith("p: read D0 x2: ") for e in errors)
    assert counters == {
        "requests": 9,
        "errors": 4,
        "scans": 9,
        "samples": 16,
        "bad_samples": 8,
        "latencies": 5,
    }
    assert requests == 2


#: one tag that is the whole reply of its request: the path that hands the reply out as the
#: sample's value (``ScanPlan.whole_reply_tag``); a short reply and failures in between
WHOLE_SCRIPT: list[Outcome] = [
    [1, 2, 3],
    lambda: PlcTimeout("no answer within 0.5 s"),
    [4, 5, 6],
    [7, 8],
    lambda: KeyError("client bug"),
    [9, 10, 11],
]
WHOLE_TAG = (TagConfig("w", "D0", vt.RAW, 3, "default"),)


async def test_whole_reply_samples_follow_the_script() -> None:
    samples, counters, _ = await _run(tags=WHOLE_TAG, script_of=WHOLE_SCRIPT, expected=6)
    assert [value for _, _, value, _, _ in samples] == [
        [1, 2, 3],
        None,
        [4, 5, 6],
        None,
        None,
        [9, 10, 11],
    ]
    assert "reply has 2 points, 3 were requested" in str(samples[3][4])
    assert counters["samples"] == 6 and counters["bad_samples"] == 3


@pytest.mark.parametrize(
    ("tags", "whole"),
    [
        (WHOLE_TAG, "w"),
        ((TagConfig("w", "D0", vt.RAW, 1, "default"),), None),  # a scalar, not a list
        ((TagConfig("w", "D0", vt.INT16, 3, "default"),), None),  # decoded, not raw
        (TWO_TAGS, None),  # two tags share the reply
    ],
)
def test_whole_reply_tag_only_for_one_unscaled_raw_list(
    tags: tuple[TagConfig, ...], whole: str | None
) -> None:
    config = PollConfig((PlcConfig("p", "e71+tcp://127.0.0.1:1", tags),), {"default": 1.0})
    poller = Poller(config, client_factory=lambda plc: FakeClient("fake://p"))
    assert poller.plan("p", "default").whole_reply_tag() == whole
