"""The algorithm registry: name -> estimator class, configuration model, access model, artifact.

One table replaces the if/elif chains of the CLI, the fit runner and the pipeline:
``offline-adp fit --algorithm NAME``, a pipeline's ``[fit] algorithm`` and the Python
function :func:`offline_adp.runs.fit` all look the algorithm up here.

Each entry's *configuration model* (the keys a TOML ``[NAME]`` table or a pipeline's
``[fit.params]`` may hold) is generated from the estimator's constructor signature,
so it cannot drift from the code: the estimator's parameters with their annotated types,
minus those that take Python objects (regressor instances, policies, models), plus the
entry's *extra keys* (a policy to evaluate by path, a simulator by name, a nested
``fqe`` table). Values are then checked as scikit-learn checks its estimators': the
estimator's ``_parameter_constraints`` by scikit-learn's ``_validate_params()``, then its
``_check_param_combinations()`` hook (:mod:`offline_adp.algorithms.params`), the two
calls its ``fit`` starts with. That happens before anything runs or is written, so
``mode = "fast"`` fails at load time, one line naming the file, section and key.
"""

from __future__ import annotations

import importlib
import inspect
import re
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from typing import Any

from pydantic import create_model
from sklearn.utils._param_validation import InvalidParameterError

from offline_adp.algorithms.params import refuse_continuous
from offline_adp.config import ConfigModel, validate_config
from offline_adp.errors import IncompatibleError, SpecError, UnknownNameError

_SIMPLE = (int, float, str, bool, dict, list, tuple, type(None))


@dataclass(frozen=True)
class AlgorithmEntry:
    """One algorithm of the chapter as the runner sees it.

    Attributes
    ----------
    name : str
        The name in the CLI and in configuration files.
    estimator : str
        ``"module:Class"`` of the scikit-learn style estimator.
    access : str
        The weakest access model it needs (the chapter's list).
    summary : str
        One line for ``--help``.
    resumable : bool
        Fits iteration by iteration with checkpoints (``--resume``).
    dask : bool
        The Dask engine has a distributed version of it.
    artifact : str
        What ``model/`` holds: ``"q"`` (a Q-function and its greedy policy) or
        ``"policy"`` (a policy, and its Q-function when it has one).
    extra : dict
        Configuration keys besides the estimator's parameters: name -> (type, default).
    exclude : tuple of str
        Constructor parameters that take Python objects and have no configuration form.
    required : dict
        Keys a run cannot do without (an extra key whose default is None): name -> what to
        write, for the message (:meth:`check_complete`).
    """

    name: str
    estimator: str
    access: str
    summary: str
    resumable: bool = False
    artifact: str = "policy"
    extra: dict[str, tuple[Any, Any]] = field(default_factory=dict)
    exclude: tuple[str, ...] = ()
    fit_with: Callable[[AlgorithmEntry, dict[str, Any], Any], Any] | None = None
    #: The Dask engine has a distributed version (``engines/dask/``), used with LightGBM.
    dask: bool = False
    required: dict[str, str] = field(default_factory=dict)

    def build_and_fit(self, params: dict[str, Any], dataset: Any) -> Any:
        """Construct the estimator from checked ``params`` (extra keys resolved: a policy
        loaded, a simulator made) and fit it on ``dataset``; returns the fitted estimator."""
        return (self.fit_with or _fit_on_data)(self, dict(params), dataset)

    def estimator_class(self) -> type:
        module, cls = self.estimator.split(":")
        return getattr(importlib.import_module(module), cls)

    def params_model(self) -> type[ConfigModel]:
        """The pydantic model of this algorithm's configuration table."""
        return _params_model(self.name)

    def check_complete(self, params: dict[str, Any] | None, source: str = "", section: str | None = None) -> None:
        """SpecError unless ``params`` hold every key a run needs (``required``). Separate
        from :meth:`check_params`, which also checks tables that are completed later (an
        ``[api.fqe]`` table gets its policy at every iteration)."""
        for key, what in self.required.items():
            if (params or {}).get(key) is None:
                where = f"{source}: " if source else ""
                raise SpecError(f"{where}{self.name} needs {what}: {key} = {_EXAMPLES[key]} in "
                                f"[{section or self.name}]")

    def check_params(self, params: dict[str, Any] | None, source: str = "",
                     section: str | None = None) -> dict[str, Any]:
        """Validate ``params`` (types, then the estimator's value checks); returns them
        with relative paths left as given and numbers as validated (a whole float for an
        integer field becomes that integer). Raises SpecError naming file and key."""
        model = validate_config(self.params_model(), params or {}, source, section or self.name)
        given = model.model_dump(exclude_unset=True)
        fqe = FQE.check_params(given["fqe"], source, f"{section or self.name}.fqe") if "fqe" in given else None
        est_params = {k: v for k, v in given.items() if k not in self.extra}
        est = self.estimator_class()(**est_params)
        try:  # the checks ``fit`` starts with (scikit-learn's, then the estimator's cross-parameter hook)
            est.check_params()  # _parameter_constraints, then the combinations
        except InvalidParameterError as exc:
            raise SpecError(parameter_error(exc, source, section or self.name)) from None
        out = dict(params or {})
        for k, v in given.items():  # numbers as validated (``2.0`` for an integer field runs as 2)
            if k in out and isinstance(v, int | float) and not isinstance(v, bool) and type(out[k]) is not type(v):
                out[k] = v
        if fqe is not None and isinstance(out.get("fqe"), dict):
            out["fqe"] = {**out["fqe"], **{k: v for k, v in fqe.items() if k in out["fqe"]}}
        return out


