"""Helpers shared by the fuzz and hostile-input tests."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any


def json_paths(obj: Any, prefix: tuple = (), max_items: int = 50) -> Iterator[tuple]:
    """Every key path into a JSON-like value (lists: their first ``max_items`` items)."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from json_paths(v, (*prefix, k), max_items)
    elif isinstance(obj, list):
        for i, v in enumerate(obj[:max_items]):
            yield from json_paths(v, (*prefix, i), max_items)


def edit_json_path(doc: Any, path: tuple, value: Any, delete: bool) -> None:
    """Set ``doc[path] = value`` in place, or delete that key when ``delete`` and its parent is a dict."""
    parent = doc
    for x in path[:-1]:
        parent = parent[x]
    if delete and isinstance(parent, dict):
        del parent[path[-1]]
    else:
        parent[path[-1]] = value


def peak_cli(*args: str, timeout: int = 300) -> tuple[Any, float]:
    """Run the CLI in a child process; returns (the CompletedProcess, the child's own peak
    RSS in MB). The peak is the child's VmHWM: ``ru_maxrss`` is not its own, since Linux
    carries the parent's high-water mark across fork/exec (a large pytest worker counted)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    code = ("import resource, runpy, sys\n"
            f"sys.argv = ['offline-adp', *{list(args)!r}]\n"
            "try:\n    runpy.run_module('offline_adp', run_name='__main__')\n"
            "except SystemExit as e:\n    code = e.code\nelse:\n    code = 0\n"
            "hwm = [ln for ln in open('/proc/self/status') if ln.startswith('VmHWM:')]\n"
            "kb = int(hwm[0].split()[1]) if hwm else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
            "sys.stderr.write('PEAK_KB=%d\\n' % kb)\n"
            "sys.exit(code)\n")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=timeout)
    peak = [ln for ln in r.stderr.splitlines() if ln.startswith("PEAK_KB=")]
    assert peak, r.stderr[-2000:]
    return r, int(peak[-1].split("=")[1]) / 1024


#: Members of a tree ensemble in the compact layout (:meth:`TreeEnsemble.to_arrays`).
COMPACT_MEMBERS = ("roots", "leaf_bits", "feature", "threshold", "value", "value_table", "value_code")


def node_layout(arrays: dict[str, Any]) -> dict[str, Any]:
    """Rewrite, in place, every tree ensemble stored in the compact layout as per-node
    arrays (``left, right, feature, threshold, value, roots``: artifact format 1, which
    the loader still reads), so that crafted edits can target one node's child, feature
    or value. Returns ``arrays``."""
    from offline_adp.trees import TreeEnsemble

    for p in [k[:-len("leaf_bits")] for k in arrays if k.endswith(".leaf_bits")]:
        ens = TreeEnsemble.from_arrays(arrays, p)
        for k in [k for k in arrays if k.startswith(p) and k[len(p):] in COMPACT_MEMBERS]:
            del arrays[k]
        arrays.update(ens.to_arrays(p, layout="nodes"))
    return arrays


def gridworld_runs(root: Any, evaluate: tuple[str, ...] = ("a",), extra: tuple[str, ...] = ()) -> Any:
    """A small gridworld log in ``root/ds`` and two quick FQI fits ``root/a`` and ``root/b``,
    the runs named in ``evaluate`` evaluated from the logs (``extra``: more evaluate flags)."""
    from pathlib import Path

    from offline_adp.cli import main
    from offline_adp.simulate import simulate

    root = Path(root)
    simulate("gridworld", 4, 4, seed=3, horizon=30).save(root / "ds")
    cfg = root / "fqi.toml"
    cfg.write_text("[fqi]\nn_iterations = 3\n[fqi.regressor_params]\nn_estimators = 5\n")
    for name in ("a", "b"):
        assert main(["fit", str((root / "ds").resolve()), "--config", str(cfg), "--out", str(root / name),
                     "--quiet"]) == 0
    for name in evaluate:
        assert main(["evaluate", str(root / name), "--simulator", "none", "--bootstrap", "5", *extra, "--quiet"]) == 0
    return root


def one_line_error(capsys: Any, argv: list[str], *names: str) -> str:
    """Run the CLI on ``argv``: exit 2, no traceback, one ``error:`` line naming every one of
    ``names`` (a file, a key); returns that line."""
    from offline_adp.cli import main

    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [x for x in err.strip().splitlines() if "error:" in x]
    assert len(lines) == 1, err
    for name in names:
        assert name in lines[0], err
    return lines[0]
