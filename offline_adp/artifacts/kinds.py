"""The registries of savable kinds (Q-functions, policies) behind :func:`register_q_kind`
and :func:`register_policy_kind` (see :mod:`offline_adp.artifacts`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from offline_adp.errors import ArtifactError


class _Kinds:
    """A registry of savable kinds (Q-functions, policies): ``kind`` in the JSON names the
    reader; the writer is found by the object's class (its MRO), never by an isinstance chain."""

    def __init__(self, what: str, load: Any = None) -> None:
        self.what, self.load = what, load  # load(): registers the package's kinds on first use
        self.writers: dict[type, tuple[str, Any]] = {}
        self.readers: dict[str, Any] = {}

    def register(self, kind: str, cls: type, write: Any, read: Any) -> None:
        """Make objects of class ``cls`` savable as ``kind``: ``write(obj, arrays, key) ->
        dict`` (JSON fields besides ``kind``) and ``read(spec, arrays, where) -> object``
        (checking every field before use; ``ArtifactError`` naming ``where``)."""
        self.writers[cls] = (kind, write)
        self.readers[kind] = read

    def _ready(self) -> None:
        if self.load is not None and not self.readers:
            self.load()

    def export(self, obj: Any, arrays: dict[str, np.ndarray], key: str) -> dict[str, Any]:
        self._ready()
        for cls in type(obj).__mro__:
            if cls in self.writers:
                kind, write = self.writers[cls]
                return {"kind": kind, **write(obj, arrays, key)}
        raise ArtifactError(f"cannot save a {type(obj).__name__} {self.what} safely")

    def read(self, spec: Any, arrays: Any, where: str = "<memory>") -> Any:
        self._ready()
        if not isinstance(spec, dict):
            raise ArtifactError(f"{where}: {self.what} entry is not a JSON object")
        read = self.readers.get(spec.get("kind"))  # type: ignore[arg-type]
        if read is None:
            raise ArtifactError(f"{where}: unknown {self.what} kind {spec.get('kind')!r}; known: "
                                f"{sorted(self.readers)}")
        return read(spec, arrays, where)
