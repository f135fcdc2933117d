"""See the policy on the log: ``offline-adp annotate RUN_DIR --log FILE.mcap --out annotated.mcap``.

The log is ingested with the run's MCAP ingestion spec (the spec stored in the run's
dataset provenance, or ``spec=``), which gives the logged steps with their log times
(``t_ns``). At each step the run's policy is evaluated and four JSON topics (with JSON
schemas, so Foxglove plots them on the log's timeline) are added next to every message
of the log, stamped with the log time of the message that made the step (its
``src_log_time``, integer nanoseconds, exactly; ``t_ns`` is the step's header stamp):

``/offline_adp/action``
    the policy's action (value and index) vs the logged one, and whether they agree;
``/offline_adp/q_gap``
    ``Q(x, a_logged) - Q(x, a_policy)`` (cost units; >= 0 for a greedy policy: how much
    worse the logged action is by the policy's own Q), null when the policy has no Q;
``/offline_adp/density_ratio``
    the per-step importance ratio ``pi(a_logged | x) / pi_b(a_logged | x)``;
``/offline_adp/support``
    ``out_of_support``: the behaviour policy (almost) never takes the policy's action
    there, ``pi_b(a_policy | x) < threshold`` (the support check of the evaluation).

``pi_b`` uses the logged propensities when the ingested log has them, else a classifier
fitted on the run's dataset (or on the log when that is not found) and evaluated at
the log's states, with probabilities clipped to ``[1e-3, 1]`` as in
:mod:`offline_adp.evaluation.behaviour`.

A policy over continuous commands (a cmd_vel-style log) gets three topics instead:
``/offline_adp/command`` (its command vs the logged one, and their difference),
``/offline_adp/q_gap`` (``Q(x, u_logged) - Q(x, u_policy)`` by its own Q; null for a
distilled policy, which has none) and ``/offline_adp/support`` (the evaluation's command
support: the distance from its command to the commands logged at the nearest states of the
run's dataset, against the logged commands' own radius; :func:`annotate_commands`).
"""

from __future__ import annotations

import json
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np

from offline_adp.errors import (
    IngestError,
    OfflineADPError,
    OutputExistsError,
    SpecError,
    WriteError,
)
from offline_adp.progress import get_logger

log = get_logger(__name__)

PREFIX = "/offline_adp"
CLIP = 1e-3
THRESHOLD = 0.01

_num = {"type": ["number", "null"]}
_T = {t: {"type": t} for t in ("number", "integer", "boolean", "string")}
_NUMBERS, _NAMES = {"type": "array", "items": _T["number"]}, {"type": "array", "items": _T["string"]}


def _schema(title: str, description: str, **props: Any) -> dict[str, Any]:
    """The JSON schema of one annotation topic: its fields after the step's ``episode_id`` and ``step``."""
    return {"title": f"offline_adp.{title}", "type": "object", "description": description,
            "properties": {"episode_id": _T["string"], "step": _T["integer"], **props}}


SCHEMAS: dict[str, dict[str, Any]] = {
    "action": _schema("PolicyAction", "The run's policy action vs the logged action at a logged step.",
                      policy_action=_NUMBERS, policy_action_index=_T["integer"], logged_action=_NUMBERS,
                      logged_action_index=_T["integer"], agree=_T["boolean"], action_dims=_NAMES),
    "q_gap": _schema("QGap", "Q(x, logged action) - Q(x, policy action), in cost units (null without a Q-function).",
                     q_gap=_num, q_policy=_num, q_logged=_num),
    "density_ratio": _schema("DensityRatio",
                             "Per-step importance ratio pi(logged action | x) / pi_b(logged action | x).",
                             ratio=_T["number"], policy_prob=_T["number"], behaviour_prob=_T["number"],
                             behaviour_source=_T["string"]),
    "support": _schema("Support",
                       "out_of_support: the behaviour policy takes the policy's action with probability < threshold.",
                       out_of_support=_T["boolean"], behaviour_prob_of_policy_action=_T["number"],
                       threshold=_T["number"]),
}


