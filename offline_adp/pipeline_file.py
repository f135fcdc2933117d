"""The pipeline file (``offline-adp run PIPELINE.toml``, :mod:`offline_adp.pipeline`): its model
(:class:`PipelineFile` and one section model per table, the JSON Schema's source), the
``--set`` overrides, and :func:`load_pipeline`, which reads and checks a whole file (inputs,
ingestion spec, fit parameters) before any stage runs.
"""

from __future__ import annotations

import glob
import json
from os import PathLike
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from offline_adp.algorithms.registry import ALGORITHMS, get_algorithm
from offline_adp.config import ConfigModel, did_you_mean, load_toml, validate_config
from offline_adp.data.rundir import NAME_PATTERN, check_name
from offline_adp.envs import PROBLEM_NAMES
from offline_adp.errors import SpecError
from offline_adp.evaluation.settings import MAX_SEED, EvaluationOptions

#: Address schemes of Dask's comm backends (distributed.comm.registry).
DASK_SCHEMES = ("tcp", "tls", "inproc", "ucx", "ws", "wss")
#: Datasets built by a documented example rather than logged or simulated.
BUILTIN = {"gridworld_lattice": "offline_adp.examples.gridworld_divergence:dataset"}


# ---------------------------------------------------------------------------- the file's model
class EngineSection(ConfigModel):
    """``[engine]``: where the heavy loops run (never what they compute)."""

    kind: Literal["local", "dask"] = "local"
    address: str | None = None
    n_workers: int | None = Field(None, ge=1)
    threads_per_worker: int | None = Field(None, ge=1)
    memory_limit: str | None = None

    @field_validator("address")
    @classmethod
    def _dask_address(cls, value: str | None) -> str | None:
        """A Dask scheduler address: ``SCHEME://HOST:PORT`` with a scheme Dask speaks, or ``HOST:PORT``."""
        if value is None:
            return value
        scheme, sep, rest = value.partition("://")
        if sep and scheme not in DASK_SCHEMES:
            raise ValueError(f"unknown address scheme {scheme!r}: a Dask scheduler address is "
                             f"{'|'.join(DASK_SCHEMES)}://HOST:PORT (e.g. tcp://10.0.0.5:8786)")
        if not (rest if sep else value).strip() or any(c.isspace() for c in value):
            raise ValueError("expected a Dask scheduler address such as tcp://10.0.0.5:8786")
        return value


