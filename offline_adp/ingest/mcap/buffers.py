"""Per-key message buffers of the streaming assembler (one per stream and epoch)."""

from __future__ import annotations

from typing import Any

import numpy as np


class _Buffer:
    """One key's messages in one epoch: appended in file order, sorted by time on demand
    (each stream on its own: never a global sort of the file)."""

    def __init__(self, names: list[str], dtype: Any = np.float64) -> None:
        self.names, self.dtype = names, dtype
        # "#id": the message's place among its topic's decoded messages (to count those set aside)
        self.new: dict[str, list] = {"t": [], "file": [], "lt": [], "#id": [], **{n: [] for n in names}}
        self.arr: dict[str, np.ndarray] = {"t": np.zeros(0, np.int64), "file": np.zeros(0, np.int32),
                                           "lt": np.zeros(0, np.int64), "#id": np.zeros(0, np.int64),
                                           **{n: np.zeros(0, dtype) for n in names}}

    def add(self, t: int, file: int, values: list[Any], log_time: int = 0, msg_id: int = 0) -> None:
        self.new["t"].append(t)
        self.new["file"].append(file)
        self.new["lt"].append(log_time)
        self.new["#id"].append(msg_id)
        for n, v in zip(self.names, values, strict=True):
            self.new[n].append(v)

    def arrays(self) -> dict[str, np.ndarray]:
        if self.new["t"]:
            merged = {k: np.concatenate([self.arr[k], np.asarray(self.new[k],
                                                                 dtype=self.arr[k].dtype)]) for k in self.arr}
            order = np.argsort(merged["t"], kind="stable")
            self.arr = {k: v[order] for k, v in merged.items()}
            self.new = {k: [] for k in self.new}
        return self.arr

    def prune(self, cutoff: int) -> None:
        """Drop messages before ``cutoff`` but keep the last one before it (``previous`` holds it)."""
        a = self.arrays()
        i = max(int(np.searchsorted(a["t"], cutoff, side="left")) - 1, 0)
        if i:
            self.arr = {k: v[i:] for k, v in a.items()}

    def take(self, which: np.ndarray) -> dict[str, np.ndarray]:
        """Remove the messages ``which`` (a mask over :meth:`arrays`) and return them."""
        a = self.arrays()
        self.arr = {k: v[~which] for k, v in a.items()}
        return {k: v[which] for k, v in a.items()}

    def __len__(self) -> int:
        return len(self.arr["t"]) + len(self.new["t"])
