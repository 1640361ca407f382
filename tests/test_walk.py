"""ARCHITECTURE.md's request and north paths are generated (``plcstack.bench.walk``): current.

The figures list every plcstack function one polled E71 read enters and one scan's sample
through the north side; a change to either path that is not in the figures fails here, with the
command that regenerates them.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from plcstack.bench.walk import Walk, replace_figures

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "ARCHITECTURE.md"


def test_the_figures_in_architecture_md_are_current(tmp_path: Path) -> None:
    copy = tmp_path / "ARCHITECTURE.md"
    shutil.copy(DOC, copy)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-m", "plcstack.bench.walk", "--write", str(copy)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=60, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert copy.read_text(encoding="utf-8") == DOC.read_text(encoding="utf-8"), (
        "the paths changed: python -m plcstack.bench.walk --write ARCHITECTURE.md"
    )


def test_the_request_walk_is_one_scan_through_the_exchange_driver() -> None:
    text = DOC.read_text(encoding="utf-8")
    block = text.split("<!-- walk:request:begin -->")[1].split("<!-- walk:request:end -->")[0]
    names = [line.split("  x")[0] for line in block.splitlines() if ".py " in line]
    # one scan: due, sent, answered, queued, next scan on the ticker; no task, no coroutine
    assert names[:2] == ["poll/ticker.py Ticker._fire", "poll/scanner.py Scanner._fire"]
    assert "clients/exchange.py Exchange.start" in names
    assert "clients/exchange.py Exchange.chunk_received" in names
    assert names[-2:] == ["poll/ticker.py Ticker.call_at", "poll/ticker.py Ticker._arm"]


def test_replacing_needs_the_markers() -> None:
    walk = Walk(set())
    with pytest.raises(ValueError, match="walk:request"):
        replace_figures("no markers here", {"request": "x"})
    text = "<!-- walk:request:begin -->\nold\n<!-- walk:request:end -->"
    assert replace_figures(text, {"request": "new"}) == (
        "<!-- walk:request:begin -->\nnew\n<!-- walk:request:end -->"
    )
    assert walk.lines() == [] and walk.files() == []


def test_a_walk_records_only_under_its_roots() -> None:
    from plcstack.poll.scanner import GroupState, advance
    from plcstack.poll.stats import PlcStats

    stats = PlcStats()
    group = GroupState("g", 1.0, (), None, next_due=0.0)  # type: ignore[arg-type]  # no plan needed

    def root() -> None:
        advance(stats, group, 0.5)

    walk = Walk({root.__code__})
    walk.arm()
    try:
        advance(stats, group, 0.5)  # not under a root: not recorded
        root()
        root()
    finally:
        walk.disarm()
    # the root itself is outside the package: not named; what it called is, with its calls
    assert walk.lines() == ["poll/scanner.py advance  x2"] and walk.depth == 0
    assert walk.files() == ["poll/scanner.py"]
