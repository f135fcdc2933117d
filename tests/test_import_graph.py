"""No import cycle in the package (issue #43).

``lint-imports`` (``make test``) checks the ``acyclic_siblings`` contract in
pyproject.toml: no cycle between the modules of any package, nor between packages. This
test checks the same at the level of single modules, package ``__init__`` modules
included (a package importing a submodule that imports the package back is a cycle the
contract, which merges a package with its submodules, does not see).

Every import counts: module level, inside functions, and under ``TYPE_CHECKING`` (a
type-only import does not run, but it is still a dependency in the design: one side of
it has to be below the other). Only imports by name are seen; the lazy registries
(``offline_adp.__init__``, ``offline_adp.envs``) import by string on first use.
"""

from __future__ import annotations

import grimp


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm,
    iterative), each sorted, in a stable order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return sorted(out)


def test_the_cycle_finder_finds_cycles():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e", "d"}, "f": {"g"}, "g": {"f"}}
    assert _cycles(edges) == [["a", "b", "c"], ["f", "g"]]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_no_import_cycle_between_modules():
    graph = grimp.build_graph("offline_adp", include_external_packages=False, cache_dir=None)
    edges = {m: set(graph.find_modules_directly_imported_by(m)) - {m} for m in graph.modules}
    assert len(edges) > 100  # the whole package was read
    found = _cycles(edges)
    detail = [
        f"{' <-> '.join(c)}: " + "; ".join(
            f"{a} -> {b} (line {graph.get_import_details(importer=a, imported=b)[0]['line_number']})"
            for a in c for b in sorted(edges[a] & set(c)))
        for c in found
    ]
    assert not found, "import cycles:\n" + "\n".join(detail)
