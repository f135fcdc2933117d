"""progress.PhaseLines: an evaluation phase's counted lines with an ETA (issue #42)."""

from __future__ import annotations

from offline_adp.progress import PhaseLines


def test_quarters_with_the_time_left_scaled_from_the_time_so_far():
    said: list[str] = []
    now = [0.0]
    lines = PhaseLines(said.append, "FQE bootstrap", 200, lines=4, clock=lambda: now[0])
    for _ in range(200):
        now[0] += 0.05  # each part takes 0.05 s
        lines(7)  # a task map's on_done passes the item's index: counted, not read
    assert said == ["FQE bootstrap 50/200, ETA 7.5 s", "FQE bootstrap 100/200, ETA 5.0 s",
                    "FQE bootstrap 150/200, ETA 2.5 s", "FQE bootstrap 200/200 in 10 s"]


def test_two_lines_by_default():
    said: list[str] = []
    lines = PhaseLines(said.append, "model rollouts: step", 200, clock=lambda: 1.0)
    for _ in range(200):
        lines()
    assert said == ["model rollouts: step 100/200, ETA 0.0 s", "model rollouts: step 200/200 in 0.0 s"]


def test_short_phases():
    said: list[str] = []
    lines = PhaseLines(said.append, "fold", 2, clock=lambda: 0.0)
    lines()
    lines()
    assert said == ["fold 1/2, ETA 0.0 s", "fold 2/2 in 0.0 s"]
    one: list[str] = []
    PhaseLines(one.append, "x", 1)()
    assert one == []  # one part: nothing to count
