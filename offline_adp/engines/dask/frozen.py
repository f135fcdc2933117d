"""The default FQI mode on the cluster: frozen extra-trees structures grown on the
workers, leaf values re-averaged from per-block leaf sums (:class:`DaskFrozenLearner`).

Per structure (a build, a constant-target structure or a restored checkpoint):

- the trees are grown on the workers: each running worker grows a contiguous range of
  the trees (tree ``t`` depends only on ``(seed, t)`` and the rows) from every block's
  joint inputs, fetched worker to worker, and the targets scattered from the client; the
  trees stay there as :class:`~offline_adp.trees.compact.CompactTree` arrays;
- each *segment* (a run of consecutive blocks on one worker: with one worker, all of
  them) looks up the leaves of its training, next-state and start inputs in every tree,
  keeps them on its worker as tree-major int32 positions, and reports which leaves hold
  training rows (packed bits); the client numbers those leaves tree by tree, in node order
  (the compact index of the in-process learner) and sends the numbering back, and every
  segment turns its positions into compact ones and sums its rows' weights per leaf.

Per iteration: the targets are scattered from the client to the segments; the leaf sums
of ``y`` (and once per structure of the weights) are taken segment after segment, each on
its worker continuing the sums of the segments before it in row order (the first one with
:func:`~offline_adp.trees.averaging.leaf_sums`, the in-process kernel), so every leaf's
sum is the in-process one bit for bit; the client divides and broadcasts the leaf values;
each segment takes the mean over trees at its queries
(:func:`~offline_adp.trees.averaging.tree_mean`), gathered in row order. The client holds
the per-transition vectors and one float per leaf, never a (trees, rows) matrix; the
structure itself comes to the client once per structure, for the Q-function the loop
snapshots.
"""

from __future__ import annotations

import contextlib
import dataclasses
import operator
from typing import Any

import numpy as np

from offline_adp.engines.dask.blocks import _Blocks, _count_starts, scheduler_workers
from offline_adp.errors import ClusterError, InvalidArgumentError
from offline_adp.learn import Learner, LearnSpec
from offline_adp.learn.base import fit_model
from offline_adp.learn.frozen import FrozenBuilds
from offline_adp.learn.schedule import FrozenSchedule
from offline_adp.qfunctions import QFunction
from offline_adp.trees import builder as compiled
from offline_adp.trees.averaging import leaf_sums, thread_map, tree_mean
from offline_adp.trees.compact import CompactTree
from offline_adp.trees.ensemble import TreeEnsemble, compiled_per_tree_leaves


# ----------------------------------------------------------------------------- on the workers
def _threads() -> int:
    """The calling worker's thread count (1 outside a worker): builds, lookups and sums
    use it; the numbers do not depend on it."""
    try:
        from distributed import get_worker

        return max(1, int(get_worker().state.nthreads))
    except (ImportError, ValueError, AttributeError):
        return 1


def _grow(native: compiled.TreeParams, trees: range, y: np.ndarray, *X: np.ndarray) -> list[CompactTree]:
    """Trees ``trees`` of the compiled builder on the blocks' joint inputs ``X`` (in row
    order) and targets ``y``, as :class:`CompactTree`."""
    native = dataclasses.replace(native, n_jobs=_threads())
    return compiled.grow_trees(np.concatenate(X), y, None, native, trees, finish=CompactTree.from_grown,
                               record_leaves=False)


def _grow_sklearn(model: Any, y: np.ndarray, *X: np.ndarray) -> list[CompactTree]:
    """The whole forest by scikit-learn (a regressor the compiled builder does not
    implement), its trees as :class:`CompactTree` (the leaves scikit-learn's ``apply`` reaches)."""
    forest = fit_model(model, np.concatenate(X), y, None)
    return [CompactTree(t.children_left, t.children_right, t.feature, t.threshold, t.value.reshape(-1))
            for t in (e.tree_ for e in forest.estimators_)]


