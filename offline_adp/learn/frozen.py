"""The frozen-structure LEARN step: a tree ensemble's structure built on a schedule,
leaf values re-averaged every iteration (Ernst, Geurts & Wehenkel 2005, section 4.3)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from types import SimpleNamespace
from typing import Any

import numpy as np

from offline_adp.errors import InvalidArgumentError
from offline_adp.learn.base import Learner, LearnSpec, fit_model
from offline_adp.learn.frozen_builds import BuildPlan, FrozenBuilds  # noqa: F401  (BuildPlan: importable from here too)
from offline_adp.learn.schedule import FrozenSchedule, screen_bias
from offline_adp.qfunctions import QFunction
from offline_adp.trees import builder as compiled
from offline_adp.trees.action_first import grow_action_first
from offline_adp.trees.averaging import (
    gather_positions,
    leaf_sums,
    leaf_sums_reuse,
    release_freed,
    resolve_n_jobs,
    thread_map,
)
from offline_adp.trees.compact import CompactTree
from offline_adp.trees.ensemble import (
    TreeEnsemble,
    compiled_per_tree_leaves,
    ensemble_per_tree_leaves,
    tree_mean,
)
from offline_adp.trees.loaded import compact_ensemble


class LeafPositions(Mapping[str, np.ndarray]):
    """The tree-major compact leaf positions of every query set and of the training rows
    (``"train"``, (trees, n) int32), as :attr:`FrozenTreesLearner.pos` shows them. The
    training rows' positions are not held: most are a next-state query's
    (:attr:`FrozenTreesLearner.reuse`), so ``pos["train"]`` is made on each access."""

    def __init__(self, queries: dict[str, np.ndarray], train: Any) -> None:
        self._queries, self._train = queries, train

    def __getitem__(self, name: str) -> np.ndarray:
        return self._train() if name == "train" else self._queries[name]

    def __iter__(self) -> Iterator[str]:
        yield from self._queries
        yield "train"

    def __len__(self) -> int:
        return len(self._queries) + 1


#: Bytes of a (trees, rows) int32 training-position matrix a frozen structure holds whole
#: (beyond this size the leaf sums read the reused rows' leaves from the next-state positions)
TRAIN_POSITIONS_HELD = 64 * 2**20


class FrozenTreesLearner(FrozenBuilds, Learner):
    """Fixed tree structure, leaf values re-averaged each iteration (joint encoding; with
    ``per_action`` the structures' trees split on the action first, :mod:`offline_adp.trees.action_first`,
    and Q is read as a joint model).

    Ernst, Geurts & Wehenkel (2005), "Tree-based batch mode reinforcement learning",
    JMLR 6, section 4.3: with the tree structure frozen, fitted Q-iteration is a kernel
    averager and converges. Update rule, with the structure built at iteration ``s``::

        structure_s = LEARN({((x_i, a_i), y_s,i)})         (at s in restructure_at)
        v_k = M @ y_k              M[leaf, i] = w_i / (sum of w of the training rows in the leaf)
        Q_k(query) = mean over trees of v_k[leaf of the query in that tree]

    The structure is (re)built at the iterations in ``restructure_at`` (and at the next
    iteration whenever the targets were constant, e.g. the first targets of a problem with
    one cost per step: LEARN on constant targets is that constant, represented by one-leaf
    trees, and says nothing about where to split). A build grows the ensemble on that
    iteration's targets (plus a tiny jitter, std ``1e-6 (u + std(y))``, a power of two ``u <= max|c| < 2u``, when the
    targets have ties, so that tied nodes still split (scikit-learn's trees do not always:
    see :mod:`offline_adp.trees.builder`); without ties a build on all rows by scikit-learn,
    ``builder="sklearn"``, is exactly the refit step; the default compiled
    builder, :mod:`offline_adp.trees.builder`, grows the same algorithm's trees from other
    random draws) -- each tree on a bootstrap sample of ``max_samples`` of
    the rows if given -- and looks up the leaf of every training and query input once
    (training rows that continue the previous row reuse the next-state lookups). Leaves
    are then *honest*: each leaf's value is the weighted mean target over **all** training
    rows falling in it, not only the rows its tree was grown on. The scikit-learn forest is
    dropped after the lookups (the arrays of :class:`~offline_adp.trees.ensemble.TreeEnsemble`
    remain). With a ``screen`` (:class:`~offline_adp.learn.schedule.TreeScreen`; opt-in,
    ``FittedQIteration(screen_trees=...)``) a build first grows ``screen.trees`` trees and grows the rest of the forest
    (scikit-learn's warm start: the same trees a one-shot fit grows) only when the greedy targets would be measurably
    biased by the smaller forest (:func:`~offline_adp.learn.schedule.greedy_min_bias`, carried through ``1 / (1 -
    gamma)``, above ``screen.tol * std(y)``). With ``early`` (:class:`~offline_adp.learn.schedule.EarlyBuilds`; opt-in)
    a build whose error is damped before the fit ends (:func:`~offline_adp.learn.schedule.build_weight` below
    ``early.ratio``) grows only ``early.trees`` trees. An iteration is one leaf sum per tree over the training rows'
    tree-major int32 leaf positions (not held for the rows that continue the previous row: those are read from the
    next-state queries' positions, in the same row order, so the sums are the same) and one gather per tree and query
    (each within that tree's leaves, so cache-sized): no tree fitting, no traversal. Builds, lookups and these sums run
    in ``n_jobs`` threads (the regressor's; -1, the extra_trees default: every core), each tree's work independent and
    every sum in one fixed order, so the Q-values are the same to the last bit for any thread count
    (:mod:`offline_adp.trees.averaging`). A build drops the previous structure first, and the compiled builder's trees
    are held as :class:`~offline_adp.trees.compact.CompactTree` (about 28 bytes a node). With a fixed structure the
    update is a gamma-contraction, so it converges -- to the fixed point of *that* averager, which is only as good as
    the structure: a structure fitted to early targets cannot represent what later targets need.

    How the number of builds and their row fractions trade score against CPU:
    docs/fqi-modes.md.
    """

    def __init__(self, spec: LearnSpec, schedule: FrozenSchedule | None = None) -> None:
        super().__init__(spec)
        # per_action: the structures' trees split on the action first (trees.action_first); Q is read as a joint model
        self.action_first = bool(self.encoder.per_action)
        if self.action_first:
            self.encoder = dataclasses.replace(self.encoder, per_action=False)
        self._init_builds(schedule)
        phi_next = self.queries["next"][0] if "next" in self.queries else None
        same = np.zeros(len(self.phi), bool)
        # (with continuous commands a next state's candidates need not hold the next row's command)
        if (phi_next is not None and len(self.phi) > 1 and phi_next.shape == self.phi.shape
                and not self.encoder.continuous):
            same[1:] = (self.phi[1:] == phi_next[:-1]).all(axis=1)
        self.reuse = np.flatnonzero(same)  # training row i's input is next-query row i - 1's (with a_i)
        self._pos: dict[str, np.ndarray] = {}  # the query sets' leaf positions (tree-major int32)
        self._rest: np.ndarray | None = None  # the training rows' positions, at the rows not reused
        self._train: np.ndarray | None = None  # all of them, held where small (TRAIN_POSITIONS_HELD)
        self._src = np.full(len(self.phi), -1, np.int64)  # training row i's column of pos["next"] (-1: in _rest)
        self._values: np.ndarray | None = None  # leaf_values' buffer, with a 0 after them
        self._cache: dict[str, np.ndarray] = {}
        params = self.regressor.get_params() if hasattr(self.regressor, "get_params") else {}
        # threads of the lookups and of every iteration's averaging: the regressor's n_jobs
        # (-1, the extra_trees default: every core); the numbers do not depend on it
        self.n_jobs = resolve_n_jobs(params.get("n_jobs"))

    def _release(self) -> None:
        """Drop the current structure (its forest or arrays, leaf positions and caches)
        before the next one is grown: the two are never held together (a forest of fully
        grown trees on 131,072 rows is ~0.7 GB)."""
        self.ensemble, self._forest = None, None
        self._pos, self._rest, self._cache, self._train = {}, None, {}, None
        self.leaf_ids = self.leaf_values = self._wsum = self._values = None  # type: ignore[assignment]
        release_freed()  # the freed structure's pages go back to the system before the next is grown

    @property
    def pos(self) -> Mapping[str, np.ndarray]:
        """Tree-major compact leaf positions (trees, queries) of every query set and of the
        training rows (``"train"``, made on access: :class:`LeafPositions`); position
        ``len(leaf_ids)`` is a leaf without training rows."""
        if self._rest is None:
            return {}
        return LeafPositions(self._pos, self._train_positions)

    def _train_positions(self) -> np.ndarray:
        assert self._rest is not None
        if self._train is not None:
            return self._train
        if not (self._src >= 0).any():
            return self._rest.copy()
        return gather_positions(self._pos["next"], self._src, self._rest)

    def _build(self, y: np.ndarray, k: int) -> None:
        self._release()
        X = self.encoder.pairs(self.phi, self.actions)
        if self._start_build(y):  # LEARN on constant targets is that constant: one leaf per tree
            self._set_ensemble(self._constant_structure(y, X.shape[1]))
            self._operators(self._ensemble_per_tree(self.ensemble))
            return
        plan = self._plan(y, k, len(X), X.shape[1])
        grow, model, full, screen, native, s = plan.grow, plan.model, plan.full, plan.screen, plan.native, self.screen
        if self.action_first and native is None:
            raise InvalidArgumentError("the frozen mode with action_encoding='per_action' grows its structures with "
                                       "the compiled extra-trees builder (the default extra_trees regressor, "
                                       "tree_builder='auto')")
        if native is not None:  # the same algorithm, compiled; tree t depends on (seed, t) only
            first = native.n_estimators if not screen else s.trees  # type: ignore[union-attr]
            n_features, grown = X.shape[1], self._grow(X, grow, native, range(first))
            if not screen:
                del X  # not held through the lookups
            self._adopt_grown(grown, n_features)
            del grown
            if screen:
                assert s is not None
                self.screen_value = self._screen_bias(np.asarray(y, dtype=np.float64), full)
                if not self.screen_value <= s.tol:
                    self._adopt_grown(self._grow(X, grow, native, range(s.trees, full)), X.shape[1], start=s.trees)
            return
        if not screen:
            self._adopt(fit_model(model, X, grow, self.weights))
            return
        assert s is not None
        model.set_params(n_estimators=s.trees, warm_start=True)  # its trees are the full forest's first ones
        self._adopt(fit_model(model, X, grow, self.weights))
        self.screen_value = self._screen_bias(np.asarray(y, dtype=np.float64), full)
        if not self.screen_value <= s.tol:  # the greedy targets need the whole forest (NaN: to be safe)
            model.set_params(n_estimators=full)
            self._adopt(fit_model(model, X, grow, self.weights), start=s.trees)

    def _adopt(self, forest: Any, start: int = 0, train_leaves: list[np.ndarray] | None = None) -> None:
        """Take ``forest`` as the structure: look up every training and query input in it
        (from tree ``start`` on: the earlier trees' lookups are held, see :meth:`_operators`)."""
        if not hasattr(forest, "estimators_") or not hasattr(forest.estimators_[0], "tree_"):
            raise InvalidArgumentError("the frozen-structure mode needs a scikit-learn tree ensemble (extra_trees, "
                                       "random_forest)")
        # the forest's arrays are exported (TreeEnsemble) only when a Q is asked for
        # (snapshot: a checkpoint, the end of the fit), not at every build
        sizes = np.array([e.tree_.node_count for e in forest.estimators_], dtype=np.int64)
        self.ensemble, self._forest = None, forest
        self._roots, self._n_nodes = np.r_[0, np.cumsum(sizes)[:-1]], int(sizes.sum())
        trees = [e.tree_ for e in forest.estimators_]
        self._operators(compiled_per_tree_leaves(trees[start:], self._roots[start:]), start=start,
                        train_leaves=train_leaves)

    def _grow(self, X: np.ndarray, y: np.ndarray, native: compiled.TreeParams,
              trees: range) -> list[tuple[Any, np.ndarray | None]]:
        """Trees ``trees`` from the compiled builder, each as a
        :class:`~offline_adp.trees.compact.CompactTree` (about 28 bytes a node, made in the calling
        thread) and its training rows' leaves (None unless every row is in the tree)."""
        def finish(t: compiled.GrownTree) -> tuple[Any, np.ndarray | None]:  # copies: the arrays are reused
            leaf = t.train_leaf.copy() if t.train_leaf is not None and int(t.train_leaf.min(initial=0)) >= 0 else None
            return CompactTree.from_grown(t), leaf

        every = not native.bootstrap and (self.weights is None or bool((np.asarray(self.weights) > 0).all()))
        if self.action_first:
            return grow_action_first(X, y, self.weights, native, trees, self.encoder.action_features.shape[1], every)
        return compiled.grow_trees(X, y, self.weights, native, trees, finish=finish, record_leaves=every)

    def _adopt_grown(self, trees: list[tuple[Any, np.ndarray | None]], n_features: int, start: int = 0) -> None:
        """As :meth:`_adopt`, for trees from the compiled builder (:meth:`_grow`): held as
        :class:`~offline_adp.trees.compact.CompactTree` (their compiled lookups, and the
        export), with each training row's leaf where every row is in the tree.
        ``start > 0``: they follow the ``start`` trees held, as a screened build grows
        its forest."""
        held = self._forest.estimators_[:start] if start else []
        new = [SimpleNamespace(tree_=tree) for tree, _ in trees]
        # every training row in every tree (no bootstrap, no zero weight): its leaf is known
        known = all(leaf is not None for _, leaf in trees)
        self._adopt(SimpleNamespace(estimators_=held + new, n_features_in_=int(n_features)), start=start,
                    train_leaves=[leaf for _, leaf in trees] if known else None)

    def _screen_bias(self, y: np.ndarray, full: int) -> float:
        """:func:`~offline_adp.learn.schedule.screen_bias` of the current (screen's) trees."""
        assert self.screen is not None
        means = self._leaf_sums(y if self._w is None else self._w * y) / self._wsum
        return screen_bias(self.screen, self._pos["next"], means, self.encoder.n_actions, self._w, y, full)

    def _set_ensemble(self, ensemble: TreeEnsemble) -> None:
        self.ensemble, self._forest = ensemble, None
        self._roots, self._n_nodes = np.asarray(ensemble.roots), len(ensemble.value)

    def _exported(self) -> TreeEnsemble:
        """The structure as arrays, exported from the forest on first use (then the forest,
        whose node arrays are as large again, is dropped)."""
        if self.ensemble is None:
            forest, self._forest = self._forest, None
            trees = [e.tree_ for e in forest.estimators_]
            forest.estimators_ = []  # ours (a clone): each tree is freed as soon as it is copied
            # the compiled builder's trees are the lookups: held as they are, the per-node arrays
            # (40 bytes a node, and a rebuilt lookup's 32) made only if asked for (trees.loaded)
            compact = all(type(t) is CompactTree for t in trees)
            ens = compact_ensemble(trees) if compact else TreeEnsemble.from_trees(trees, consume=True)
            ens.n_features_in_ = int(forest.n_features_in_)  # type: ignore[attr-defined]
            if (u := self.schedule.target_unit) != 1.0:  # grown on y / u (FrozenBuilds._plan)
                ens = ens.with_values(ens.value * u)
            self._set_ensemble(ens)
        return self.ensemble

    def _operators(self, tree_leaves: Any, start: int = 0, train_leaves: list[np.ndarray] | None = None) -> None:
        """The training rows' leaf positions (only those of the rows not reused: ``_rest``, with
        ``_src`` saying which column of ``pos["next"]`` the others read), the leaf weights and
        the query operators (leaf positions),
        tree by tree: ``tree_leaves(X)`` returns ``leaves(t)``, the global leaf id of every
        row of ``X`` in tree ``t``. Training rows that continue the previous row (``x_i == x'_{i-1}``)
        take their leaves from the next-state lookup (a third of the lookups with two
        actions). Everything is tree-major int32 and no (rows, trees) int64 matrix is ever
        held: one tree's lookups at a time per thread. The trees are looked up in
        ``n_jobs`` threads, each tree's positions local to it (its own compact leaves,
        numbered in node order), then shifted by the leaves of the trees before it: the
        same numbers for any thread count. ``start > 0``: the first ``start`` trees are
        those whose lookups are held already (a screened build growing its forest); their
        positions are kept and ``tree_leaves`` looks up the later trees only.

        ``train_leaves`` (the compiled builder's, one array per tree from ``start`` on, local
        node ids): every training row's leaf is known, so nothing is looked up for the training
        rows, and the next-state queries they repeat are not looked up either: half of them
        with two actions."""
        n, m = len(self.phi), len(self._roots)
        names = [q for q in self.queries if q != "train"]
        inputs = {q: self._joint(*self.queries[q]) for q in names}
        reuse = self.reuse if len(self.reuse) and "next" in inputs else np.zeros(0, np.int64)
        rest = np.ones(n, bool)
        rest[reuse] = False
        # row i continues row i - 1: its leaf is x'_{i-1}'s with a_i (never with continuous commands: reuse is empty)
        from_next = self.actions[reuse] * n + reuse - 1 if len(reuse) else np.zeros(0, np.int64)
        looked = None  # the next-state queries looked up (the others are training rows' leaves)
        if train_leaves is not None and len(reuse):
            looked = np.ones(len(inputs["next"]), bool)
            looked[from_next] = False
            inputs = {**inputs, "next": inputs["next"][looked]}
        lookups = {q: tree_leaves(inputs[q]) for q in names}
        if rest.any() and train_leaves is None:
            lookups[""] = tree_leaves(self.encoder.pairs(self.phi[rest], self.actions[rest]))
        sizes = {q: (len(looked) if q == "next" and looked is not None else len(inputs[q])) for q in names}
        del inputs
        ends = np.r_[self._roots[1:], self._n_nodes]
        held, held_rest, held_bounds, held_ids = ((self._pos, self._rest, self._bounds, self.leaf_ids) if start
                                                  else ({}, None, None, None))
        self._pos, self._rest = {}, None  # the previous structure's positions go before the new ones are made
        self._pos = {q: np.empty((m, sizes[q]), np.int32) for q in names}
        all_rest = bool(rest.all())
        # the training rows' positions: only those of the rows not reused are held (the
        # others are their next-state query's, read from pos["next"] by the leaf sums)
        train = np.empty((m, int(rest.sum())), np.int32)
        if start:  # the same trees, the same compact leaves (re-marked for the new leaf count below)
            assert held_rest is not None
            for q, p in [*self._pos.items(), ("train", train)]:
                p[:start] = (held_rest if q == "train" else held[q])[:start]
            del held, held_rest

        def one(t: int) -> np.ndarray:
            """Tree t's positions, local to its compact leaves (-1: a leaf without training
            rows), written into its rows; returns its leaves' global node ids."""
            raw = {q: f(t - start) for q, f in lookups.items()}
            root = int(self._roots[t])
            if train_leaves is not None:
                leaf = train_leaves[t - start]
                if looked is not None:
                    full = np.empty(len(looked), np.int64)
                    full[looked] = raw["next"]
                    full[from_next] = leaf[reuse] + root
                    raw["next"] = full
                leaf_local = leaf
            else:
                leaf = np.empty(n, np.int64)
                leaf[rest] = raw.pop("", None) if rest.any() else 0
                if len(reuse):
                    leaf[reuse] = raw["next"][from_next]
                leaf_local = leaf - root
            used = np.zeros(int(ends[t]) - root, bool)
            used[leaf_local] = True
            local = np.flatnonzero(used)  # this tree's leaves holding training samples
            lookup = np.full(len(used), -1, np.int32)
            lookup[local] = np.arange(len(local), dtype=np.int32)
            train[t] = lookup[leaf_local if all_rest else leaf_local[rest]]
            for q in names:
                r = raw.pop(q)
                r -= root
                self._pos[q][t] = lookup[r]
            return local + root

        new_ids = thread_map(one, range(start, m), self.n_jobs)
        ids = ([held_ids] if start else []) + new_ids
        bounds = np.r_[np.asarray(held_bounds[:start + 1], np.int64) if start else np.zeros(1, np.int64),
                       (int(held_bounds[start]) if start else 0) + np.cumsum([len(i) for i in new_ids], dtype=np.int64)]
        joined = np.concatenate(ids)
        # compact index: tree t's leaves are [bounds[t], bounds[t + 1])
        self.leaf_ids = joined.astype(np.int32) if self._n_nodes < 2**31 else joined
        del joined
        L = len(self.leaf_ids)
        old_L = len(held_ids) if start else None

        def shift(t: int) -> None:
            """Tree t's positions from local to global compact leaves; a leaf without
            training weight reads value L (0)."""
            lo = int(bounds[t])
            for q, p in [*self._pos.items(), ("train", train)]:
                row = p[t]
                if t < start:  # held: already global; "no training leaf" was the old L
                    if q != "train":
                        row[row == old_L] = L
                    continue
                row += lo
                if q != "train":
                    row[row < lo] = L

        thread_map(shift, range(m), self.n_jobs)
        for q, p in [*self._pos.items(), ("train", train)]:  # the gathers skip bounds checks: keep them in range
            if p.size and (int(p.min()) < 0 or int(p.max()) > L):
                raise RuntimeError(f"frozen structure: leaf positions of {q!r} outside [0, {L}]")
        self._bounds, self._m = bounds, m
        self._w = None if self.weights is None else np.asarray(self.weights, dtype=np.float64)
        self._src = np.full(n, -1, np.int64)
        self._src[reuse] = from_next
        self._rest = train  # every training leaf holds its own sample
        # the whole (trees, rows) training matrix where it is small: the leaf sums then read it
        # in order (~1.3x faster than through pos["next"]; the same sums bit for bit); above
        # TRAIN_POSITIONS_HELD bytes the memory matters more (1M rows x 50 trees: 0.19 GiB)
        self._train = None
        if len(reuse) and m * n * 4 <= TRAIN_POSITIONS_HELD:
            self._train = gather_positions(self._pos["next"], self._src, self._rest)
        self._wsum = self._leaf_sums(np.ones(n) if self._w is None else self._w)
        release_freed()  # the lookups' temporaries

    def _ensemble_per_tree(self, ens: TreeEnsemble) -> Any:
        """The per-tree leaf lookup of a structure held as arrays (a restored checkpoint, the
        constant-target structure), checked against our inputs' width first."""
        return ensemble_per_tree_leaves(ens, self.encoder.pairs(self.phi[:1], self.actions[:1]))

    def leaf_weight_sums(self, v: np.ndarray) -> np.ndarray:
        """``sum of v_i`` over the training rows in each leaf (compact index, as
        ``leaf_ids``); the same numbers as ``np.bincount`` over each tree's leaves."""
        return self._leaf_sums(np.asarray(v, dtype=np.float64))

    def reused_positions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(nxt, src, rest, wsum)``: training row ``i``'s leaf in tree ``t`` is ``nxt[t, src[i]]``
        where ``src[i] >= 0``, else the next column of ``rest[t]`` (the positions the fit holds,
        none made), and the leaf weights (:attr:`weight_sums`)."""
        assert self._rest is not None and self._wsum is not None
        if self._train is not None or self._rest.shape[1] == len(self._src):  # every row's held
            rest = self._rest if self._train is None else self._train
            return rest, np.full(len(self._src), -1, np.int64), rest, self._wsum
        return self._pos["next"], self._src, self._rest, self._wsum

    @property
    def weight_sums(self) -> np.ndarray | None:
        """The training weight in each leaf (compact index), held: ``leaf_weight_sums`` of the
        weights (of ones without weights), the same numbers."""
        return self._wsum

    def _leaf_sums(self, v: np.ndarray) -> np.ndarray:
        """``sum of v_i`` over the training rows in each leaf (compact index), trees in
        ``n_jobs`` threads (rows summed in order: the same numbers for any count)."""
        assert self._rest is not None
        if self._train is not None or self._rest.shape[1] == len(self._src):  # held, or no row reused
            return leaf_sums(self._rest if self._train is None else self._train, self._bounds, v, self.n_jobs)
        return leaf_sums_reuse(self._pos["next"], self._src, self._rest, self._bounds, v, self.n_jobs)

    def fit(self, y: np.ndarray, k: int) -> None:
        built = self._builds_at(k)
        if built:
            self._build(y, k)
        self._built()
        y = np.asarray(y, dtype=np.float64)
        prev = None if built or self.settle is None else self.leaf_values  # Q_{k-1}'s, for the settling
        self._cache, self.leaf_values, self._values = {}, None, None  # type: ignore[assignment]  # the last ones go first
        sums = self._leaf_sums(y if self._w is None else self._w * y)
        # the leaf means of y_k and a 0 after them (what a query reads for "no training leaf")
        self._values = np.empty(len(sums) + 1)
        np.divide(sums, self._wsum, out=self._values[:-1])
        self._values[-1] = 0.0
        del sums
        if prev is not None:  # the final structure may settle (learn.settle)
            v = self._settle(y, self._values[:-1], prev, k, built)
            del prev
            if v.base is not self._values:  # the solver's (learn.settle), not the plain step's
                self._values[:-1] = v
        else:
            self.inner_backups = 0
        self.leaf_values = self._values[:-1]

    def _leaf_means(self, y: np.ndarray) -> np.ndarray:
        y = np.asarray(y, dtype=np.float64)
        return self._leaf_sums(y if self._w is None else self._w * y) / self._wsum

    def _next_q(self, values: np.ndarray) -> np.ndarray:
        phi = self.queries["next"][0]
        q = tree_mean(np.r_[values, 0.0], self._pos["next"], self.n_jobs)
        return q.reshape(self.encoder.n_actions, len(phi)).T

    def predict(self, name: str) -> np.ndarray:
        if name in self._cache:
            return self._cache[name]
        phi, actions = self.queries[name]
        values = self._cache.get("")  # leaf values and a 0 for "no training leaf", once per iteration
        if values is None:
            own = self._values is not None and self.leaf_values is not None and self.leaf_values.base is self._values
            values = self._cache[""] = self._values if own else np.r_[self.leaf_values, 0.0]
        # the same leaves: the same numbers
        if name == "train" and self._rest is not None and self._rest.shape[1] < len(phi):
            v = np.empty(len(phi))
            rest = self._src < 0
            v[rest] = tree_mean(values, self._rest, self.n_jobs)
            v[self.reuse] = self.predict("next")[self.reuse - 1, self.actions[self.reuse]]
        elif name == "train" and self._rest is not None:
            v = tree_mean(values, self._rest, self.n_jobs)
        else:
            v = tree_mean(values, self._pos[name], self.n_jobs)  # mean over trees of the reached leaves
        self._cache[name] = v if actions is not None else v.reshape(self.encoder.n_actions, len(phi)).T
        return self._cache[name]

    def restore(self, q: QFunction, iteration: int, rows: list[dict[str, Any]] | None = None) -> None:
        """The saved ``Q_k`` carries its structure: recompute the leaves of the training and
        query inputs with it (the same leaves the structure's forest gave) and read the
        leaf values back."""
        # a TreeQ, or the RegressorQ of TreeEnsembles load_q returns  # type: ignore[attr-defined]
        self._set_ensemble(q.models[0])
        self._operators(self._ensemble_per_tree(self.ensemble))
        self.leaf_values = np.asarray(self.ensemble.value[self.leaf_ids], dtype=np.float64)
        self._cache = {}
        self._restore_builds(rows)
