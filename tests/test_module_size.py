"""Modules and functions a reader can hold (issue #43, "a house for evaluation").

No module of the package is over :data:`MAX_MODULE_LINES` lines, except those in
:data:`LONG_MODULES`; no function of ``offline_adp/evaluation/`` (``off_policy`` and every
stage it calls, the FQE interval code included) is over :data:`MAX_FUNCTION_LINES` lines,
from its first decorator (or ``def``) to its last line, docstring included: one screen.
Functions are found by walking each file's syntax tree, methods and nested functions
included, and reported by file, line, qualified name and length.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "offline_adp"
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 60
#: Modules allowed over MAX_MODULE_LINES, and only these.
LONG_MODULES: set[str] = set()


def _relative(path: Path) -> str:
    return path.relative_to(PACKAGE.parent).as_posix()


def _line_count(path: Path) -> int:
    return len(path.read_text(encoding="utf-8").splitlines())


def _functions(path: Path) -> Iterator[tuple[str, int, int]]:
    """``(qualified name, first line, length in lines)`` of every function and method in ``path``."""

    def walk(node: ast.AST, prefix: str) -> Iterator[tuple[str, int, int]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                first = min([child.lineno] + [d.lineno for d in child.decorator_list])
                yield f"{prefix}{child.name}", first, child.end_lineno - first + 1
                yield from walk(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                yield from walk(child, f"{prefix}{child.name}.")
            else:
                yield from walk(child, prefix)

    yield from walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path)), "")


def test_no_module_is_over_500_lines():
    modules = sorted(PACKAGE.rglob("*.py"))
    assert len(modules) > 100  # the whole package was read
    over = {_relative(p): n for p in modules if (n := _line_count(p)) > MAX_MODULE_LINES}
    unexpected = {p: n for p, n in over.items() if p not in LONG_MODULES}
    assert not unexpected, (f"modules over {MAX_MODULE_LINES} lines (split them along a seam): "
                            + ", ".join(f"{p} ({n} lines)" for p, n in sorted(unexpected.items())))


def test_no_evaluation_function_is_over_60_lines():
    found = [(_relative(p), name, line, n) for p in sorted((PACKAGE / "evaluation").rglob("*.py"))
             for name, line, n in _functions(p)]
    names = {name for _, name, _, _ in found}
    assert {"off_policy", "fqe_with_interval", "evaluate_run", "evaluation_metrics", "verdict_line"} <= names
    long = [f"{path}:{line} {name} ({n} lines)" for path, name, line, n in found if n > MAX_FUNCTION_LINES]
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines (extract named stages): " + "; ".join(long)


def test_the_function_walk_sees_methods_nested_functions_and_decorators(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("@dec\n@dec2\ndef f():\n    def g():\n        pass\n    return g\n\n\n"
                   "class C:\n    async def h(self):\n        pass\n")
    assert sorted(_functions(src)) == [("C.h", 10, 2), ("f", 1, 6), ("f.g", 4, 2)]