def parameter_error(exc: InvalidParameterError, source: str, section: str) -> str:
    """scikit-learn's ``The 'key' parameter of Class must be ... Got ... instead.`` as one
    line naming the file, section and key: ``FILE: section.key must be ... Got ... instead.``"""
    text = " ".join(str(exc).split())
    m = re.match(r"The '(\w+)' parameter of \w+ (.*)", text)
    where = f"{source}: " if source else ""
    return f"{where}{section}.{m.group(1)} {m.group(2)}" if m else f"{where}[{section}] {text}"


def _config_type(annotation: Any) -> Any | None:
    """The annotation if every member of it is a plain configuration type (else None)."""
    if annotation is Any:
        return Any
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is None:
        return annotation if annotation in _SIMPLE else None
    if origin in (typing.Union, types.UnionType):
        return annotation if all(_config_type(a) is not None for a in args) else None
    if origin in (dict, list, tuple, typing.Literal):
        return annotation
    return None


@cache
def _params_model(name: str) -> type[ConfigModel]:
    entry = ALGORITHMS[name]
    cls = entry.estimator_class()
    sig = inspect.signature(cls.__init__)
    try:
        hints = typing.get_type_hints(cls.__init__)
    except Exception:  # an annotation that cannot be resolved at run time: accept any value
        hints = {}
    fields: dict[str, Any] = {}
    for name, p in sig.parameters.items():
        if name == "self" or name in entry.exclude or p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL):
            continue
        typ = _config_type(hints.get(name, Any))
        if typ is None:
            continue
        fields[name] = (typ, p.default)
    for name, (typ, default) in entry.extra.items():
        fields[name] = (typ, default)
    model = create_model(f"{cls.__name__}Config", __base__=ConfigModel, **fields)
    model.__doc__ = f"Configuration of {entry.name}: {entry.summary}"
    return model


def _fit_on_data(entry: AlgorithmEntry, p: dict[str, Any], ds: Any) -> Any:
    return entry.estimator_class()(**p).fit(ds)



def _simulator(p: dict[str, Any], ds: Any = None) -> Any:
    """The configured simulator: ``problem_options`` when given, else the options the
    dataset's own problem was made with (:func:`offline_adp.envs.problem_for_dataset`)."""
    from offline_adp.envs import make_problem, problem_for_dataset

    name, options = p.pop("simulator", None), p.pop("problem_options", None)
    if name is None:
        return None
    if options is None and ds is not None:
        return problem_for_dataset(name, ds.info)
    return make_problem(name, **(options or {}))


def _fit_fqe(entry: AlgorithmEntry, p: dict[str, Any], ds: Any) -> Any:
    from offline_adp.artifacts import load_index_policy

    entry.check_complete(p)
    policy = load_index_policy(p.pop("policy"))
    if getattr(policy, "continuous", False):  # its Q reads the policy's own commands: not a savable model yet
        raise IncompatibleError("fit --algorithm fqe of a continuous policy is not supported (its Q-function reads the "
                                "policy's own commands and cannot be saved yet); `offline-adp evaluate RUN` runs FQE "
                                "over commands as part of the evaluation")
    return entry.estimator_class()(policy=policy, **p).fit(ds)