def _spec_for(run_dataset: Path | None, spec: Any) -> Any:
    from offline_adp.ingest.mcap import load_mcap_spec

    if spec is not None:
        if not isinstance(spec, str | PathLike):
            return spec
        return load_mcap_spec(spec)  # a regular file of bounded size (it reads through read_config_bytes)
    raw = None
    if run_dataset is not None:
        from offline_adp.data.io import read_info

        info = read_info(run_dataset)
        raw = (info.get("provenance") or {}).get("spec")
    if not raw:
        raise SpecError("the run's dataset does not record an MCAP ingestion spec (it was not ingested from MCAP); "
                        "pass --spec FILE.toml")
    try:  # the spec as the run's dataset recorded it
        from offline_adp.ingest.mcap import parse_mcap_spec
    except ImportError as exc:  # pragma: no cover - depends on the ingestion module's layout
        raise SpecError("cannot rebuild the run's MCAP spec here; pass --spec FILE.toml") from exc
    return parse_mcap_spec(raw, where=f"{run_dataset}/meta/info.json provenance.spec", base_dir=str(run_dataset))


def _behaviour_probs(obs: np.ndarray, fit_obs: np.ndarray, fit_action: np.ndarray, n_actions: int) -> np.ndarray:
    """pi_b(. | x) at ``obs`` from a classifier fitted on (fit_obs, fit_action), clipped."""
    from offline_adp.regressors import make_classifier

    if len(np.unique(fit_action)) == 1:
        probs = np.zeros((len(obs), n_actions))
        probs[:, int(fit_action[0])] = 1.0
    else:
        clf = make_classifier("lightgbm").fit(fit_obs, fit_action)
        probs = np.zeros((len(obs), n_actions))
        probs[:, np.asarray(clf.classes_, dtype=np.int64)] = clf.predict_proba(obs)
    probs = np.maximum(probs, CLIP)
    return probs / probs.sum(axis=1, keepdims=True)


def annotate_steps(policy: Any, log_ds: Any, fit_ds: Any = None) -> dict[str, Any]:
    """The annotation values at every step of ``log_ds`` (arrays, one row per step)."""
    a = log_ds.arrays()
    obs, step, logged = a.obs, a.step, a.action.astype(np.int64)
    n, A = len(obs), policy.n_actions
    idx = np.asarray(policy.act_index(obs, step), dtype=np.int64)
    pi_probs = policy.probabilities(obs, step)
    rows = np.arange(n)
    q = getattr(policy, "q", None)
    qv = q.values(obs, step) if q is not None and hasattr(q, "values") else None
    src = fit_ds if fit_ds is not None else log_ds
    fa = src.arrays()
    b_all = _behaviour_probs(obs, fa.obs, fa.action, A)
    b_logged = b_all[rows, logged]
    source = "estimated" if fit_ds is not None else "estimated (from the log)"
    if a.behavior_prob is not None and np.isfinite(a.behavior_prob).all():
        b_logged, source = np.maximum(a.behavior_prob, CLIP), "logged"
    return {
        "policy_index": idx, "logged_index": logged,
        "q_policy": None if qv is None else qv[rows, idx], "q_logged": None if qv is None else qv[rows, logged],
        "policy_prob": pi_probs[rows, logged], "behaviour_prob": b_logged,
        "ratio": pi_probs[rows, logged] / b_logged,
        "behaviour_prob_of_policy_action": b_all[rows, idx],
        "out_of_support": b_all[rows, idx] < THRESHOLD,
        "behaviour_source": source,
    }


def _f(x: Any) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


