"""Helpers shared by the fuzz tests."""

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