def _node_counts(trees: list[Any]) -> list[int]:
    return [int(t.node_count) for t in trees]


def _lookup(blocks: list[dict[str, np.ndarray]], chunks: list[list[Any]], roots: np.ndarray, encoder: Any,
            start: np.ndarray | None, n_nodes: int) -> dict[str, Any]:
    """A segment's leaves in every tree (global node ids, tree-major int32): ``train`` (its
    rows' ``[x_i, f(a_i)]``; a row continuing the previous one reads the next-state
    lookup), ``next`` and ``start`` (every action, action-major over the segment's rows);
    ``used``: the nodes holding a training row (packed bits, for the client)."""
    trees = [t for c in chunks for t in c]
    prepare = compiled_per_tree_leaves(trees, roots)
    X = np.concatenate([b["X"] for b in blocks])
    nxt = np.concatenate([b["next"] for b in blocks])
    starts = np.concatenate([b["start"] for b in blocks]) if start is None else start
    action = np.concatenate([b["action"] for b in blocks])
    follows = np.concatenate([b["follows"] for b in blocks])
    n, m = len(X), len(trees)
    reuse = np.flatnonzero(follows)
    rest = np.flatnonzero(~follows)
    from_next = action[reuse] * n + reuse - 1  # the next-state query of row i - 1 at action a_i
    looks = {"next": prepare(encoder.all_pairs(nxt)), "start": prepare(encoder.all_pairs(starts)),
             "rest": prepare(X[rest])}
    del X
    pos = {"train": np.empty((m, n), np.int32), "next": np.empty((m, len(nxt) * encoder.n_actions), np.int32),
           "start": np.empty((m, len(starts) * encoder.n_actions), np.int32)}

    def one(t: int) -> None:
        nx = looks["next"](t)
        pos["next"][t] = nx
        pos["start"][t] = looks["start"](t)
        pos["train"][t, rest] = looks["rest"](t)
        pos["train"][t, reuse] = nx[from_next]

    thread_map(one, range(m), _threads())
    used = np.zeros(n_nodes, bool)
    used[pos["train"].ravel()] = True
    return {"pos": pos, "used": np.packbits(used), "n": n, "n_actions": encoder.n_actions}


def _used(state: dict[str, Any]) -> np.ndarray:
    return state["used"]


def _compact(state: dict[str, Any], node_map: np.ndarray, bounds: np.ndarray) -> dict[str, Any]:
    """The segment's positions in the compact leaf index (``node_map``: a node's compact
    leaf, ``L`` -- the value 0 -- for a leaf without training rows), remapped in place
    (the lookup's state is released)."""
    pos = state["pos"]
    for p in pos.values():
        for t in range(len(p)):  # one tree's temporary at a time
            p[t] = node_map[p[t]]
    return {"pos": pos, "bounds": bounds, "n": state["n"], "n_actions": state["n_actions"]}


def _sums(state: dict[str, Any], v: np.ndarray | None, carry: np.ndarray | None) -> np.ndarray:
    """``sum of v_i`` per compact leaf over the rows of every segment up to this one, in
    row order: the in-process kernel on the first segment, then each next segment adds
    its rows to the sums so far (``carry``), so every leaf's sum is the in-process one,
    bit for bit, however the rows are split. ``v`` None: the rows' count (the weights)."""
    pos, bounds = state["pos"]["train"], state["bounds"]
    v = np.ones(state["n"]) if v is None else np.ascontiguousarray(v, dtype=np.float64)
    return leaf_sums(pos, bounds, v, _threads(), carry=carry)


def _means(state: dict[str, Any], values: np.ndarray) -> dict[str, np.ndarray]:
    """Q at the segment's queries: the mean over trees of the reached leaves' values."""
    j, A, n = _threads(), state["n_actions"], state["n"]
    p = state["pos"]
    return {"train": tree_mean(values, p["train"], j),
            "next": tree_mean(values, p["next"], j).reshape(A, n).T,
            "start": tree_mean(values, p["start"], j).reshape(A, -1).T}


