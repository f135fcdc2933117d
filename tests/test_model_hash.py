"""A run records its model's sha256 (run.json ``model_sha256``) and loading checks it: a
model file re-saved with one changed leaf value is refused, naming the file (issue #43)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_adp import load_policy
from offline_adp.cli import main
from offline_adp.errors import ArtifactError

from .test_continuous_commands import lq_dataset


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("hash")
    lq_dataset(20, continuous=False).save(root / "data")
    (root / "fqi.toml").write_text("[fqi]\nn_iterations = 3\nregressor_params = {n_estimators = 5}\n")
    assert main(["fit", str(root / "data"), "--config", str(root / "fqi.toml"), "--out", str(root / "run"), "-q"]) == 0
    return root / "run"


def test_the_run_records_its_model_and_loads_it(run):
    recorded = json.loads((run / "run.json").read_text())["model_sha256"]
    assert set(recorded) == {"q.json", "q.npz"} and all(len(h) == 64 for h in recorded.values())
    assert load_policy(run).act(np.zeros((2, 1))).shape == (2,)


def test_a_model_resaved_with_one_changed_leaf_is_refused(run, tmp_path, capsys):
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    with np.load(copy / "model" / "q.npz") as z:
        arrays = {k: z[k].copy() for k in z.files}
    key = next(k for k in arrays if k.endswith("value_table"))  # the leaf values
    arrays[key].flat[0] += 1.0  # a valid file with one leaf value changed
    np.savez_compressed(copy / "model" / "q.npz", **arrays)
    with pytest.raises(ArtifactError, match=r"q\.npz: its sha256 differs"):
        load_policy(copy)
    assert main(["evaluate", str(copy), "--simulator", "none", "--fqe-bootstrap", "0", "--bootstrap", "0", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sha256 differs" in err[0]


def test_a_policy_file_added_to_the_model_is_refused(run, tmp_path):
    import shutil

    from offline_adp.artifacts import save_policy
    from offline_adp.policies import UniformPolicy

    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    save_policy(UniformPolicy(5), copy / "model")  # loading would prefer policy.json
    with pytest.raises(ArtifactError, match=r"policy\.json: not among the model files"):
        load_policy(copy)
