"""A dataset as a user's raw transition table (Parquet or CSV) plus the spec that ingests it.

Column names are those a user's logger would write (``episode``, ``step``,
``timestamp_ns``, the feature names, ``next_<feature>``, the action's value or label,
``cost``, ``terminated``, ``truncated``, ``source``, ``behavior_prob``), not the dataset
format's, so ``ingest parquet`` with the written spec is a real round trip.
"""

from __future__ import annotations

from os import PathLike
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from offline_adp.data import schema as S
from offline_adp.data.dataset import TransitionDataset


def raw_table(ds: TransitionDataset) -> tuple[pa.Table, str]:
    """The raw table and the TOML spec text that maps it back to ``ds``'s format."""
    t = ds.table
    at = ds.info.action_table
    one_dim = len(at.dims) == 1
    a = t.column(S.ACTION).to_numpy()
    exact = ds.commands() if at.continuous else None  # continuous commands: one column per component, as logged
    action = at.values[a, 0] if one_dim else np.asarray(at.names, dtype=object)[a]
    cols: dict[str, object] = {"episode": t.column(S.EPISODE_ID), "step": t.column(S.STEP)}
    if S.T_NS in t.column_names:
        cols["timestamp_ns"] = t.column(S.T_NS)
    names = ds.feature_names
    for nm in names:
        cols[nm] = t.column(S.obs_column(nm))
    if exact is not None:
        for j, d in enumerate(at.dims):
            cols[f"{d}_command"] = exact[:, j]
    else:
        cols["command" if one_dim else "action"] = pa.array(action)
    cols["cost"] = t.column(S.COST)
    for nm in names:
        cols[f"next_{nm}"] = t.column(S.next_obs_column(nm))
    cols["terminated"] = t.column(S.TERMINATED)
    cols["truncated"] = t.column(S.TRUNCATED)
    cols["source"] = t.column(S.SOURCE).cast(pa.string())
    if ds.has_propensities:
        cols["behavior_prob"] = t.column(S.BEHAVIOR_PROB)
    table = pa.table(cols)

    q = lambda xs: "[" + ", ".join(f'"{x}"' for x in xs) + "]"  # noqa: E731
    units = ", ".join(f'{f.name} = "{f.unit}"' for f in ds.info.features if f.unit)
    if exact is not None:
        bound = lambda b: "[" + ", ".join(repr(float(x)) for x in b) + "]"  # noqa: E731
        action_spec = (f"columns = {q([f'{d}_command' for d in at.dims])}\ntype = \"continuous\"\nnames = "
                       f"{q(at.dims)}\n"
                       + (f"units = {q(at.units)}\n" if at.units else "")
                       + (f"low = {bound(at.low)}\n" if at.low is not None else "")
                       + (f"high = {bound(at.high)}\n" if at.high is not None else ""))
    elif one_dim:
        vals = ", ".join(repr(float(v)) for v in at.values[:, 0])
        action_spec = (
            f'column = "command"\ntype = "discrete"\nvalues = [{vals}]\nnames = {q(at.names)}\n'
            f'dim = "{at.dims[0]}"\n' + (f'unit = "{at.units[0]}"\n' if at.units else "")
        )
    else:
        vecs = ", ".join("[" + ", ".join(repr(float(x)) for x in v) + "]" for v in at.values)
        action_spec = (
            f'column = "action"\ntype = "discrete"\nvalues = {q(at.names)}\n'
            f"vectors = [{vecs}]\ndims = {q(at.dims)}\n"
        )
    hints = []
    if ds.info.gamma is not None:
        hints.append(f"gamma = {ds.info.gamma!r}")
    if ds.info.horizon is not None:
        hints.append(f"horizon = {ds.info.horizon}")
    spec = f"""# Ingestion spec for the raw table written by `offline-adp simulate {ds.info.problem or ''}`
kind = "transitions"
name = "{ds.info.name}"

[episode]
id = "episode"
step = "step"
{'time = "timestamp_ns"' + chr(10) + 'time_unit = "ns"' if S.T_NS in t.column_names else ''}

[observations]
columns = {q(names)}
next_columns = {q(['next_' + n for n in names])}
units = {{ {units} }}

[action]
{action_spec}
[cost]
column = "cost"

[end]
terminated = "terminated"
truncated = "truncated"

[source]
column = "source"
{'''
[propensity]
column = "behavior_prob"
''' if ds.has_propensities else ''}
[hints]
{chr(10).join(hints)}
"""
    return table, spec


def write_raw(ds: TransitionDataset, path: str | PathLike[str], fmt: str = "parquet") -> tuple[Path, Path]:
    """Write the raw table (``.parquet`` or ``.csv``) and ``<stem>.spec.toml`` next to it."""
    from offline_adp.data.files import atomic_file, atomic_write_text

    path = Path(path)
    table, spec = raw_table(ds)
    with atomic_file(path, what="table") as tmp:  # temporary removed whatever happens
        if fmt == "csv":
            pacsv.write_csv(table, tmp)
        else:
            pq.write_table(table, tmp, compression="zstd")
    spec_path = path.with_name(path.name.split(".")[0] + ".spec.toml")
    atomic_write_text(spec_path, spec, what="spec")
    return path, spec_path
