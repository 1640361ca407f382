"""The import rules of ARCHITECTURE.md, checked against every import in ``plcstack/``.

The rules are data: the two tables between the ``layers`` and ``exceptions`` markers of
ARCHITECTURE.md. This test parses them, reads every module's imports with ``ast`` (imports inside
functions and under ``TYPE_CHECKING`` included: they are dependencies too), and fails with the
importer, the line and the rule broken. A module that fits no row fails as well, so a new
package is placed in the picture in the commit that adds it.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "plcstack"
DOC = ROOT / "ARCHITECTURE.md"
#: the root package's own module (``plcstack/__init__.py``); a bare ``plcstack`` row means it
#: alone, never "everything under plcstack"
ROOT_MODULE = "plcstack.__init__"


@dataclass(frozen=True)
class Layer:
    name: str
    modules: tuple[str, ...]
    may_import: frozenset[str]
    forbidden: tuple[str, ...]


def _table(text: str, name: str) -> list[list[str]]:
    match = re.search(rf"<!-- {name}:begin -->(.*?)<!-- {name}:end -->", text, re.S)
    assert match, f"ARCHITECTURE.md has no {name} table"
    rows = [line.strip() for line in match.group(1).strip().splitlines()]
    cells = [[c.strip() for c in row.strip("|").split("|")] for row in rows if row.startswith("|")]
    return cells[2:]  # header and separator


def _names(cell: str) -> tuple[str, ...]:
    return tuple(n.strip() for n in cell.split(",") if n.strip())


def load_rules(text: str) -> tuple[list[Layer], set[tuple[str, str]]]:
    layers = [
        Layer(row[0], _names(row[1]), frozenset(_names(row[2])), _names(row[3]))
        for row in _table(text, "layers")
    ]
    exceptions = {(row[0], row[1]) for row in _table(text, "exceptions")}
    return layers, exceptions


def _matches(module: str, entry: str) -> bool:
    if entry == "plcstack":
        return module == ROOT_MODULE
    return module == entry or module.startswith(entry + ".")


def layer_of(module: str, layers: list[Layer]) -> Layer | None:
    best: tuple[int, Layer] | None = None
    for layer in layers:
        for entry in layer.modules:
            if _matches(module, entry) and (best is None or len(entry) > best[0]):
                best = (len(entry), layer)
    return best[1] if best else None


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts == ["plcstack", "__init__"]:
        return ROOT_MODULE
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package = module_name(path).removesuffix(".__init__")
    if path.name != "__init__.py":
        package = package.rpartition(".")[0]
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                name = ".".join([*base, *([node.module] if node.module else [])])
            else:
                name = node.module or ""
            out.append((node.lineno, name))
    return out


def _target(name: str) -> str:
    return ROOT_MODULE if name == "plcstack" else name


def violations(layers: list[Layer], exceptions: set[tuple[str, str]]) -> list[str]:
    by_name = {layer.name: layer for layer in layers}
    problems: list[str] = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = module_name(path)
        layer = layer_of(module, layers)
        where = path.relative_to(ROOT)
        if layer is None:
            problems.append(f"{where}: {module} is in no layer of ARCHITECTURE.md")
            continue
        allowed = {layer.name} | layer.may_import
        for line, name in imports(path):
            for bad in layer.forbidden:
                if name == bad or name.startswith(bad + "."):
                    problems.append(
                        f"{where}:{line}: {layer.name} must not import {name} (forbidden: {bad})"
                    )
            if not name.startswith("plcstack"):
                continue
            target = layer_of(_target(name), layers)
            if target is None:
                problems.append(f"{where}:{line}: imports {name}, which is in no layer")
            elif target.name not in allowed and not any(
                _matches(module, imp) and _matches(_target(name), dep) for imp, dep in exceptions
            ):
                problems.append(
                    f"{where}:{line}: {layer.name} may not import {target.name} ({name}); "
                    f"allowed: {', '.join(sorted(allowed))}"
                )
    for layer in layers:
        unknown = layer.may_import - by_name.keys()
        assert not unknown, f"layer {layer.name} names unknown layers {unknown}"
    return problems


RULES = load_rules(DOC.read_text(encoding="utf-8"))


def test_every_import_follows_the_rules_of_architecture_md() -> None:
    problems = violations(*RULES)
    assert not problems, "\n".join(problems)


def test_every_listed_layer_exists_and_the_codecs_stay_sans_io() -> None:
    layers, _ = RULES
    names = [layer.name for layer in layers]
    assert names[:3] == ["foundation", "codecs", "transports"]
    codecs = next(layer for layer in layers if layer.name == "codecs")
    assert codecs.may_import == {"foundation"}
    assert {"asyncio", "socket", "time"} <= set(codecs.forbidden)


# -- the checker itself must be able to fail ---------------------------------------------------

SAMPLE = """
<!-- layers:begin -->
| layer | modules | may import | forbidden |
|---|---|---|---|
| low | plcstack.errors | | |
| codecs | plcstack.codecs | low | asyncio |
| clients | plcstack.clients | low, codecs | |
| tools | plcstack | low, codecs, clients | |
<!-- layers:end -->
<!-- exceptions:begin -->
| importer | imported | why |
|---|---|---|
| plcstack.codecs.odd | plcstack.clients.base | a test |
<!-- exceptions:end -->
"""


@pytest.mark.parametrize(
    ("module", "imported", "allowed"),
    [
        ("plcstack.clients.e71", "plcstack.codecs.e71", True),
        ("plcstack.codecs.e71", "plcstack.clients.base", False),
        ("plcstack.codecs.odd", "plcstack.clients.base", True),  # the listed exception
        ("plcstack.codecs.e71", "asyncio", False),
        ("plcstack.__init__", "plcstack.clients", True),
        ("plcstack.clients.e71", "plcstack", False),  # the root package is the tools layer
    ],
)
def test_rules_decide_as_written(module: str, imported: str, allowed: bool) -> None:
    layers, exceptions = load_rules(SAMPLE)
    layer = layer_of(module, layers)
    assert layer is not None
    target_name = _target(imported)
    if not imported.startswith("plcstack"):
        assert (imported not in layer.forbidden) is allowed
        return
    target = layer_of(target_name, layers)
    assert target is not None
    ok = target.name in {layer.name} | layer.may_import or any(
        _matches(module, imp) and _matches(target_name, dep) for imp, dep in exceptions
    )
    assert ok is allowed


def test_unknown_modules_fall_in_no_layer() -> None:
    layers, _ = load_rules(SAMPLE)
    assert layer_of("plcstack.newthing", layers) is None
    assert layer_of("plcstack.codecs.new", layers) is not None