class DataSection(ConfigModel):
    """``[data]``: exactly one of ``inputs`` (files to ingest), ``simulate`` or ``builtin``."""

    format: Literal["mcap", "parquet"] | None = None
    inputs: list[str] | None = None
    spec: str | dict[str, Any] | None = None
    on_error: Literal["fail", "quarantine"] | None = None
    simulate: str | None = None
    demonstrations: int = Field(100, ge=0)
    exploration: int = Field(100, ge=0)
    horizon: int | None = Field(None, ge=1)
    problem_options: dict[str, Any] | None = None
    builtin: Literal[tuple(BUILTIN)] | None = None  # type: ignore[valid-type]

    @model_validator(mode="after")
    def _one_source(self) -> DataSection:
        given = [k for k in ("inputs", "simulate", "builtin") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("[data] needs exactly one of inputs = [...] (files to ingest), simulate = \"PROBLEM\" or "
                             f"builtin = one of {sorted(BUILTIN)}; got {given or 'none'}")
        if self.inputs is not None:
            if self.format is None:
                raise ValueError('[data] with inputs needs format = "mcap" or "parquet"')
            if self.spec is None:
                raise ValueError('[data] needs spec = "FILE.toml" or an inline [data.spec] table')
        if self.simulate is not None and self.simulate not in PROBLEM_NAMES:
            raise ValueError(f"[data] simulate = {self.simulate!r}: known problems are {list(PROBLEM_NAMES)}")
        return self


class FitSection(ConfigModel):
    """``[fit]``: the algorithm, its parameters (``[fit.params]``) or a config file, and the
    share of episodes held out of the fit (``holdout``, as ``offline-adp fit --holdout``)."""

    algorithm: Literal[tuple(ALGORITHMS)] = "fqi"  # type: ignore[valid-type]
    params: dict[str, Any] = Field(default_factory=dict)
    config: str | None = None
    holdout: float | None = Field(None, ge=0, lt=1, description="fraction of whole episodes kept out of the fit, "
                                  "in [0, 1): the evaluate stage reads the policy on them (default: none)")


#: ``[evaluate]``: the evaluation's settings (all but the seed: the pipeline's ``seed``),
#: one model with the CLI's ``evaluate`` flags and the Python API (:mod:`offline_adp.evaluation.settings`).
EvaluateSection = EvaluationOptions


class EmptySection(ConfigModel):
    """A table that takes no keys (``[validate]``, ``[report]``)."""


class PipelineFile(ConfigModel):
    """A pipeline file (see the module docstring). JSON Schema: ``docs/schemas/pipeline.schema.json``."""

    name: str | None = Field(None, pattern=NAME_PATTERN)
    seed: int = Field(0, ge=0, le=MAX_SEED, description="seed of the data, the fit and the evaluation")
    description: str | None = None
    data: DataSection
    validate_: EmptySection | None = Field(None, alias="validate")
    fit: FitSection
    evaluate: EvaluateSection | None = None
    report: EmptySection | None = None
    engine: EngineSection = Field(default_factory=EngineSection)


def _apply_overrides(raw: dict[str, Any], overrides: dict[str, Any]) -> None:
    """``--set data.exploration=10``: set a dotted key of the raw file (checked with it)."""
    tables = {"data": DataSection, "fit": FitSection, "evaluate": EvaluateSection, "engine": EngineSection}
    valid = [f"{t}.{k}" for t, m in tables.items() for k in m.model_fields] + ["fit.params.NAME"]
    for dotted, value in overrides.items():
        *parents, leaf = dotted.split(".")
        ok = bool(parents) and parents[0] in tables and (
            (len(parents) == 1 and leaf in tables[parents[0]].model_fields) or parents[:2] == ["fit", "params"])
        if not ok:
            raise SpecError(f"--set {dotted}: not a pipeline setting{did_you_mean([dotted], valid)}; settings are "
                            f"{', '.join(valid)}")
        node = raw
        for k in parents:
            if not isinstance(node.get(k), dict):
                node[k] = {}
            node = node[k]
        node[leaf] = value


#: The ``[data]`` keys each source reads (the others are ignored by it).
DATA_KEYS = {"inputs": ("format", "inputs", "spec", "on_error"),
             "simulate": ("simulate", "demonstrations", "exploration", "horizon", "problem_options"),
             "builtin": ("builtin",)}


def _warn_unused(data: DataSection, overrides: dict[str, Any], p: Path) -> None:
    """A ``--set data.KEY=...`` the pipeline's data source does not read: a warning saying so
    (not a silent no-op: ``data.spec`` on a pipeline that simulates its data changes nothing)."""
    import warnings

    source = next(k for k in DATA_KEYS if getattr(data, k) is not None)
    for dotted in overrides:
        table, _, key = dotted.partition(".")
        if table == "data" and key in DataSection.model_fields and key not in DATA_KEYS[source]:
            warnings.warn(f"--set {dotted}: unused, ignored: the data source of {p} is [data] {source} = "
                          f"{getattr(data, source)!r}, which reads only {', '.join(DATA_KEYS[source])}",
                          UserWarning, stacklevel=3)


def _regular_input(path: str, p: Path, pattern: str) -> str:
    """An input file of ``[data] inputs``: a regular file (a device such as ``/dev/zero``, a
    FIFO or a directory would be hashed and read forever, or not at all)."""
    import stat

    try:
        mode = Path(path).stat().st_mode
    except OSError as exc:
        raise SpecError(f"{p}: [data] inputs {pattern!r}: {path}: cannot be read ({exc.strerror or exc})") from None
    if not stat.S_ISREG(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else "a device, pipe or socket"
        raise SpecError(f"{p}: [data] inputs {pattern!r}: {path} is {kind}, not a regular file")
    return path


def load_pipeline(path: str | PathLike[str], overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Read and check a whole pipeline file before anything runs; paths become absolute
    (relative to the file). Every problem is a SpecError naming the file and key: unknown
    keys and values, a spec that does not load, fit parameters the algorithm does not
    take or values it refuses, an unknown simulator.
    """
    p = Path(path).resolve()
    raw = load_toml(p, "pipeline")
    _apply_overrides(raw, overrides or {})
    model = validate_config(PipelineFile, raw, str(p))
    _warn_unused(model.data, overrides or {}, p)
    data = model.data.model_dump(exclude_none=True)
    if "inputs" in data:
        files: list[str] = []
        for pattern in data["inputs"]:
            hits = sorted(glob.glob(str(p.parent / pattern)))
            if not hits:
                raise SpecError(f"{p}: [data] inputs pattern {pattern!r} matches no file (relative to {p.parent})")
            files += [_regular_input(h, p, pattern) for h in hits]
        data["inputs"] = files
        if isinstance(data["spec"], str):
            data["spec"] = str((p.parent / data["spec"]).resolve())
        _check_spec(data, p)
    fit = model.fit.model_dump(exclude_none=True)
    entry = get_algorithm(fit["algorithm"])
    if "config" in fit:
        from offline_adp.runs import load_config

        fit["params"] = {**load_config(p.parent / fit.pop("config"), fit["algorithm"]), **fit.get("params", {})}
    fit["params"] = entry.check_params(fit["params"], str(p), "fit.params")
    if isinstance(fit["params"].get("policy"), str):  # relative to the pipeline file, as every path in it
        fit["params"]["policy"] = str((p.parent / fit["params"]["policy"]).resolve())
    entry.check_complete(fit["params"], str(p), "fit.params")
    # checked by its model
    evaluate = model.evaluate.model_dump(exclude_none=True) if model.evaluate is not None else None
    return {"name": model.name or check_name(p.stem, f"{p}: the pipeline's name (from its file name)"),
            "seed": model.seed,
            "file": str(p), "data": data, "fit": fit, "evaluate": evaluate,
            "report": model.report is not None, "engine": model.engine.model_dump(exclude_none=True)}


def _check_spec(data: dict[str, Any], p: Path) -> None:
    """Load the ingestion spec now, so a bad spec fails before any stage runs."""
    _load_spec(data, p)


def _load_spec(data: dict[str, Any], p: str | PathLike[str]) -> Any:
    """The ``[data]`` section's ingestion spec, checked: a file path is loaded (relative
    paths inside it are relative to that file), an inline ``[data.spec]`` table is parsed
    with paths inside it relative to the pipeline file ``p``. The one loader of the
    check (:func:`load_pipeline`) and of the data stage, so both read the same spec."""
    spec, p = data["spec"], Path(p)  # both loaders read a spec file through read_config_bytes (bounded, regular)
    if data["format"] == "parquet":
        from offline_adp.ingest.spec import load_parquet_spec, parse_parquet_spec

        return load_parquet_spec(spec) if isinstance(spec, str) else parse_parquet_spec(
            spec, where=f"{p} [data.spec]")
    from offline_adp.ingest.mcap import load_mcap_spec, parse_mcap_spec

    return load_mcap_spec(spec) if isinstance(spec, str) else parse_mcap_spec(
        spec, json.dumps(spec, sort_keys=True), where=f"{p} [data.spec]", base_dir=str(p.parent))
