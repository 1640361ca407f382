"""The documentation reaches a wheel user and speaks of the product only.

- No page, README, ARCHITECTURE.md, docstring, comment or help text speaks of how the project was
  made (issue numbers, closing notes, the issue's wording) or points at paths outside the
  repository: a user has none of those.
- docs/README.md indexes every page.
- ``plcstack docs`` lists every page and prints one; a misspelt page gets a suggestion. That the
  wheel carries the pages (setup.py's build hook) is checked by .ci/dist-check on an installed
  wheel.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from plcstack.cli import _all_parsers, build_parser, main
from plcstack.cli.docs import doc_pages

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

#: words of the making, not of the product (the same patterns the project's review hook greps)
MAKING = re.compile(
    r"issue ?#?[0-9]+|closing note|notes/issue|the issue (asks|says|wants|forbids)|/work/"
    r"|source distribution",
    re.IGNORECASE,
)


def _texts() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "ARCHITECTURE.md", *sorted(DOCS.glob("*.md"))]
    files += sorted((ROOT / "plcstack").rglob("*.py"))
    files += sorted((ROOT / "plcstack").rglob("*.toml"))
    files += sorted((ROOT / "examples").glob("*")) if (ROOT / "examples").is_dir() else []
    return [f for f in files if f.is_file()]


def test_no_text_speaks_of_its_making() -> None:
    found = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in _texts()
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if MAKING.search(line)
    ]
    assert found == []


def test_no_help_text_speaks_of_its_making() -> None:
    helps = [parser.format_help() for parser in _all_parsers(build_parser())]
    assert [h for h in helps if MAKING.search(h)] == []


def test_the_pattern_finds_what_it_is_for() -> None:
    for line in ("see the closing note of issue 17", "`/work/coord/notes/x.md`", "(issue #15)"):
        assert MAKING.search(line), line


def test_the_index_lists_every_page() -> None:
    index = (DOCS / "README.md").read_text(encoding="utf-8")
    linked = set(re.findall(r"\]\(([\w.-]+\.md)\)", index))
    pages = {p.name for p in DOCS.glob("*.md")} - {"README.md"}
    assert pages - linked == set()


def test_plcstack_docs_lists_and_prints_the_pages(capsys: pytest.CaptureFixture[str]) -> None:
    assert set(doc_pages()) == {p.stem for p in DOCS.glob("*.md")}
    assert main(["docs"]) == 0
    listing = capsys.readouterr().out
    for page in DOCS.glob("*.md"):
        assert re.search(rf"^{re.escape(page.stem)}\s", listing, re.MULTILINE), page.name
    assert "Plant data out" in listing  # the titles, not only the names
    assert main(["docs", "north.md"]) == 0
    assert capsys.readouterr().out == (DOCS / "north.md").read_text(encoding="utf-8")
    assert main(["docs", "nort"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("plcstack: error: no page nort (did you mean north?)")


def test_plcstack_docs_lists_the_files_the_pages_use(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["docs"]) == 0
    listing = capsys.readouterr().out
    for path in sorted((DOCS / "tags").iterdir()):
        assert f"tags/{path.name}" in listing
    assert main(["docs", "tags/pres.csv"]) == 2
    assert "no page tags/pres.csv (did you mean tags/press.csv?)" in capsys.readouterr().err
