"""The structure of the package, checked on every run: no import cycle, no oversized module, no
private name taken from another module, no private attribute of another object in the clients
and the poller.

Why these four: a cycle means two modules are halves of one (neither can be read, tested or
replaced alone); a module over 800 lines mixes concerns; a private name imported, or a private
attribute of another object used, is a dependency the owner of that name cannot see, so the
owner's next change breaks a stranger. Like tests/test_architecture.py, the checks read the
source with ``ast``: imports inside functions and under ``TYPE_CHECKING`` count, since they are
dependencies too (a cycle hidden behind ``TYPE_CHECKING`` is still two halves of one module).

Each check is a function over source text that returns its findings, so the tests below can
prove on small samples that it finds what it should.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "plcstack"
#: the most lines a module may have
MAX_LINES = 800
#: packages in which no code may use a private attribute of another object (``x._y`` with ``x``
#: not ``self`` or ``cls``): the request path, where such shortcuts were taken for speed
NO_FOREIGN_PRIVATES = ("plcstack.clients", "plcstack.poll")

#: modules over MAX_LINES that another change is splitting, each with the reason it may wait
OVERSIZED_FOR_NOW: dict[str, str] = {}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def sources() -> dict[str, tuple[Path, str]]:
    """Every module of the package: dotted name -> (path, source text)."""
    return {
        module_name(p): (p, p.read_text(encoding="utf-8")) for p in sorted(PACKAGE.rglob("*.py"))
    }


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def import_edges(modules: Mapping[str, tuple[Path, str]]) -> dict[str, set[str]]:
    """module -> the package's modules it imports. ``from a import b`` imports ``a.b`` when
    that is a module, else ``a``; every import counts, wherever it is written."""
    edges: dict[str, set[str]] = {name: set() for name in modules}
    for name, (path, text) in modules.items():
        package = name if _is_package(path) else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Import):
                edges[name].update(a.name for a in node.names if a.name in modules)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    source = ".".join([*base, *([node.module] if node.module else [])])
                else:
                    source = node.module or ""
                for alias in node.names:
                    if f"{source}.{alias.name}" in modules:
                        edges[name].add(f"{source}.{alias.name}")
                    elif source in modules:
                        edges[name].add(source)
        edges[name].discard(name)
    return edges


def cycles(edges: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return sorted(found)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_imports(text: str) -> list[str]:
    """``from x import _y``: a private name of another module."""
    return [
        f"{node.lineno}: from {node.module or '.'} import {alias.name}"
        for node in ast.walk(ast.parse(text))
        if isinstance(node, ast.ImportFrom)
        for alias in node.names
        if _private(alias.name)
    ]


def foreign_privates(text: str) -> list[str]:
    """``x._y`` where ``x`` is not ``self`` or ``cls``: a private attribute of another object."""
    found = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            owner = node.value
            if isinstance(owner, ast.Name) and owner.id in ("self", "cls"):
                continue
            found.append(f"{node.lineno}: {ast.unparse(node)}")
    return found


# -- the package ---------------------------------------------------------------------------------

MODULES = sources()


def test_no_import_cycle() -> None:
    found = cycles(import_edges(MODULES))
    assert not found, "modules that import each other (directly or around a cycle):\n" + (
        "\n".join(" <-> ".join(c) for c in found)
    )


def test_no_module_over_800_lines() -> None:
    over = {
        str(path.relative_to(ROOT)): len(text.splitlines())
        for path, text in MODULES.values()
        if len(text.splitlines()) > MAX_LINES
    }
    unexpected = {p: n for p, n in over.items() if p not in OVERSIZED_FOR_NOW}
    assert not unexpected, f"modules over {MAX_LINES} lines: {unexpected}"
    done = set(OVERSIZED_FOR_NOW) - set(over)
    assert not done, f"no longer over {MAX_LINES} lines, drop from OVERSIZED_FOR_NOW: {done}"


def test_no_private_name_imported_from_another_module() -> None:
    found = [
        f"{path.relative_to(ROOT)}:{hit}"
        for path, text in MODULES.values()
        for hit in private_imports(text)
    ]
    assert not found, "\n".join(found)


def test_no_private_attribute_of_another_object_in_clients_and_poll() -> None:
    found = [
        f"{path.relative_to(ROOT)}:{hit}"
        for name, (path, text) in MODULES.items()
        if name.startswith(NO_FOREIGN_PRIVATES)
        for hit in foreign_privates(text)
    ]
    assert not found, "\n".join(found)


# -- the checks themselves must be able to fail --------------------------------------------------


def _sample(tmp: Path, files: dict[str, str]) -> dict[str, tuple[Path, str]]:
    out = {}
    for rel, text in files.items():
        path = tmp / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        parts = list(Path(rel).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = (path, text)
    return out


def test_a_cycle_behind_type_checking_or_in_a_function_is_found(tmp_path: Path) -> None:
    modules = _sample(
        tmp_path,
        {
            "pkg/__init__.py": "",
            "pkg/a.py": "from pkg.b import B\n",
            "pkg/b.py": (
                "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.c import C\n"
            ),
            "pkg/c.py": "def f():\n    from . import a\n",
            "pkg/d.py": "from pkg import a\n",
        },
    )
    assert cycles(import_edges(modules)) == [["pkg.a", "pkg.b", "pkg.c"]]


def test_no_cycle_when_the_imports_run_one_way(tmp_path: Path) -> None:
    modules = _sample(
        tmp_path,
        {"pkg/__init__.py": "", "pkg/a.py": "import pkg.b\n", "pkg/b.py": "X = 1\n"},
    )
    assert cycles(import_edges(modules)) == []


@pytest.mark.parametrize(
    ("text", "found"),
    [
        ("from m import _x\n", ["1: from m import _x"]),
        ("from . import _helpers\n", ["1: from . import _helpers"]),
        ("from m import x, __version__\n", []),
    ],
)
def test_private_imports_are_found(text: str, found: list[str]) -> None:
    assert private_imports(text) == found


@pytest.mark.parametrize(
    ("text", "found"),
    [
        ("client._lock.release()\n", ["1: client._lock"]),
        ("self._poller._slots\n", ["1: self._poller._slots"]),
        ("self._lock.release()\ncls._cache\nobj.__class__\n", []),
    ],
)
def test_foreign_private_attributes_are_found(text: str, found: list[str]) -> None:
    assert foreign_privates(text) == found
