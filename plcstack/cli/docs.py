"""``plcstack docs [PAGE]``: the documentation pages, from any install.

Without PAGE it lists the pages with their titles; with one it prints that page (Markdown) to
stdout, e.g. ``plcstack docs troubleshooting``. The pages come with the wheel (copied into the
package when it is built); in a source checkout they are read from its ``docs/`` folder.
"""

from __future__ import annotations

import argparse
from importlib import resources
from importlib.abc import Traversable
from pathlib import Path
from typing import Any

from plcstack.cli import UsageError, plain_text
from plcstack.errors import unknown_names


def register(subparsers: Any) -> None:
    docs = subparsers.add_parser(
        "docs",
        help="list the documentation pages, or print one",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    docs.add_argument(
        "page",
        nargs="?",
        default=None,
        help="page to print, e.g. north or north.md (default: list)",
    )
    docs.set_defaults(func=run_docs)


def doc_pages() -> dict[str, Traversable]:
    """Page name (without ``.md``) -> the page, from the wheel or else from the checkout."""
    shipped = resources.files("plcstack") / "docs"
    folder: Traversable = shipped
    if not shipped.is_dir():
        folder = Path(__file__).resolve().parents[2] / "docs"
        if not folder.is_dir():
            return {}
    return {
        entry.name.removesuffix(".md"): entry
        for entry in sorted(folder.iterdir(), key=lambda e: e.name)
        if entry.name.endswith(".md")
    }


def title(page: Traversable) -> str:
    """A page's first heading, without the ``#``."""
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("#"):
            return line.lstrip("#").strip()
    return ""


async def run_docs(args: argparse.Namespace) -> int:
    pages = doc_pages()
    if not pages:
        raise UsageError("no documentation pages in this installation")
    if args.page is None:
        width = max(len(name) for name in pages)
        for name, page in pages.items():
            print(f"{name:<{width}}  {title(page)}")
        print("\nplcstack docs PAGE prints one (Markdown), e.g.: plcstack docs README")
        return 0
    name = args.page.removesuffix(".md")
    if name not in pages:
        raise UsageError(f"no page {unknown_names([name], pages)}; pages: {', '.join(pages)}")
    print(pages[name].read_text(encoding="utf-8"), end="")
    return 0
