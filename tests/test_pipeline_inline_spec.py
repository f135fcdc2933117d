"""A pipeline's inline ``[data.spec]`` table is read by one loader for the check and the
data stage: relative paths inside it are relative to the pipeline file whatever the
working directory, and an inline Parquet spec ingests like the same spec in a file."""

from __future__ import annotations

import json
from pathlib import Path

from offline_adp.data.dataset import read_dataset
from offline_adp.pipeline import load_pipeline, run_pipeline
from offline_adp.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
MCAP_SPEC = ROOT / "data" / "specs" / "path_tracking_mcap.toml"
#: Only the data stage matters here: the smallest fit that completes.
TINY_FIT = {"fit.params.n_iterations": 2, "fit.params.regressor_params": {"n_estimators": 3}}


def _inline(spec_text: str) -> str:
    """A spec file's text as the ``[data.spec]`` table of a pipeline file."""
    out = ["[data.spec]"]
    for line in spec_text.splitlines():
        if line.startswith("[["):
            line = "[[data.spec." + line[2:]
        elif line.startswith("["):
            line = "[data.spec." + line[1:]
        out.append(line)
    return "\n".join(out) + "\n"


def _quiet(_msg: str) -> None:
    pass


def test_inline_mcap_spec_paths_are_relative_to_the_pipeline_file(tmp_path, monkeypatch):
    from offline_adp.simulate.mcap_writer import write_mcap

    ds = simulate("path_tracking", 2, 2, seed=4, horizon=20)
    conf = tmp_path / "conf"
    files = write_mcap(ds, conf / "logs", encoding="json", seed=1)
    assert files
    spec = _inline(MCAP_SPEC.read_text()).replace("[data.spec.clock]",
                                                   '[data.spec.sources]\nfiles = ["logs/*.mcap"]\n\n[data.spec.clock]')
    # no inputs: the recordings are the spec's [sources] files, relative to this file
    (conf / "pipe.toml").write_text('name = "inline"\n[data]\nformat = "mcap"\ninputs = []\n\n' + spec + "\n[fit]\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    load_pipeline(conf / "pipe.toml")  # the check
    run = run_pipeline(conf / "pipe.toml", out=tmp_path / "run", say=_quiet, overrides=TINY_FIT)  # the run
    man = json.loads((run / "manifest.json").read_text())
    assert man["stages"]["data"]["status"] == "completed", man["stages"]
    back = read_dataset(run / "dataset")
    assert sorted(back.source_counts()) == ["demonstration", "exploration"]
    assert len(back.episode_ids) == len(ds.episode_ids) == 4


def test_inline_parquet_spec_ingests_like_the_spec_file(tmp_path, monkeypatch):
    from offline_adp.simulate.raw import write_raw

    ds = simulate("gridworld", 3, 3, seed=2, horizon=25)
    conf = tmp_path / "conf"
    conf.mkdir()
    _raw, spec_path = write_raw(ds, conf / "raw.parquet")
    (conf / "pipe.toml").write_text('name = "inline_pq"\n[data]\nformat = "parquet"\ninputs = ["raw.parquet"]\n\n'
                                    + _inline(spec_path.read_text()) + "\n[fit]\n")
    monkeypatch.chdir(tmp_path)
    run = run_pipeline(conf / "pipe.toml", out=tmp_path / "run", say=_quiet, overrides=TINY_FIT)
    assert read_dataset(run / "dataset").fingerprint() == ds.fingerprint()
