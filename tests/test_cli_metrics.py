"""`python -m tmrl --trainer` writes its metrics where the docs say: one row per round in
``<data folder>/logs/<RUN_NAME>/metrics.csv`` (what examples/metrics_plot.py and a user's own
plotting read), besides the console line."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

PW = "metrics test password"


@pytest.mark.posix
def test_cli_trainer_writes_metrics_csv_under_the_data_folder(tmp_path, port_factory):
    data = tmp_path / "data"
    override = {
        "RUN_NAME": "csv_run",
        "PORT": port_factory(),
        "TLS": False,
        "PASSWORD": PW,
        "ENV": {"RTGYM_INTERFACE": "GYM", "GYM_ID": "Pendulum-v1"},
        "MAX_EPOCHS": 1,
        "ROUNDS_PER_EPOCH": 3,
        "TRAINING_STEPS_PER_ROUND": 10,
        "ENVIRONMENT_STEPS_BEFORE_TRAINING": 50,
        "UPDATE_MODEL_INTERVAL": 10,
        "UPDATE_BUFFER_INTERVAL": 10,
    }
    env = dict(os.environ, TMRL_DATA=str(data), TMRL_CONFIG_OVERRIDE=json.dumps(override))
    procs = []
    logs = []
    try:
        for role in ("server", "trainer", "worker"):
            log = open(tmp_path / f"{role}.log", "w")  # noqa: SIM115 (closed below)
            logs.append(log)
            procs.append(subprocess.Popen([sys.executable, "-m", "tmrl", f"--{role}"], stdout=log,
                                          stderr=subprocess.STDOUT, env=env, cwd=tmp_path))
        trainer = procs[1]
        # the trainer ends by itself after its one epoch of 3 rounds
        trainer.wait(timeout=240)
        trainer_log = (tmp_path / "trainer.log").read_text()
        assert trainer.returncode == 0, trainer_log[-3000:]
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 30
        for p in procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
        for log in logs:
            log.close()
    path = Path(data) / "logs" / "csv_run" / "metrics.csv"
    assert path.is_file(), f"no {path}; trainer log:\n{trainer_log[-2000:]}"
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3  # one per round
    assert [int(r["round"]) for r in rows] == [0, 1, 2] or [int(r["round"]) for r in rows] == [1, 2, 3]
    assert int(rows[-1]["total_updates"]) == 30
    assert float(rows[-1]["loss_critic"]) == float(rows[-1]["loss_critic"])  # a number, not empty
