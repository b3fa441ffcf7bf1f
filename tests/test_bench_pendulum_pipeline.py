"""How ``python -m bench pendulum_pipeline`` counts the steps to the threshold: snapshots of the
trainer's weights file on a grid of environment steps, and the first of them that passes.

Evaluations come every 2 s at least, so a side that steps faster takes more steps between the
moment its weights first pass and the evaluation that sees it; the snapshots take that speed out
of the steps and updates counted. Real files in a temporary folder; the test return is a stand-in
for the evaluation episodes (the selection logic is what is tested here).
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.pendulum_pipeline import THRESHOLD, _Snapshots, first_passing


def _count(path: Path, n: int) -> None:
    path.write_text(f"{n:20d}\n")  # the format the benchmark's step counter writes


def test_snapshots_are_taken_once_per_grid_line_with_the_counts_read_then(tmp_path):
    weights, steps, updates = tmp_path / "model_trainer.tmod", tmp_path / "steps", tmp_path / "updates"
    snaps = _Snapshots(weights, tmp_path, t0=0.0, grid=1000)
    weights.write_bytes(b"weights at 950")
    _count(steps, 950)
    _count(updates, 80)
    assert not snaps.poll() and snaps.take() == []  # before the first grid line
    _count(steps, 1000)
    weights.write_bytes(b"weights at 1000")
    assert snaps.poll()
    assert not snaps.poll()  # the same line is not taken twice
    _count(steps, 3450)  # lines 2000 and 3000 passed between two polls: one snapshot, then 4000 is next
    _count(updates, 300)
    weights.write_bytes(b"weights at 3450")
    assert snaps.poll()
    _count(steps, 3999)
    assert not snaps.poll()
    taken = snaps.take()
    assert [(s["steps"], s["updates"], s["data"]) for s in taken] == [(1000, 80, b"weights at 1000"),
                                                                     (3450, 300, b"weights at 3450")]
    assert snaps.take() == []  # taken once: the evaluator keeps only those since its last evaluation


def test_a_missing_weights_file_is_not_a_snapshot_and_is_tried_again(tmp_path):
    snaps = _Snapshots(tmp_path / "model_trainer.tmod", tmp_path, t0=0.0, grid=100)
    _count(tmp_path / "steps", 150)
    assert not snaps.poll()
    (tmp_path / "model_trainer.tmod").write_bytes(b"w")
    assert snaps.poll() and snaps.take()[0]["steps"] == 150


def _window(*steps: int) -> list[dict]:
    return [{"steps": s, "updates": s // 10, "t_read": s / 1000, "data": str(s).encode()} for s in steps]


def test_the_first_passing_snapshot_in_order_gives_the_counts():
    returns = {b"1000": -400.0, b"2000": -150.0, b"3000": -500.0, b"4000": -120.0}
    first, tried = first_passing(_window(1000, 2000, 3000, 4000), 4500, lambda data: returns[data])
    assert first == {"steps": 2000, "updates": 200, "t_read": 2.0, "ret": -150.0} and tried == 2


def test_no_snapshot_passes_or_none_before_the_evaluation_then_none_is_chosen():
    assert first_passing(_window(1000, 2000), 3000, lambda data: THRESHOLD - 1) == (None, 2)
    # snapshots taken at or after the passing evaluation's own read are not earlier: not tested
    seen: list[bytes] = []
    first, tried = first_passing(_window(1000, 2000, 3000), 2000, lambda data: seen.append(data) or THRESHOLD + 1)
    assert first is not None and first["steps"] == 1000 and seen == [b"1000"]
    assert first_passing(_window(3000), 2500, lambda data: THRESHOLD + 1) == (None, 0)
    assert first_passing(_window(2000), 2000, lambda data: THRESHOLD + 1) == (None, 0)


def test_a_snapshot_that_cannot_be_loaded_is_skipped():
    returns = {b"1000": None, b"2000": -100.0}
    first, tried = first_passing(_window(1000, 2000), 5000, lambda data: returns[data])
    assert first is not None and first["steps"] == 2000 and tried == 1