# ----------------------------------------------------------------------------- on the client
class DaskFrozenLearner(FrozenBuilds, Learner):
    """The frozen-structure LEARN step (:class:`~offline_adp.learn.frozen.FrozenTreesLearner`,
    the default mode of :class:`~offline_adp.algorithms.fqi.FittedQIteration`) over the
    dataset's blocks on a Dask cluster; see the module's text for where each part runs.

    The build decisions (schedule, row fraction, jitter of tied targets, early builds, the
    builder and its seeds) are the in-process learner's own (:class:`FrozenBuilds`); the
    trees are grown from the same rows with the same seeds, so the structure is the
    in-process one for any number of workers, and so are the leaf positions. Every leaf
    sum is taken in row order, segment after segment (consecutive blocks on one worker),
    and each query's mean over trees in tree order: the Q-values, the history and the
    saved model equal the in-process fit's **bit for bit, on one worker or several** (and
    so two runs give the same Q). The price: the leaf sums of an iteration run one segment
    after another (a pass over the segment's (trees, rows) positions each, a few percent
    of an iteration), not in parallel.

    Not on the cluster: ``screen_trees`` (the screen reads every next state's per-tree
    values: refused) and sample weights (the Dask engine has none).
    """

    QUERIES = ("train", "next", "start")

    def __init__(self, client: Any, blocks: _Blocks, regressor: Any, encoder: Any, actions: np.ndarray, seed: int,
                 schedule: FrozenSchedule, *, start_obs: np.ndarray | None = None) -> None:
        super().__init__(LearnSpec(regressor, encoder, None, actions, {}, None, seed))  # type: ignore[arg-type]
        if encoder.per_action:
            raise InvalidArgumentError("the frozen mode with action_encoding='per_action' is not available on the "
                                       "Dask engine; use the joint encoding or the local engine")
        if schedule.screen is not None:
            raise InvalidArgumentError("screen_trees is not available on the Dask engine (the screen reads every "
                                       "next state's per-tree values); leave it unset or use the local engine")
        self._init_builds(schedule)
        self.client, self.blocks, self.start_obs = client, blocks, start_obs
        self.n_features = len(blocks.args[0]) + blocks.args[2].shape[1]
        self.n_start = int(sum(client.gather(blocks.map(_count_starts))))
        self.segments = self._segments()
        self._states: list[Any] = []  # per segment: its compact leaf positions (futures)
        self._trees: list[Any] = []  # the structure's tree chunks (futures), until exported
        self.ensemble: TreeEnsemble | None = None  # the structure on the client (exported on first snapshot)
        self._cache: dict[str, np.ndarray] = {}

    def _segments(self) -> list[tuple[list[int], str, int, int]]:
        """Runs of consecutive blocks on one worker: (block indices, worker, first row, end row)."""
        out: list[tuple[list[int], str, int, int]] = []
        edges = np.r_[0, np.cumsum(self.blocks.lengths)]
        for i, w in enumerate(self.blocks.where):
            if out and out[-1][1] == w:
                out[-1][0].append(i)
                out[-1] = (out[-1][0], w, out[-1][2], int(edges[i + 1]))
            else:
                out.append(([i], w, int(edges[i]), int(edges[i + 1])))
        return out

    # ------------------------------------------------------------------ structures
    def _release(self) -> None:
        for f in [*self._states, *self._trees]:
            with contextlib.suppress(Exception):
                f.release()
        self._states, self._trees, self.ensemble, self._cache = [], [], None, {}

    def _build(self, y: np.ndarray, k: int) -> None:
        self._release()
        if self._start_build(y):  # constant targets: one-leaf trees
            self._adopt_ensemble(self._constant_structure(y, self.n_features))
            return
        plan = self._plan(y, k, len(y), self.n_features)
        client, blocks = self.client, self.blocks
        X = blocks.map(operator.getitem, "X")  # the joint inputs stay on their workers until a builder fetches them
        workers = list(dict.fromkeys(blocks.where))
        if plan.native is not None:  # tree t depends on (seed, t) only: contiguous ranges over the workers
            edges = np.linspace(0, plan.native.n_estimators, len(workers) + 1).astype(int)
            jobs = [(w, range(int(a), int(b))) for w, a, b in zip(workers, edges[:-1], edges[1:], strict=True) if b > a]
            self._trees = [client.submit(_grow, plan.native, r, client.scatter(plan.grow, workers=[w], hash=False), *X,
                                         workers=[w], allow_other_workers=True, pure=False) for w, r in jobs]
        else:  # scikit-learn's forest: one task
            w = workers[0]
            self._trees = [client.submit(_grow_sklearn, plan.model, client.scatter(plan.grow, workers=[w], hash=False),
                                         *X, workers=[w], allow_other_workers=True, pure=False)]
        sizes = [n for c in client.gather([client.submit(_node_counts, t, pure=False) for t in self._trees]) for n in c]
        for f in X:
            f.release()
        self._look_up(sizes)

    def _adopt_ensemble(self, ens: TreeEnsemble) -> None:
        """A structure held as arrays (constant targets, a restored checkpoint): its trees
        to the workers, and the leaves looked up there."""
        ens.check_inputs(np.zeros((1, self.n_features)))  # every feature a split reads is an input
        trees = ens.compiled_trees()
        if trees is None:
            raise InvalidArgumentError("the Dask engine's frozen mode needs numba's compiled tree lookups")
        self._trees = [self.client.scatter(trees, workers=[self.segments[0][1]], hash=False)]
        self._look_up([t.node_count for t in trees])
        self.ensemble = ens

    def _look_up(self, sizes: list[int]) -> None:
        """Every segment's leaves (kept on its worker), the compact leaf index on the client
        (``leaf_ids``, ``_bounds``) and the leaf weights ``_wsum``."""
        client = self.client
        roots = np.r_[0, np.cumsum(sizes, dtype=np.int64)[:-1]]
        n_nodes = int(np.sum(sizes))
        if n_nodes >= 2**31 - 1:
            raise InvalidArgumentError(f"a structure of {n_nodes} nodes does not fit int32 leaf positions")
        extra = self.start_obs if self.n_start == 0 else None  # no start state in the data: the first row
        looked = []
        for j, (idx, w, _, _) in enumerate(self.segments):
            blocks = [self.blocks.futures[i] for i in idx]
            looked.append(client.submit(_lookup, blocks, self._trees, roots, self.encoder, extra if j == 0 else None,
                                        n_nodes, workers=[w], allow_other_workers=True, pure=False))
        used = np.zeros(n_nodes, bool)
        for bits in client.gather([client.submit(_used, s, workers=[w], allow_other_workers=True, pure=False)
                                   for s, (_, w, _, _) in zip(looked, self.segments, strict=True)]):
            used |= np.unpackbits(bits, count=n_nodes).astype(bool)
        self.leaf_ids = np.flatnonzero(used)  # tree by tree, in node order: the in-process compact index
        L = len(self.leaf_ids)
        self._bounds = np.r_[np.searchsorted(self.leaf_ids, roots), L].astype(np.int64)
        node_map = np.full(n_nodes, L, np.int32)
        node_map[self.leaf_ids] = np.arange(L, dtype=np.int32)
        workers = list(dict.fromkeys(w for _, w, _, _ in self.segments))
        m_f = client.scatter(node_map, workers=workers, broadcast=True, hash=False)
        self._states = [client.submit(_compact, s, m_f, self._bounds, workers=[w], allow_other_workers=True,
                                      pure=False) for s, (_, w, _, _) in zip(looked, self.segments, strict=True)]
        del looked  # the lookups' futures: their positions live on in the compact states
        self._wsum = self._leaf_sums(None)
        self._m = len(sizes)

    def _leaf_sums(self, y: np.ndarray | None) -> np.ndarray:
        """``sum of y_i`` (None: of 1) over the training rows in each compact leaf, summed
        segment after segment on their workers (each continues the previous one's sums)."""
        client, carry = self.client, None
        for s, (_, w, lo, hi) in zip(self._states, self.segments, strict=True):
            v = None if y is None else client.scatter(y[lo:hi], workers=[w], hash=False)
            carry = client.submit(_sums, s, v, carry, workers=[w], allow_other_workers=True, pure=False)
        return np.asarray(carry.result(), dtype=np.float64)  # type: ignore[union-attr]

    # ------------------------------------------------------------------ the Learner interface
    def _check_workers(self) -> None:
        """The segments' workers are still there (their leaf positions live nowhere else)."""
        alive = set(scheduler_workers(self.client)) if self._states else set()
        gone = sorted({w for _, w, _, _ in self.segments} - alive) if self._states else []
        if gone:
            raise ClusterError(f"workers {gone} holding the frozen structure's leaf positions are gone")

    def fit(self, y: np.ndarray, k: int) -> None:
        self._check_workers()
        y = np.asarray(y, dtype=np.float64)
        built = self._builds_at(k)
        if built:
            self._build(y, k)
        self._built()
        prev = None if built else getattr(self, "leaf_values", None)
        self._cache = {}
        self.leaf_values = self._settle(y, self._leaf_means(y), prev, k, built)  # leaf means of y_k (learn.settle)
        self._cache = {}

    def _leaf_means(self, y: np.ndarray) -> np.ndarray:
        return self._leaf_sums(y) / self._wsum

    def _next_q(self, values: np.ndarray) -> np.ndarray:
        held, self.leaf_values, self._cache = self.leaf_values, values, {}
        try:
            return self.predict("next")
        finally:
            self.leaf_values, self._cache = held, {}

    def predict(self, name: str) -> np.ndarray:
        if not self._cache:  # Q_k on every query set at once (the loop and its diagnostics read all)
            client = self.client
            workers = list(dict.fromkeys(w for _, w, _, _ in self.segments))
            values = client.scatter(np.r_[self.leaf_values, 0.0], workers=workers, broadcast=True, hash=False)
            got = client.gather([client.submit(_means, s, values, workers=[w], allow_other_workers=True, pure=False)
                                 for s, (_, w, _, _) in zip(self._states, self.segments, strict=True)])
            self._cache = {q: np.concatenate([g[q] for g in got]) for q in self.QUERIES}
        return self._cache[name]

    def _exported(self) -> TreeEnsemble:
        """The structure as arrays on the client, fetched from the workers once per structure."""
        if self.ensemble is None:
            trees = [t for chunk in self.client.gather(self._trees) for t in chunk]
            ens = TreeEnsemble.from_trees(trees, consume=True)
            ens.n_features_in_ = int(self.n_features)  # type: ignore[attr-defined]
            if (u := self.schedule.target_unit) != 1.0:  # grown on y / u (FrozenBuilds._plan)
                ens = ens.with_values(ens.value * u)
            self.ensemble = ens
        return self.ensemble

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        """The saved ``Q_k`` carries its structure: its trees go to the workers, the leaves
        are looked up there and the leaf values read back (as in-process)."""
        self._release()
        self._adopt_ensemble(q.models[0])  # type: ignore[attr-defined]
        self.leaf_values = np.asarray(self.ensemble.value[self.leaf_ids], dtype=np.float64)  # type: ignore[union-attr]
        self._cache = {}
        self._restore_builds(rows)

    def release(self) -> None:
        """Drop the structure and the leaf positions on the workers."""
        self._release()
