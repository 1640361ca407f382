"""``plcstack docs [PAGE]``: the documentation pages, from any install.

Without PAGE it lists the pages with their titles; with one it prints that page (Markdown) to
stdout, e.g. ``plcstack docs troubleshooting``. The files the pages show (the tag lists of the
tags page) are copied out the same way: ``plcstack docs tags/press.csv > press.csv``. The pages
come with the wheel (copied into the package when it is built); in a source checkout they are
read from its ``docs/`` folder.
"""

from __future__ import annotations

import argparse
import sys
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
        help="page to print, e.g. north or north.md, or a file the pages use, e.g. tags/press.csv "
        "(default: list)",
    )
    docs.set_defaults(func=run_docs)


def _folder() -> Traversable | None:
    """The documentation folder: in the wheel, or else in the checkout."""
    shipped = resources.files("plcstack") / "docs"
    if shipped.is_dir():
        return shipped
    folder = Path(__file__).resolve().parents[2] / "docs"
    return folder if folder.is_dir() else None


def doc_pages() -> dict[str, Traversable]:
    """Page name (without ``.md``) -> the page, from the wheel or else from the checkout."""
    folder = _folder()
    if folder is None:
        return {}
    return {
        entry.name.removesuffix(".md"): entry
        for entry in sorted(folder.iterdir(), key=lambda e: e.name)
        if entry.name.endswith(".md")
    }


def doc_files() -> dict[str, Traversable]:
    """``tags/press.csv`` -> the file: what the pages show besides themselves (tag lists to
    import, an image). A wheel has no source tree to find them in; ``plcstack docs FILE``
    copies one out, byte for byte (a GX export is UTF-16 or Shift-JIS, not this terminal's)."""
    folder = _folder()
    files: dict[str, Traversable] = {}
    pending = [("", folder)] if folder is not None else []
    while pending:
        prefix, here = pending.pop()
        for entry in here.iterdir():
            if entry.is_dir():
                pending.append((f"{prefix}{entry.name}/", entry))
            elif not entry.name.endswith(".md"):
                files[prefix + entry.name] = entry
    return dict(sorted(files.items()))


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
        files = doc_files()
        if files:
            print(f"files the pages use: {', '.join(files)}")
            print("plcstack docs FILE > NAME copies one: plcstack docs tags/press.csv > press.csv")
        return 0
    files = doc_files()
    if args.page in files:
        sys.stdout.flush()
        sys.stdout.buffer.write(files[args.page].read_bytes())
        return 0
    name = args.page.removesuffix(".md")
    if name not in pages:
        known = [*pages, *files]
        raise UsageError(
            f"no page {unknown_names([name], known)}; pages: {', '.join(pages)}; "
            f"files: {', '.join(files)}"
        )
    print(pages[name].read_text(encoding="utf-8"), end="")
    return 0
