"""The benchmark harness (bench/harness.py): order of the sides, the summary and its JSON lines,
the floor's products, and the command line. No benchmark is run here."""

from __future__ import annotations

import json
import math
import platform
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench import BENCHMARKS, harness  # noqa: E402
from bench.trainer_speed import update_products  # noqa: E402


def test_sides_alternate_their_order_every_round():
    order = list(harness.alternate(["ours", "tmrl", "sb3"], 4))
    assert order == [(0, "ours"), (0, "tmrl"), (0, "sb3"), (1, "sb3"), (1, "tmrl"), (1, "ours"),
                     (2, "ours"), (2, "tmrl"), (2, "sb3"), (3, "sb3"), (3, "tmrl"), (3, "ours")]


def test_recorder_summarises_medians_spread_and_writes_json_lines(tmp_path, capsys):
    rec = harness.Recorder("unit", {"batch": 256}, out_dir=tmp_path)
    for rnd, (ours, tmrl) in enumerate([(10.0, 4.0), (30.0, 6.0), (20.0, 5.0)]):
        rec.add("case", "updates_per_s", "ours", ours, round=rnd)
        rec.add("case", "updates_per_s", "tmrl", tmrl, round=rnd)
    rec.add("case", "steps", "ours", None, round=0, higher_is_better=False)
    rec.add("case", "steps", "ours", 500.0, round=1, higher_is_better=False)
    rows = {(r["metric"], r["side"]): r for r in rec.print_table()}
    rec.close()
    assert (rows["updates_per_s", "ours"]["median"], rows["updates_per_s", "ours"]["min"],
            rows["updates_per_s", "ours"]["max"]) == (20.0, 10.0, 30.0)
    assert rows["updates_per_s", "tmrl"]["median"] == 5.0
    assert (rows["steps", "ours"]["n"], rows["steps", "ours"]["of"]) == (1, 2)  # a run that never got there
    lines = [json.loads(line) for line in rec.path.read_text().splitlines()]
    assert lines[0]["kind"] == "run" and lines[0]["settings"] == {"batch": 256}
    # the install the figures came from: runs are exact on one install only
    from importlib import metadata

    assert lines[0]["install"]["packages"]["torch"] == metadata.version("torch")
    assert lines[0]["install"]["python"] == platform.python_version()
    assert lines[0]["install"]["environment"] == sys.prefix
    assert sum(1 for r in lines if r["kind"] == "measure") == 8
    assert all("load1" in r for r in lines if r["kind"] == "measure")
    ratio = next(r for r in lines if r["kind"] == "ratio")
    assert ratio["ratio"] == pytest.approx(4.0)
    assert "ours vs tmrl: 4.00x" in capsys.readouterr().out


def test_two_records_started_in_the_same_second_get_two_files(tmp_path, monkeypatch):
    """Two commands started in the same second (two runs side by side) keep one record each."""
    monkeypatch.setattr(harness.time, "strftime", lambda fmt, *a: "20261126-141956" if "%H%M%S" in fmt else "x")
    first, second = (harness.Recorder("unit", {"side": n}, out_dir=tmp_path) for n in (1, 2))
    first.close()
    second.close()
    assert (first.path.name, second.path.name) == ("unit-20261126-141956.jsonl", "unit-20261126-141956-2.jsonl")
    headers = [json.loads(p.read_text().splitlines()[0])["settings"] for p in (first.path, second.path)]
    assert headers == [{"side": 1}, {"side": 2}] and len(first.path.read_text().splitlines()) == 1


def test_floor_counts_the_products_of_one_update():
    # 256x256x256 products of one SAC update: actor on o and o' (2), two target critics (2),
    # two critics forward and backward on (o, a) (6), forward and input gradient on (o, pi) (4),
    # actor backward (2); REDQ-SAC with 10 critics and 2 targets: 56.
    def big(products):
        return sum(count for count, m, k, n in products if (m, k, n) == (256, 256, 256))

    assert big(update_products(3, 1, 256, 256, n_critics=2, n_targets=2)) == 16
    assert big(update_products(3, 1, 256, 256, n_critics=10, n_targets=2)) == 56


def test_list_shows_every_benchmark_and_unknown_names_are_refused():
    out = subprocess.run([sys.executable, "-m", "bench", "--list"], cwd=REPO, capture_output=True, text=True,
                         timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    for name in BENCHMARKS:
        assert f"  {name} " in out.stdout
    bad = subprocess.run([sys.executable, "-m", "bench", "nope"], cwd=REPO, capture_output=True, text=True,
                         timeout=120, check=False)
    assert bad.returncode != 0 and "unknown benchmark 'nope'" in bad.stderr


@pytest.mark.posix  # a POSIX side: /usr/bin/python3 and PATH=/usr/bin:/bin
def test_children_load_bench_without_putting_the_checkout_on_the_path(tmp_path):
    # What lets the original's interpreter import its installed tmrl: a child of another side
    # loads `bench` from this checkout but does not see this checkout's `tmrl`. The system
    # interpreter stands for that side (it has no tmrl of its own).
    python = "/usr/bin/python3"
    if not Path(python).exists():
        python = sys.executable
    side = harness.Side("other", python, {"PATH": "/usr/bin:/bin"}, str(tmp_path))
    out = subprocess.run(side.command("harness"), env=side.env, cwd=side.cwd, capture_output=True, text=True,
                         timeout=60, check=False)
    assert out.returncode == 0, out.stderr
    where = json.loads(out.stdout)
    assert where["bench"] == str(REPO / "bench")
    assert where["tmrl"] is None or not where["tmrl"].startswith(str(REPO / "tmrl"))


@pytest.mark.parametrize("windows", [pytest.param(False, id="posix", marks=pytest.mark.posix),
                                     pytest.param(True, id="windows")])
def test_json_lines_and_load_averages_without_the_names_windows_lacks(windows, monkeypatch):
    # Windows has neither non-blocking pipes nor load averages: JsonLines reads through a thread,
    # the load is NaN, and the records and summaries still come.
    if windows:
        monkeypatch.delattr(harness.os, "set_blocking", raising=False)
        monkeypatch.delattr(harness.os, "getloadavg", raising=False)
    code = "import json, time\nfor i in range(3):\n    print(json.dumps({'i': i}), flush=True)\n    time.sleep(0.05)\n"
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    try:
        got = [rec["i"] for rec in harness.JsonLines(proc).wait(30)]
    finally:
        proc.wait(30)
        proc.stdout.close()
    assert got == [0, 1, 2]
    load = harness.load_average()
    assert math.isnan(load) if windows else load >= 0  # NaN where the system keeps none
    assert "CPUs" in harness._loads()