def _action_topics(policy: Any, log_ds: Any, fit_ds: Any, base: list[dict[str, Any]]) -> tuple[dict, dict]:
    """The four topics of a policy over an action table, one message a step, and the summary's numbers."""
    v = annotate_steps(policy, log_ds, fit_ds)
    values, dims = policy.signature.action_table.values, list(policy.signature.action_table.dims)
    msgs: dict[str, list[dict[str, Any]]] = {name: [] for name in ("action", "q_gap", "density_ratio", "support")}
    for i, b in enumerate(base):  # one message per step and topic (the output's size, not a data loop)
        pi_i, lg_i = int(v["policy_index"][i]), int(v["logged_index"][i])
        qp = None if v["q_policy"] is None else _f(v["q_policy"][i])
        ql = None if v["q_logged"] is None else _f(v["q_logged"][i])
        msgs["action"].append({**b, "policy_action": values[pi_i].tolist(), "policy_action_index": pi_i,
                               "logged_action": values[lg_i].tolist(), "logged_action_index": lg_i,
                               "agree": pi_i == lg_i, "action_dims": dims})
        msgs["q_gap"].append({**b, "q_gap": None if qp is None or ql is None else ql - qp, "q_policy": qp,
                              "q_logged": ql})
        msgs["density_ratio"].append({**b, "ratio": float(v["ratio"][i]), "policy_prob": float(v["policy_prob"][i]),
                                      "behaviour_prob": float(v["behaviour_prob"][i]),
                                      "behaviour_source": v["behaviour_source"]})
        msgs["support"].append({**b, "out_of_support": bool(v["out_of_support"][i]),
                                "behaviour_prob_of_policy_action": float(v["behaviour_prob_of_policy_action"][i]),
                                "threshold": THRESHOLD})
    n = len(base)
    summary = {"agreement": float(np.mean(v["policy_index"] == v["logged_index"])) if n else None,
               "out_of_support": int(np.sum(v["out_of_support"])), "behaviour": v["behaviour_source"]}
    return {k: (SCHEMAS[k], m) for k, m in msgs.items()}, summary


class _GivenCommands:
    """One candidate command per row, given (the logged ones): Q read at ``(x_i, u_i)``."""

    k = n_slots = 1

    def __init__(self, u: np.ndarray) -> None:
        self.u = u

    def __call__(self, phi: np.ndarray) -> np.ndarray:
        return self.u.reshape(len(phi), 1, -1)


