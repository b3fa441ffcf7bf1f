"""Tests of tmrl.metrics: console line, CSV file (created lazily, resumed), optional backends."""

from __future__ import annotations

import builtins
import csv
import logging

import numpy as np
import pytest
import torch

from tmrl.errors import UserError
from tmrl.metrics import MetricsLogger, format_row

ROW = {
    "epoch": 1, "round": 3, "rounds": 50, "total_updates": 400, "loss_actor": -3.2109,
    "loss_critic": torch.tensor(0.12345), "entropy_coef": np.float32(0.04123), "return_train": -140.5,
    "return_test": float("nan"), "memory_len": 12000, "updates_per_second": 105.33,
    "samples_per_second": 51.2, "custom": 7,
}


def test_console_line_is_compact():
    line = format_row(ROW)
    assert "\n" not in line
    assert line.startswith("epoch 1 round 3/50 | loss_actor -3.211 loss_critic 0.1235 entropy_coef 0.04123")
    assert "return train -140.5 test -" in line and "memory 12000" in line and "105.3 upd/s 51.2 smp/s" in line


def test_csv_created_on_first_row_and_resumed(tmp_path, caplog):
    metrics = MetricsLogger("myrun", folder=tmp_path, tensorboard=False)
    assert not (tmp_path / "logs").exists()
    with caplog.at_level(logging.INFO, logger="tmrl.metrics"):
        metrics.log_round(ROW)
    assert any("round 3/50" in r.getMessage() for r in caplog.records)
    path = tmp_path / "logs" / "myrun" / "metrics.csv"
    assert metrics.csv_path == path
    metrics.log_round({**ROW, "round": 4, "new_metric": 1.0})
    # a restarted run appends under the same header, after closing a line cut by a crash
    with open(path, "a") as f:
        f.write("1,5,40")
    again = MetricsLogger("myrun", folder=tmp_path, tensorboard=False, console=False)
    again.log_round({**ROW, "round": 6})
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header = rows[0]
    assert header[:3] == ["epoch", "round", "total_updates"] and "custom" in header and "new_metric" not in header
    body = [dict(zip(header, r)) for r in rows[1:]]
    assert [r["round"] for r in body] == ["3", "4", "5", "6"]
    assert float(body[0]["loss_critic"]) == pytest.approx(0.12345) and body[0]["return_test"] == "nan"
    assert body[3]["memory_len"] == "12000"


def test_console_only_without_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    metrics = MetricsLogger("x", folder=None)
    metrics.log_round(ROW)
    assert metrics.csv_path is None and list(tmp_path.iterdir()) == []


def test_missing_optional_backends_are_named(monkeypatch):
    real_import = builtins.__import__

    def no_optional(name, *args, **kwargs):
        if name in ("wandb", "torch.utils.tensorboard"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_optional)
    with pytest.raises(UserError, match=r'pip install "\.\[wandb\]"'):
        MetricsLogger("x", wandb=True)
    with pytest.raises(UserError, match="pip install tensorboard"):
        MetricsLogger("x", folder="somewhere", tensorboard=True)
    MetricsLogger("x", folder="somewhere")  # tensorboard=None: silently without it


def test_wandb_only_when_asked(monkeypatch):
    calls = []

    class FakeWandb:
        @staticmethod
        def init(**kwargs):
            calls.append(("init", kwargs))
            return type("Run", (), {"finish": lambda self: calls.append(("finish",))})()

        @staticmethod
        def log(data, step):
            calls.append(("log", step, sorted(data)))

    import sys

    monkeypatch.setitem(sys.modules, "wandb", FakeWandb)
    MetricsLogger("quiet", tensorboard=False).log_round(ROW)
    assert calls == []
    metrics = MetricsLogger("loud", tensorboard=False, wandb=True, wandb_project="p")
    metrics.log_round(ROW)
    metrics.close()
    assert calls[0] == ("init", {"project": "p", "name": "loud", "resume": "allow"})
    assert calls[1][0] == "log" and calls[1][1] == 400 and "loss_critic" in calls[1][2]
    assert calls[2] == ("finish",)
