"""``python -m bench first_lap`` (issue 40): the tool that measures the Quick start's first lap
against the demo's. Its two detectors on what the demo and the worker write, then one short real
run of both (no lap expected in a few seconds) that records both, prints the load and leaves no
process and no folder behind."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import process_support
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.first_lap import demo_lapped, worker_lapped

pytestmark = pytest.mark.timeout(300)


def test_a_lap_is_an_episode_past_the_lap_bonus():
    log = ("12:00:01 DEBUG tmrl.networking: train episode 46: return 61.7 in 544 steps; 545 samples sent; "
           "weights version 163\n12:00:02 INFO tmrl.networking: train episodes 1-46: return last 161.7, mean 2.6\n")
    assert not worker_lapped(log)  # a whole track without the bonus, and a summary line, are not laps
    assert worker_lapped(log + "12:00:03 DEBUG tmrl.networking: train episode 47: return 161.7 in 852 steps; "
                               "853 samples sent; weights version 176\n")
    assert not worker_lapped("train episode 3: return -150.0 in 10 steps")


def test_the_demo_lapped_once_its_status_file_says_so(tmp_path):
    assert demo_lapped(tmp_path) is None
    run = tmp_path / "tmrl-demo-abc"
    run.mkdir()
    (run / "trainer.json").write_text(json.dumps({"updates": 1234}))
    (run / "worker.json").write_text(json.dumps({"steps": 9000, "first_lap_s": None}))
    assert demo_lapped(tmp_path) is None
    (run / "worker.json").write_text(json.dumps({"steps": 9000, "first_lap_s": 71.5}))
    assert demo_lapped(tmp_path) == 1234


@pytest.mark.posix  # the bench stops its runs with SIGINT to their process groups (bench/harness.py)
def test_a_short_run_of_both_records_them_and_leaves_nothing_behind(tmp_path):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = dict(os.environ, TMPDIR=str(tmp), PYTHONUNBUFFERED="1")
    done = subprocess.run([sys.executable, "-m", "bench", "first_lap", "--rounds", "1", "--timeout", "5"], cwd=REPO,
                          env=env, capture_output=True, text=True, timeout=240, check=False)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-3000:]
    assert re.search(r"first_lap: load average [\d.]+/[\d.]+/[\d.]+ \(\d+ CPUs\) at start", out), out[-3000:]
    for mode in ("demo", "quickstart"):
        assert re.search(rf"\] {mode} +first_lap_s = (-|[\d.]+) s +\(round 0, load [\d.]+\)", out), out[-3000:]
    results = Path(re.search(r"^results: (.+\.jsonl)$", out, re.MULTILINE).group(1))
    try:
        records = [json.loads(line) for line in results.read_text().splitlines()]
    finally:
        results.unlink()
    assert {r["side"] for r in records if r.get("metric") == "first_lap_s" and r["kind"] == "measure"} == \
        {"demo", "quickstart"}
    assert process_support.marked(str(tmp)) == []  # every process of both runs is gone
    assert list(tmp.iterdir()) == [] or all(p.name.startswith("torchinductor") for p in tmp.iterdir()), \
        list(tmp.iterdir())