def _q_at(q: Any, obs: np.ndarray, t: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``Q(x_i, u_i)`` of a Q-function over commands (a time-indexed one: its step's)."""
    from offline_adp.qfunctions import with_candidates

    if not hasattr(q, "qs"):
        return with_candidates(q, _GivenCommands(u)).values(obs)[:, 0]
    out, T = np.empty(len(obs)), len(q.qs)
    for s in np.unique(t):
        rows = t == s
        out[rows] = with_candidates(q.qs[min(int(s), T - 1)], _GivenCommands(u[rows])).values(obs[rows])[:, 0]
    return out


def annotate_commands(policy: Any, log_ds: Any, fit_ds: Any = None) -> dict[str, Any]:
    """The annotation values of a continuous policy at every step of ``log_ds``: its command
    and the logged one; ``Q(x, u_logged) - Q(x, u_policy)`` by the policy's own Q where it
    has one (a greedy policy; a distilled one has none); and the command support of the
    evaluation (:func:`~offline_adp.qfunctions.command_support_distances`): the policy's
    command against the commands logged at the nearest states of the run's dataset (else of
    the log), unsupported beyond the logged commands' own 95% quantile."""
    from offline_adp.qfunctions import command_encoder, command_support_distances

    a, u_log = log_ds.arrays(), log_ds.commands()
    u_pi = np.asarray(policy.commands(a.obs, a.step), np.float64).reshape(len(a.obs), -1)
    q = getattr(policy, "q", None)
    with_q = q is not None and command_encoder(q) is not None
    src = fit_ds if fit_ds is not None and fit_ds.commands() is not None else log_ds
    sa = src.arrays()
    query = sa.obs if src is log_ds else a.obs
    dist, radius = command_support_distances(sa.obs, src.commands(), src.info.action_table.bounds(), query, u_pi)
    return {"policy": u_pi, "logged": u_log, "q_policy": _q_at(q, a.obs, a.step, u_pi) if with_q else None,
            "q_logged": _q_at(q, a.obs, a.step, u_log) if with_q else None, "distance": dist, "radius": radius,
            "source": "the run's dataset" if src is fit_ds else "the log (the run's dataset was not found)"}


COMMAND_SCHEMAS: dict[str, dict[str, Any]] = {
    "command": _schema("PolicyCommand",
                       "The run's policy command vs the logged command at a logged step (and policy - logged).",
                       policy_command=_NUMBERS, logged_command=_NUMBERS, difference=_NUMBERS, command_dims=_NAMES),
    "q_gap": SCHEMAS["q_gap"],
    "support": _schema("CommandSupport",
                       "out_of_support: the policy's command is farther from the commands logged at the nearest "
                       "logged states than the logged commands are from their neighbours' (distance > radius).",
                       out_of_support=_T["boolean"], distance=_T["number"], radius=_T["number"],
                       compared_with=_T["string"]),
}


def _command_topics(policy: Any, log_ds: Any, fit_ds: Any, base: list[dict[str, Any]]) -> tuple[dict, dict]:
    """The three topics of a continuous policy, one message a step, and the summary's numbers."""
    v = annotate_commands(policy, log_ds, fit_ds)
    dims = list(policy.signature.action_table.dims)
    msgs: dict[str, list[dict[str, Any]]] = {name: [] for name in COMMAND_SCHEMAS}
    for i, b in enumerate(base):  # one message per step and topic (the output's size, not a data loop)
        up, ul = v["policy"][i], v["logged"][i]
        qp = None if v["q_policy"] is None else _f(v["q_policy"][i])
        ql = None if v["q_logged"] is None else _f(v["q_logged"][i])
        msgs["command"].append({**b, "policy_command": up.tolist(), "logged_command": ul.tolist(),
                                "difference": (up - ul).tolist(), "command_dims": dims})
        msgs["q_gap"].append({**b, "q_gap": None if qp is None or ql is None else ql - qp, "q_policy": qp,
                              "q_logged": ql})
        msgs["support"].append({**b, "out_of_support": bool(v["distance"][i] > v["radius"]),
                                "distance": float(v["distance"][i]), "radius": v["radius"],
                                "compared_with": v["source"]})
    summary = {"agreement": None, "out_of_support": int(np.sum(v["distance"] > v["radius"])),
               "behaviour": f"commands logged near each state in {v['source']}"}
    return {k: (COMMAND_SCHEMAS[k], m) for k, m in msgs.items()}, summary


def annotate_mcap(run_dir: str | PathLike[str], log_file: str | PathLike[str], out: str | PathLike[str], *,
                  spec: Any = None, dataset: str | PathLike[str] | None = None,
                  overwrite: bool = False) -> dict[str, Any]:
    """Write ``out``: every message of ``log_file`` plus the annotation topics (see module
    docstring). Returns a summary (steps, agreement, out-of-support count). The output is
    locked for the whole command (a second writer fails at once) and written to a
    temporary renamed into place, so it is one run's output or the file it was before."""
    from offline_adp.data.files import clean_stale_temporaries, locked_directory
    from offline_adp.data.rundir import check_outside_run

    out = Path(out)
    if out.is_dir() and not out.is_symlink():
        raise WriteError(f"--out {out} is a directory; name the annotated MCAP file to write")
    if Path(out).resolve() == Path(log_file).resolve():
        raise OutputExistsError(f"--out {out} is the input log; write the annotated copy elsewhere")
    check_outside_run(run_dir, out)
    with locked_directory(out, what="annotated MCAP"):
        if out.exists() and not overwrite:
            raise OutputExistsError(f"{out} already exists; pass --overwrite to replace it")
        clean_stale_temporaries(out)
        topics, numbers, stamp = _annotations(run_dir, log_file, spec, dataset)
        n_copied = _write_annotated(log_file, out, topics, stamp)
    summary = {"out": str(out), "messages_copied": n_copied, "steps": int(len(stamp)), **numbers,
               "topics": [f"{PREFIX}/{k}" for k in topics]}
    log.info("annotated %s -> %s: %d steps, agreement %s", log_file, out, summary["steps"], summary["agreement"])
    return summary


def _annotations(run_dir: Any, log_file: Any, spec: Any, dataset: Any) -> tuple[dict, dict, np.ndarray]:
    """The log ingested with the run's spec, checked against the policy, and its topics."""
    from offline_adp.deploy import load_run_policy, run_dataset
    from offline_adp.errors import IncompatibleError
    from offline_adp.ingest.mcap import ingest_mcap

    policy = load_run_policy(run_dir, dataset)
    continuous = bool(getattr(policy, "continuous", False))
    try:
        ds_path: Path | None = run_dataset(run_dir, dataset)
    except OfflineADPError:
        ds_path = None
    mspec = _spec_for(ds_path, spec)
    log_ds, _summary = ingest_mcap([log_file], mspec)
    if "t_ns" not in log_ds.table.column_names:
        raise IngestError(f"{log_file}: the ingested steps have no log times (t_ns)")
    sig = policy.signature
    if log_ds.feature_names != list(sig.feature_names):
        raise IncompatibleError(f"{log_file}: the spec gives features {log_ds.feature_names}, the policy reads "
                                f"{list(sig.feature_names)}; pass the spec the run's dataset was ingested "
                                "with (--spec)")
    at = log_ds.info.action_table
    if continuous and (list(at.dims) != list(sig.action_table.dims) or log_ds.commands() is None):
        raise IncompatibleError(f"{log_file}: the spec gives the commands {list(at.dims)}"
                                + ("" if log_ds.commands() is not None else " without their exact values")
                                + f", the policy commands {list(sig.action_table.dims)}; pass the spec the run's "
                                "dataset was ingested with (--spec)")
    if not continuous and not np.array_equal(at.values, sig.action_table.values):
        raise IncompatibleError(f"{log_file}: the spec's action table {at.values.ravel().tolist()} "
                                f"differs from the policy's {sig.action_table.values.ravel().tolist()}")
    fit_ds = None
    if ds_path is not None:
        from offline_adp.data.dataset import read_dataset

        fit_ds = read_dataset(ds_path)
    t_ns = log_ds.column("t_ns").astype(np.int64)
    # the annotated message's own log_time (integer ns), not the step's header stamp (t_ns),
    # which the transport delay puts before it
    stamp = log_ds.column("src_log_time").astype(np.int64) if "src_log_time" in log_ds.table.column_names else t_ns
    base = [{"episode_id": e, "step": int(k)} for e, k in zip(log_ds.column("episode_id").astype(str).tolist(),
                                                             log_ds.column("step").astype(np.int64).tolist(),
                                                             strict=True)]
    topics, numbers = (_command_topics if continuous else _action_topics)(policy, log_ds, fit_ds, base)
    return topics, numbers, stamp


def _write_annotated(log_file: Any, out: Path, topics: dict[str, tuple[dict, list]], stamp: np.ndarray) -> int:
    """Copy every message of ``log_file`` into ``out`` (through a temporary) and add
    ``topics``, one message a step at ``stamp``; returns the messages copied."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    from offline_adp.data.files import atomic_file

    n_copied = 0
    try:
        with atomic_file(out, what="annotated MCAP", lock=False) as tmp, open(log_file, "rb") as fin, \
                open(tmp, "wb") as fout:
            reader = make_reader(fin)
            w = Writer(fout, compression=CompressionType.ZSTD)
            w.start(profile=reader.get_header().profile, library="offline_adp annotate")
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            for schema, channel, msg in reader.iter_messages(log_time_order=False):
                if schema is not None and schema.id not in schema_ids:
                    schema_ids[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
                if channel.id not in channel_ids:
                    channel_ids[channel.id] = w.register_channel(channel.topic, channel.message_encoding,
                                                                 schema_ids.get(channel.schema_id, 0),
                                                                 dict(channel.metadata))
                w.add_message(channel_ids[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
                n_copied += 1
            for name, (schema, msgs) in topics.items():
                sid = w.register_schema(schema["title"], "jsonschema", json.dumps(schema).encode())
                chan = w.register_channel(f"{PREFIX}/{name}", "json", sid)
                for i, m in enumerate(msgs):
                    w.add_message(chan, int(stamp[i]), json.dumps(m).encode(), int(stamp[i]), i)
            w.finish()
    except Exception as exc:  # the temporary is gone (atomic_file); say what failed
        if isinstance(exc, OfflineADPError):
            raise
        if isinstance(exc, OSError) and (exc.filename is None or Path(exc.filename) != Path(log_file)):
            from offline_adp.errors import os_error_message

            raise WriteError(os_error_message(exc, out)) from None
        raise IngestError(f"{log_file}: cannot copy the log's messages ({type(exc).__name__}: {exc})") from exc
    return n_copied
