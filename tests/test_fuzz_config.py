"""Fuzz the configuration layer: any pipeline file or fit config, however mangled, loads
or fails with one of our errors naming the file; never a raw exception.

CI runs a bounded, derandomised number of examples; ``--hypothesis-profile nightly``
runs many more.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from offline_adp.errors import OfflineADPError
from offline_adp.pipeline import load_pipeline
from offline_adp.runs import load_config

N = max(300, settings.default.max_examples)  # 300 in CI, the profile's count under --hypothesis-profile nightly

GOOD = (b'name = "p"\nseed = 0\n[data]\nsimulate = "tabular"\nexploration = 3\n[fit]\nalgorithm = "fqi"\n'
        b'[fit.params]\nn_iterations = 3\nmode = "refit"\n[evaluate]\nsimulator = "tabular"\nepisodes = 5\n')

scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(allow_nan=True),
                    st.text(max_size=12), st.lists(st.integers(-3, 3), max_size=3))
keys = st.sampled_from(["name", "seed", "data", "fit", "evaluate", "engine", "report", "validate", "params",
                        "algorithm",
                        "simulate", "inputs", "format", "spec", "exploration", "horizon", "mode", "n_iterations",
                        "gamma", "simulator", "episodes", "kind", "bogus"])
tables = st.recursive(scalars, lambda inner: st.dictionaries(keys, inner, max_size=5), max_leaves=12)


def _toml(value: object) -> str:
    if value is None:
        return '""'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if value != value else ("inf" if value == float("inf") else "-inf" if value == float("-inf")
                                             else repr(value))
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"').encode("unicode_escape").decode() + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"  # type: ignore[union-attr]


@settings(max_examples=N)
@given(st.binary(max_size=40), st.integers(0, len(GOOD)), st.integers(0, 20))
def test_mangled_pipeline_bytes(tmp_path_factory, junk, at, cut):
    p = tmp_path_factory.mktemp("fz") / "p.toml"
    p.write_bytes(GOOD[:at] + junk + GOOD[at + cut:])
    try:
        load_pipeline(p)
    except OfflineADPError as e:
        assert str(p) in str(e) or "p.toml" in str(e) or "name" in str(e)


@settings(max_examples=N)
@given(st.dictionaries(keys, tables, max_size=6))
def test_random_pipeline_tables(tmp_path_factory, doc):
    p = tmp_path_factory.mktemp("fz") / "p.toml"
    p.write_text("\n".join(f"{k} = {_toml(v)}" for k, v in doc.items()) + "\n")
    try:
        load_pipeline(p)
    except OfflineADPError:
        pass


@settings(max_examples=N)
@given(st.sampled_from(["fqi", "fqe", "api", "cpi", "psdp"]), st.dictionaries(keys, tables, max_size=5))
def test_random_fit_configs(tmp_path_factory, algorithm, table):
    p = tmp_path_factory.mktemp("fz") / "fit.toml"
    p.write_text(f"{algorithm} = {_toml(table)}\n")
    try:
        load_config(p, algorithm)
    except OfflineADPError as e:
        assert "fit.toml" in str(e) or algorithm in str(e)
