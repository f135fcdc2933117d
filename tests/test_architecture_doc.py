"""``docs/architecture.md`` cannot drift silently from the code (issue #43).

- every module of the package is listed in the document by its path, and every path the
  document names (``offline_adp/...``, ``tests/...``, ``docs/...``) exists;
- every dotted name ``offline_adp.a.b[.c]`` resolves to a module, or to a name defined in one;
- every reference written ``offline_adp/path.py: name, Class.member`` names definitions of
  that file (a function, class, assignment or import at its top level, or a member of a class);
- the layers block lists the import-linter contract's layers (``pyproject.toml``), in order;
- the import picture is the one grimp computes from the code now;
- no line is over 100 characters.

``python tests/test_architecture_doc.py`` prints the import picture, to paste into the
document between its ``imports`` markers after an import between packages changes.
"""

from __future__ import annotations

import ast
import re
import textwrap
import tomllib
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "architecture.md"
PACKAGE = ROOT / "offline_adp"
WIDTH = 100


def _doc() -> str:
    return DOC.read_text(encoding="utf-8")


def _block(name: str) -> list[str]:
    """The lines between ``<!-- name:start -->`` and ``<!-- name:end -->``, code fences dropped."""
    m = re.search(rf"<!-- {name}:start -->\n(.*?)<!-- {name}:end -->", _doc(), re.S)
    assert m, f"docs/architecture.md has no {name}:start / {name}:end markers"
    return [ln for ln in m.group(1).splitlines() if not ln.startswith("```")]


def _modules() -> list[str]:
    return sorted(p.relative_to(ROOT).as_posix() for p in PACKAGE.rglob("*.py"))


def _contract_layers() -> list[str]:
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    layered = [c for c in cfg["tool"]["importlinter"]["contracts"] if c["type"] == "layers"]
    assert len(layered) == 1
    return [" | ".join(p.strip().removeprefix("offline_adp.") for p in layer.split("|"))
            for layer in layered[0]["layers"]]


