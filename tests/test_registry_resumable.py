"""Which algorithms resume is a property of their registry entry, asked by the fit runner,
never a list of names in the runner."""

from __future__ import annotations

import dataclasses

import pytest

from offline_adp.algorithms import registry
from offline_adp.errors import OfflineADPError
from offline_adp.runs import fit_run


def test_resumable_algorithms_are_the_entries_flagged_resumable():
    names = registry.resumable_algorithms()
    assert names == [n for n, e in registry.ALGORITHMS.items() if e.resumable]
    assert "fqi" in names and "psdp" not in names
    for n in names:  # a resumable entry's estimator iterates (the runner checkpoints its fit_iter)
        assert callable(getattr(registry.get_algorithm(n).estimator_class(), "fit_iter", None)), n


def test_resume_refusal_lists_what_the_registry_says(tmp_path, monkeypatch):
    with pytest.raises(OfflineADPError, match=r"--resume is for \['fqi'\] runs; psdp runs as a whole"):
        fit_run(tmp_path / "ds", tmp_path / "run", algorithm="psdp", resume=True)
    # flag another entry resumable: the runner's message follows the registry
    monkeypatch.setitem(registry.ALGORITHMS, "fqe", dataclasses.replace(registry.FQE, resumable=True))
    with pytest.raises(OfflineADPError, match=r"--resume is for \['fqi', 'fqe'\] runs; psdp runs as a whole"):
        fit_run(tmp_path / "ds", tmp_path / "run", algorithm="psdp", resume=True)
