"""The learning benchmark in environment steps (bench/track_learning.py): the figures it derives
from a run's episodes, and one short real run of its loop on the simulator."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench import track_learning as tl

RUN = {
    # (end step, return, lap time or None)
    "episodes": [(1200, 5.0, None), (2600, 80.0, 41.0), (3500, 90.0, 38.5), (5200, 95.0, 33.0)],
    "tests": [(2000, 30.0, None), (3000, 100.0, 36.0), (4000, 60.0, None)],
}


def test_laps_come_from_training_and_test_episodes_in_step_order():
    assert tl.laps(RUN) == [(2600, 41.0), (3000, 36.0), (3500, 38.5), (5200, 33.0)]
    assert tl.first_step(RUN) == 2600
    assert tl.first_step(RUN, within=36.5) == 3000  # the first lap no slower than 36.5 s
    assert tl.first_step(RUN, within=30.0) is None
    assert tl.best_lap(RUN) == 33.0
    assert tl.best_lap({"episodes": [(10, 0.0, None)], "tests": []}) is None


def test_steps_to_a_return_read_the_test_episodes():
    assert tl.steps_to_return(RUN, 50.0) == 3000
    assert tl.steps_to_return(RUN, 200.0) is None


@pytest.mark.parametrize(
    ("values", "median"),
    [
        ([3, 1, 2], 2),
        ([4, 1, 2, 3], 2.5),
        ([None, 1, 2], 2),  # a seed that never got there counts as the slowest
        ([None, None, 1], None),  # most seeds never got there: no median
        ([None, 1, 2, 3], 2.5),
        ([None, 1, 2, None], None),
    ],
)
def test_median_counts_a_run_that_never_got_there_as_the_slowest(values, median):
    assert tl.median_or_none(values) == median


def test_every_variant_has_a_lidar_model_and_an_agent():
    from tmrl.algorithms import agent_class

    for label, (alg, source, utd) in tl.VARIANTS.items():
        assert source in ("tmrl", "demo", "class") and utd >= 1, label
        agent_class(alg)
        assert tl._lidar_model(alg) is not None


def test_a_short_run_drives_the_simulator_and_trains(capsys):
    res = tl.run(env_name="oval", label="SAC", seed=0, steps=300, utd=1, start_steps=100, eval_every=300,
                 batch_size=32, append_every=10)
    assert res["updates"] == 200  # one update per step after the random start
    assert len(res["tests"]) == 1 and res["tests"][0][0] == 300
    assert all(step <= 300 for step, _, _ in res["episodes"])
    assert "[oval SAC seed 0] step    300" in capsys.readouterr().err