# ------------------------------------------------------------------ names defined in a module
@cache
def _definitions(path: Path) -> dict[str, set[str]]:
    """``{top-level name: its members}``: functions, classes (with their methods and class
    attributes), assignments and imports at the top level of ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out: dict[str, set[str]] = {}

    def targets(node: ast.AST) -> list[str]:
        if isinstance(node, ast.Assign):
            return [n.id for t in node.targets for n in ast.walk(t) if isinstance(n, ast.Name)]
        if isinstance(node, ast.AnnAssign | ast.AugAssign) and isinstance(node.target, ast.Name):
            return [node.target.id]
        return []

    def walk(body: list[ast.stmt]) -> None:
        for node in body:
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                out.setdefault(node.name, set())
            elif isinstance(node, ast.ClassDef):
                members = out.setdefault(node.name, set())
                for child in node.body:
                    if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                        members.add(child.name)
                    members.update(targets(child))
            elif isinstance(node, ast.Import | ast.ImportFrom):
                for alias in node.names:
                    out.setdefault((alias.asname or alias.name).split(".")[0], set())
            elif isinstance(node, ast.If | ast.Try):  # TYPE_CHECKING blocks, optional imports
                walk(node.body)
                walk(getattr(node, "orelse", []))
            else:
                for name in targets(node):
                    out.setdefault(name, set())

    walk(tree.body)
    return out


def _defined(path: Path, dotted: str) -> bool:
    """Whether ``name`` or ``Class.member`` is defined in the module at ``path``."""
    head, _, member = dotted.partition(".")
    defs = _definitions(path)
    if head not in defs:
        return False
    return not member or member.split(".")[0] in defs[head]


def _module_file(parts: list[str]) -> Path | None:
    base = ROOT.joinpath(*parts)
    for p in (base.with_suffix(".py"), base / "__init__.py"):
        if p.is_file():
            return p
    return None


# ------------------------------------------------------------------ the tests
def test_every_module_of_the_package_is_listed():
    doc = _doc()
    modules = _modules()
    assert len(modules) > 100  # the whole package was read
    missing = [m for m in modules if f"`{m}`" not in doc]
    assert not missing, "modules missing from docs/architecture.md: " + ", ".join(missing)


def test_every_path_the_document_names_exists():
    named = set(re.findall(r"\b((?:offline_adp|tests|docs|benchmarks|pipelines)/[\w./-]*[\w/])", _doc()))
    assert len(named) > 100
    gone = sorted(p for p in named if not (ROOT / p).exists())
    assert not gone, "paths named in docs/architecture.md that do not exist: " + ", ".join(gone)


def test_every_dotted_name_resolves():
    names = set(re.findall(r"\boffline_adp(?:\.\w+)+", _doc()))
    assert names
    bad = []
    for name in sorted(names):
        parts = name.split(".")
        for k in range(len(parts), 0, -1):  # the longest prefix that is a module
            path = _module_file(parts[:k])
            if path is not None:
                rest = ".".join(parts[k:])
                if rest and not _defined(path, rest):
                    bad.append(name)
                break
        else:
            bad.append(name)
    assert not bad, "dotted names in docs/architecture.md that name nothing: " + ", ".join(bad)


def test_every_file_reference_names_its_definitions():
    refs = re.findall(r"`(offline_adp/[\w/]+\.py): ([^`]*)`", _doc())
    assert len(refs) > 30
    bad = []
    for path, names in refs:
        for name in (n.strip() for n in names.split(",")):
            if not re.fullmatch(r"\w+(\.\w+)?", name) or not (ROOT / path).is_file() \
                    or not _defined(ROOT / path, name):
                bad.append(f"{path}: {name}")
    assert not bad, "names in docs/architecture.md not defined where it says: " + "; ".join(bad)


def test_the_layers_are_the_contracts():
    listed = [re.split(r"\s{2,}", ln.strip())[0] for ln in _block("layers") if re.match(r"^ \S", ln)]
    assert listed == _contract_layers()


def import_picture() -> str:
    """Which top-level modules and packages of ``offline_adp`` import which, from grimp's
    graph (every import counts: module level, in functions, under ``TYPE_CHECKING``); one row
    per importer, in the contract's layer order (the package's own ``__init__`` first)."""
    import grimp

    graph = grimp.build_graph("offline_adp", include_external_packages=False, cache_dir=None)

    def top(module: str) -> str:
        parts = module.split(".")
        return "__init__" if len(parts) == 1 else parts[1]

    edges: dict[str, set[str]] = {}
    for m in graph.modules:
        for imported in graph.find_modules_directly_imported_by(m):
            a, b = top(m), top(imported)
            if a != b:
                edges.setdefault(a, set()).add(b)
    order = ["__init__"] + [name for layer in _contract_layers() for name in layer.split(" | ")]
    assert set(edges) <= set(order), f"not in any layer: {sorted(set(edges) - set(order))}"
    rows = []
    for name in order:
        if name in edges:
            rows.extend(textwrap.wrap(" ".join(sorted(edges[name])), WIDTH - 4,
                                      initial_indent=f"{name:<15} -> ", subsequent_indent=" " * 19,
                                      break_on_hyphens=False))
    return "\n".join(rows)


def test_the_import_picture_is_the_codes():
    assert "\n".join(_block("imports")) == import_picture(), (
        "the import picture in docs/architecture.md is out of date: "
        "regenerate it with `python tests/test_architecture_doc.py`")


def test_no_line_is_over_100_characters():
    long = [f"{i}: {len(ln)}" for i, ln in enumerate(_doc().splitlines(), 1) if len(ln) > WIDTH]
    assert not long, "lines over 100 characters (line: length): " + ", ".join(long)


if __name__ == "__main__":
    print(import_picture())
