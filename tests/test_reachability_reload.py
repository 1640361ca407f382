"""A PLC a reload removed stays said offline: the scans of its last requests, delivered after
the removal (a request in flight ends and is delivered), decide nothing about it."""

from __future__ import annotations

import json
import time

from plcstack.errors import PlcTimeout
from plcstack.north.layout import JsonLayout, Reachability
from plcstack.poll.samples import Quality, Scan, make_sample


def _scan(plc: str, good: bool = True) -> Scan:
    now = time.time()
    if good:
        sample = make_sample(plc, "x", 1, Quality.GOOD, now, now, None)
    else:
        sample = make_sample(plc, "x", None, Quality.BAD, now, now, "timeout", PlcTimeout)
    return Scan(plc, "default", now, now, (sample,))


def test_a_removed_plc_is_decided_by_no_late_scan_until_it_is_added_again() -> None:
    reach = Reachability({"a": {"default"}, "b": {"default"}})
    assert reach.update(_scan("b")) is True
    reach.reconfigure({"a": {"default"}})
    assert reach.get("b") is None
    assert reach.update(_scan("b")) is None  # its last request, delivered after the removal
    assert reach.update(_scan("b", good=False)) is None
    assert reach.get("b") is None
    reach.reconfigure({"a": {"default"}, "b": {"default"}})  # added again: judged again
    assert reach.update(_scan("b")) is True


def test_the_json_status_of_a_removed_plc_is_not_said_online_again_by_a_late_scan() -> None:
    layout = JsonLayout("plant", "gw", groups={"a": {"default"}, "b": {"default"}}, plcs=["a", "b"])
    said = [p for p in layout.messages([_scan("b")]) if p[0] == "plant/b/status"]
    assert [json.loads(p[1])["status"] for p in said] == ["online"]
    layout.reachability.reconfigure({"a": {"default"}})  # what a reload removing b does
    late = layout.messages([_scan("b")])
    assert [p for p in late if p[0].endswith("/status")] == []
