"""Scans for the tests that feed sinks directly: what the poller hands the north side."""

from __future__ import annotations

from collections.abc import Iterable

from plcstack.poll.samples import Sample, Scan


def scan(*samples: Sample, group: str = "default") -> Scan:
    """One scan of one PLC's group holding ``samples`` (times: the earliest send, the latest
    answer, as the poller sets them)."""
    assert samples and len({s.plc for s in samples}) == 1, "a scan is one PLC's"
    return Scan(
        samples[0].plc,
        group,
        min(s.source_time for s in samples),
        max(s.receive_time for s in samples),
        tuple(samples),
    )


def each(samples: Iterable[Sample], group: str = "default") -> list[Scan]:
    """Each sample as a scan of its own (a group of one tag per scan)."""
    return [scan(s, group=group) for s in samples]
