"""What every reference problem offers: metadata, behaviour policies and a gymnasium.Env."""

from __future__ import annotations

import functools
import inspect
import json
from typing import Any

import gymnasium as gym
import numpy as np

from offline_adp.access import ResetModel
from offline_adp.data.info import ActionTable, DatasetInfo, Feature
from offline_adp.policies import Policy, UniformPolicy


class ReferenceProblem:
    """Mix-in for a reference problem; combine with an access model class.

    A reference problem is fully observed: its state is the observation vector whose
    features are ``features``. Subclasses set ``name``, ``features``, ``action_table``,
    ``gamma``, ``horizon`` and implement the access model's methods.
    """

    name: str = ""
    features: tuple[Feature, ...] = ()
    action_table: ActionTable
    #: Dotted path of the module documenting the problem's source.
    reference: str = ""
    #: Seconds per step (for time axes), when the problem has a physical clock.
    dt: float | None = None
    #: MCAP layout ``offline-adp simulate --format mcap-*`` writes (``generic`` or ``vehicle``).
    mcap_layout: str = "generic"
    #: Features whose mean absolute value over rollout time is worth a figure: name -> label.
    traced_features: dict[str, str] = {}
    #: The two features the report's policy, value and coverage maps span (None: the first two).
    map_features: tuple[str, str] | None = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Record the constructor options of every instance (:attr:`problem_options`).

        The outermost ``__init__`` of a subclass is wrapped so the keywords it was called
        with (positional ones by name) are kept; :meth:`dataset_info` writes them into the
        dataset's provenance and every simulator built for the dataset
        (:func:`offline_adp.envs.problem_for_dataset`) is constructed with them, so
        evaluation rolls out the system the data came from, not the default one.
        """
        super().__init_subclass__(**kwargs)
        init = cls.__dict__.get("__init__")
        if init is None:
            return
        sig = inspect.signature(init)

        @functools.wraps(init)
        def recording_init(self: Any, *args: Any, **kw: Any) -> None:
            if "_problem_options" not in self.__dict__:  # the outermost constructor records
                try:
                    bound = sig.bind(self, *args, **kw)
                    opts: dict[str, Any] | None = {}
                    for name, value in list(bound.arguments.items())[1:]:
                        kind = sig.parameters[name].kind
                        if kind is inspect.Parameter.VAR_POSITIONAL:
                            opts = None if value else opts  # positional extras cannot be replayed by name
                        elif kind is inspect.Parameter.VAR_KEYWORD:
                            opts = None if opts is None else {**opts, **value}
                        elif opts is not None:
                            opts[name] = value
                    json.dumps(opts)  # only JSON options can be recorded and replayed
                except (TypeError, ValueError):
                    opts = None
                self.__dict__["_problem_options"] = opts
            init(self, *args, **kw)

        cls.__init__ = recording_init  # type: ignore[method-assign]

    @property
    def problem_options(self) -> dict[str, Any] | None:
        """The constructor options this instance was made with (``{}``: the defaults);
        ``None`` when they cannot be recorded (not JSON)."""
        opts = self.__dict__.get("_problem_options", {})
        return None if opts is None else dict(opts)

    @property
    def feature_names(self) -> list[str]:
        return [f.name for f in self.features]

    def demonstrator(self) -> Policy:
        """A reasonable heuristic/expert behaviour policy (stochastic where noisy)."""
        return UniformPolicy(self.action_table.__len__())

    def exploration(self) -> Policy:
        """The exploration behaviour policy (uniformly random actions by default)."""
        return UniformPolicy(len(self.action_table))

    def dataset_info(self, **provenance: Any) -> DatasetInfo:
        """Metadata for data logged on this problem."""
        assert isinstance(self, ResetModel)
        provenance = {**provenance}
        provenance.setdefault("problem_options", self.problem_options)
        return DatasetInfo(
            features=self.features,
            action_table=self.action_table,
            gamma=self.gamma,
            horizon=self.horizon,
            propensity_source="logged",
            provenance=provenance,
            name=self.name,
            problem=self.name,
        )

    def rollout_summary(self, states: list[np.ndarray], terminated: np.ndarray) -> dict[str, float]:
        """Problem-specific numbers about rollouts (``states[t]``: the running episodes'
        states at step t). Default: the fraction of episodes that terminated."""
        return {"terminated_fraction": float(np.mean(terminated))}

    def named_scores(self, policy: Policy) -> dict[str, dict[str, Any]]:
        """Scores the problem's literature defines for a policy (name -> {"value", "method"});
        none by default. The evaluation reports them next to its own numbers."""
        return {}

    @classmethod
    def summary_line(cls, policy: dict[str, Any], demonstrator: dict[str, Any]) -> str:
        """Problem-specific words after the rollout comparison on the CLI (from the two
        :meth:`rollout_summary` blocks); empty by default."""
        return ""

    def make_env(self, **kwargs: Any) -> ProblemEnv:
        """This problem as a ``gymnasium.Env`` (reward = -cost)."""
        return ProblemEnv(self, **kwargs)


class ProblemEnv(gym.Env):
    """A reference problem as a ``gymnasium.Env``.

    Observations are the problem's feature vector, actions indices into its action
    table (a ``Box`` of commands within the table's bounds for a problem that accepts
    continuous commands, e.g. path_tracking with ``commands = "continuous"``), ``reward = -cost`` (gymnasium maximises;
    this library minimises cost and reports ``info["cost"]``). ``truncated`` is set at the problem's horizon.
    ``reset(options={"state": x})`` starts from a given state.
    """

    metadata = {"render_modes": []}

    def __init__(self, problem: ReferenceProblem, max_episode_steps: int | None = None) -> None:
        assert isinstance(problem, ResetModel)
        self.problem = problem
        self.max_episode_steps = max_episode_steps if max_episode_steps is not None else problem.horizon
        self.commands = bool(getattr(problem, "accepts_commands", False))
        if self.commands:
            lo, hi = problem.action_table.bounds()
            self.action_space: gym.Space = gym.spaces.Box(lo, hi, dtype=np.float64)
        else:
            self.action_space = gym.spaces.Discrete(len(problem.action_table))
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(problem.obs_dim,), dtype=np.float64)
        self._state: np.ndarray | None = None
        self._t = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if options and "state" in options:
            self._state = np.asarray(options["state"], dtype=np.float64).reshape(1, -1)
        else:
            self._state = self.problem.initial_states(1, self.np_random)
        self._t = 0
        return self._state[0].copy(), {}

    def step(self, action: Any):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action, np.float64).reshape(1, -1) if self.commands else np.array([int(action)])
        r = self.problem.step(self._state, a, self.np_random)
        self._state = r.next_states
        self._t += 1
        terminated = bool(r.terminated[0])
        truncated = (not terminated) and self.max_episode_steps is not None and self._t >= self.max_episode_steps
        cost = float(r.costs[0])
        return self._state[0].copy(), -cost, terminated, truncated, {"cost": cost}
