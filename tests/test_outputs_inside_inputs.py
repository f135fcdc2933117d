"""No command writes into what it reads (a crash audit, 2026-11-29): `export --out
RUN/model/q.npz --overwrite`, `convert DS --out DS/meta/info.json --overwrite` and
`fit DS --out DS` exited 0 and broke the run or dataset; `run --out DS` refused only after
writing config.json and manifest.json into the dataset. Each is refused before anything is
written now, and what it would have broken still loads."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from offline_adp.cli import main
from offline_adp.data.dataset import read_dataset
from offline_adp.runs import fit_run
from offline_adp.simulate import simulate


def _digest(d: Path) -> str:
    h = hashlib.sha256()
    for f in sorted(p for p in d.rglob("*") if p.is_file()):
        h.update(str(f.relative_to(d)).encode() + f.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    base = tmp_path_factory.mktemp("inside")
    simulate("gridworld", 3, 6, seed=0, horizon=20).save(base / "ds")
    simulate("gridworld", 2, 2, seed=1, horizon=20).save(base / "other")
    fit_run(base / "ds", base / "run", params={"n_iterations": 2, "regressor_params": {"n_estimators": 3}})
    return base


def test_export_into_its_run_is_refused(made, capsys):
    pytest.importorskip("onnx")
    before = _digest(made / "run")
    for out in (made / "run" / "model" / "q.npz", made / "run" / "run.json", made / "run" / "model" / "new.onnx",
                made / "run" / "model" / "x" / "y.onnx"):
        assert main(["export", str(made / "run"), "--out", str(out), "--overwrite"]) == 2
        assert "would replace or change the files of the run" in capsys.readouterr().err
    assert _digest(made / "run") == before and not (made / "run" / "model" / "x").exists()  # nothing made either
    # a new file beside the run's own is not the run's: allowed (it was before)
    assert main(["export", str(made / "run"), "--out", str(made / "run" / "policy.onnx")]) == 0
    (made / "run" / "policy.onnx").unlink()


def test_convert_into_its_source_is_refused(made, capsys):
    before = _digest(made / "ds")
    assert main(["convert", str(made / "ds"), "--to", "d4rl", "--out", str(made / "ds" / "meta" / "info.json"),
                 "--overwrite"]) == 2
    assert "lies inside the dataset directory" in capsys.readouterr().err
    assert _digest(made / "ds") == before and len(read_dataset(made / "ds")) > 0


def test_fit_into_a_dataset_is_refused(made, capsys):
    before, other = _digest(made / "ds"), _digest(made / "other")
    assert main(["fit", str(made / "ds"), "--out", str(made / "ds")]) == 2
    assert "is the input dataset" in capsys.readouterr().err
    assert main(["fit", str(made / "ds"), "--out", str(made / "other")]) == 2
    assert "is a dataset directory" in capsys.readouterr().err
    assert main(["fit", str(made / "ds"), "--out", str(made / "ds" / "run")]) == 2
    assert "lies inside the dataset directory" in capsys.readouterr().err
    assert (_digest(made / "ds"), _digest(made / "other")) == (before, other)


def test_a_run_holding_its_dataset_still_fits(made, tmp_path):
    """`fit RUN/dataset --out RUN` adds files to RUN (a layout load_policy knows): not refused."""
    import shutil

    shutil.copytree(made / "ds", tmp_path / "r" / "dataset")
    before = _digest(tmp_path / "r" / "dataset")
    assert main(["fit", str(tmp_path / "r" / "dataset"), "--out", str(tmp_path / "r"), "-q"]) == 0
    assert _digest(tmp_path / "r" / "dataset") == before and (tmp_path / "r" / "model").is_dir()


def test_a_pipeline_into_a_dataset_writes_nothing_there(made, tmp_path, capsys):
    pl = tmp_path / "p.toml"
    pl.write_text('name = "p"\n[data]\nsimulate = "gridworld"\ndemonstrations = 1\nexploration = 1\nhorizon = 5\n'
                  '[fit]\nalgorithm = "fqi"\n')
    before = _digest(made / "other")
    assert main(["run", str(pl), "--out", str(made / "other")]) == 2
    assert "lies inside the dataset directory" in capsys.readouterr().err
    assert _digest(made / "other") == before