def _fit_api(entry: AlgorithmEntry, p: dict[str, Any], ds: Any) -> Any:
    from offline_adp.algorithms.api import default_evaluator

    table = p.pop("fqe", None)  # API's evaluator defaults under the [api.fqe] table's keys
    return entry.estimator_class()(fqe=default_evaluator(**(table or {})), **p).fit(ds)


def _fit_cpi(entry: AlgorithmEntry, p: dict[str, Any], ds: Any) -> Any:
    from offline_adp.algorithms.api import default_evaluator

    refuse_continuous("cpi", ds)
    table = p.pop("fqe", None)  # API's evaluator defaults under the [cpi.fqe] table's keys
    return entry.estimator_class()(fqe=default_evaluator(**(table or {})), model=_simulator(p, ds), **p).fit(ds)


def _fit_psdp(entry: AlgorithmEntry, p: dict[str, Any], ds: Any) -> Any:
    from offline_adp.features import drop_features

    entry.check_complete(p)
    refuse_continuous("psdp", ds)
    sim = _simulator(p, ds)
    source, drop = p.pop("baseline_source", None), p.pop("drop_features", None)
    baseline = ds.filter_source(source) if source else ds
    fmap = drop_features(ds.feature_names, drop) if drop else None
    return entry.estimator_class()(feature_map=fmap, **p).fit(sim, baseline)


_EXAMPLES = {"policy": '"RUN_DIR/model"', "simulator": '"path_tracking"'}

FQI = AlgorithmEntry(
    "fqi", "offline_adp.algorithms.fqi:FittedQIteration", "trace data",
    "fitted Q-iteration (Algorithms 10, 11; tree-based as in Ernst, Geurts & Wehenkel 2005)",
    resumable=True, artifact="q", exclude=("feature_map", "initial_q"), dask=True,
)
FQE = AlgorithmEntry(
    "fqe", "offline_adp.algorithms.fqe:FittedQEvaluation", "trace data",
    "fitted Q evaluation of a saved policy (Algorithms 12, 13)",
    extra={"policy": (str | None, None)}, exclude=("policy", "feature_map", "initial_q"), fit_with=_fit_fqe,
    required={"policy": "the policy to evaluate"},
)
API = AlgorithmEntry(
    "api", "offline_adp.algorithms.api:ApproximatePolicyIteration", "trace data",
    "approximate policy iteration (FQE + greedy improvement)",
    extra={"fqe": (dict[str, Any] | None, None)}, exclude=("fqe", "initial_policy", "model"), fit_with=_fit_api,
)
CPI = AlgorithmEntry(
    "cpi", "offline_adp.algorithms.cpi:ConservativePolicyIteration", "trace data (reset model for rollout values)",
    "conservative policy iteration (Kakade & Langford 2002), line search or the safe step",
    extra={"fqe": (dict[str, Any] | None, None), "simulator": (str | None, None),
           "problem_options": (dict[str, Any] | None, None)},
    exclude=("fqe", "initial_policy", "model"), fit_with=_fit_cpi,
)
PSDP = AlgorithmEntry(
    "psdp", "offline_adp.algorithms.psdp:PSDP", "reset model (a simulator) + baseline state distribution",
    "policy search by dynamic programming (Algorithm 14)",
    extra={"simulator": (str | None, None), "problem_options": (dict[str, Any] | None, None),
           "baseline_source": (str | None, None), "drop_features": (list[str] | None, None)},
    exclude=("feature_map",), fit_with=_fit_psdp, required={"simulator": "a simulator (a reference problem)"},
)

#: name -> entry, in the order ``--help`` lists them.
ALGORITHMS: dict[str, AlgorithmEntry] = {e.name: e for e in (FQI, FQE, API, CPI, PSDP)}


def resumable_algorithms() -> list[str]:
    """Names of the algorithms whose entry is ``resumable`` (``--resume`` continues them
    from their last checkpoint), in registry order."""
    return [name for name, entry in ALGORITHMS.items() if entry.resumable]


def get_algorithm(name: str) -> AlgorithmEntry:
    """The registry entry for ``name`` (``UnknownNameError`` lists the known names)."""
    try:
        return ALGORITHMS[name]
    except KeyError:
        raise UnknownNameError(f"unknown algorithm {name!r}; known: {list(ALGORITHMS)}") from None
