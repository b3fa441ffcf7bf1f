"""bench update_cost: each variant's measured update, times its ratio, against the reference."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_update_cost_prints_each_variant_against_the_reference_and_keeps_a_record():
    proc = subprocess.run(
        [sys.executable, "-m", "bench", "update_cost", "--agents", "BRO-UTD4-CAP-R250,SAC-UTD4-FA", "--rounds", "2",
         "--updates", "6", "--warmup", "1", "--batch-size", "32"],
        cwd=ROOT, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    assert "processor" in lines[0] and "load" in lines[0]
    table = {line.split()[0]: line.split() for line in lines[2:5]}
    # the reference joins the run when not named, at 8 updates per step and a ratio of 1
    assert set(table) == {"BRO-UTD4-CAP-R250", "SAC-UTD4-FA", "REDQSAC-UTD8-CAP-R250"}
    assert table["REDQSAC-UTD8-CAP-R250"][-3] == "8" and table["REDQSAC-UTD8-CAP-R250"][-1] == "1.00"
    assert table["BRO-UTD4-CAP-R250"][-3] == "4"
    record = Path(lines[-1].split("record: ", 1)[1])
    try:
        rows = [json.loads(line) for line in record.read_text(encoding="utf-8").splitlines()]
    finally:
        record.unlink()
    by_agent = {r["agent"]: r for r in rows[1:]}
    for r in by_agent.values():
        assert len(r["rounds"]) == 2 and r["min"] <= r["ms_per_update"] <= r["max"]
        assert r["ms_per_step"] == r["ms_per_update"] * r["updates_per_step"]
