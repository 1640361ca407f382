"""The documentation stays true and self-contained.

- No page points at files a user of the package does not have (the project's design notes, the
  protocol specs it was written from) and every relative link resolves.
- Each protocol page's quickstart runs: its ``plcstack sim`` line is started (on a free port
  instead of the documented default), then every ``plcstack read|write|info|rab-read`` line runs
  against it; a trailing comment that shows output must match, ``exit N`` must be the exit code.
"""

from __future__ import annotations

import asyncio
import re
import shlex
from pathlib import Path

import pytest

from plcstack.cli import build_parser
from plcstack.errors import AddressError, PlcError

DOCS = Path(__file__).resolve().parents[1] / "docs"
PAGES = sorted(DOCS.glob("*.md"))
QUICKSTARTS = ["e71.md", "s5lan.md", "as511.md", "fetchwrite.md"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_pages_are_self_contained(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    for bad in ("../shared", "DESIGN.md", "specs/", "[R]", "§", "tests/"):
        assert bad not in text, f"{page.name} mentions {bad!r}"
    # a section number of the specifications the code was written from ("(A.7)", "C.6.4"):
    # a reader of the page has no such document to look it up in
    assert not re.search(r"\b[A-F]\.\d+(\.\d+)*\b", text), f"{page.name}: a spec section"
    for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", text):
        assert (page.parent / target).exists(), f"{page.name}: broken link {target}"


def _quickstart(page: str) -> list[str]:
    text = (DOCS / page).read_text(encoding="utf-8")
    section = text.split("## Quickstart", 1)[1]
    block = section.split("```sh", 1)[1].split("```", 1)[0]
    return [line.strip() for line in block.splitlines() if line.strip()]


async def _run(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    try:
        code: int = await args.func(args)
    except AddressError:
        return 2
    except PlcError:
        return 1
    return code


@pytest.mark.parametrize("page", QUICKSTARTS)
async def test_quickstart_runs(page: str, capsys: pytest.CaptureFixture[str]) -> None:
    lines = _quickstart(page)
    sim_line = next(line for line in lines if line.startswith("plcstack sim "))
    sim_argv = shlex.split(sim_line.split("&", 1)[0])[1:]
    default = build_parser().parse_args(sim_argv)
    sim = asyncio.create_task(_run([*sim_argv, "--port", "0"]))
    try:
        for _ in range(200):
            if "listening on" in (out := capsys.readouterr().out):
                break
            await asyncio.sleep(0.02)
        where = out.split("listening on ", 1)[1].split()[0]
        for line in lines:
            command, _, comment = line.partition("#")
            argv = shlex.split(command)
            if argv[:2] == ["plcstack", "sim"] or argv[1] not in (
                "read",
                "write",
                "info",
                "rab-read",
            ):
                continue
            argv = [a.replace(f"127.0.0.1:{default.port}", where) for a in argv[1:]]
            code = await _run(argv)
            shown = capsys.readouterr().out.strip()
            comment = comment.strip()
            expected_code = int(m.group(1)) if (m := re.match(r"exit (\d)", comment)) else 0
            assert code == expected_code, f"{page}: {line}"
            expected_out = comment.split(" (", 1)[0]
            if argv[0] in ("read", "write", "rab-read") and not comment.startswith("exit"):
                # a newcomer sees what each command prints before typing it
                assert comment, f"{page}: {line}: shown without its output"
                assert shown == expected_out, f"{page}: {line}"
    finally:
        sim.cancel()
        await asyncio.gather(sim, return_exceptions=True)
