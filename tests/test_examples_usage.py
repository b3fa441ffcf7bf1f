"""The usage-mode examples run end to end with a tiny budget: examples/custom_interface.py (a
custom real-time interface, checked then driven), examples/vector_env.py (Gymnasium vector
environments of simulators), examples/sb3_simulator.py (Stable-Baselines3 on the simulator and on
the real-time drone) and examples/metrics_plot.py (a tiny real run, then its learning curve).

The older examples are run by tests/test_examples.py and by the test files of the modules they
show (their names are not repeated here, so that tests/test_docs.py's check that each example is
named by a test keeps meaning something).
"""

from __future__ import annotations

import csv
import importlib.util
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_example(name: str, *args: str, tmp_path: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    env = dict(os.environ, TMRL_DATA=str(tmp_path / "data"), MPLBACKEND="Agg")
    env.pop("DISPLAY", None)
    return subprocess.run([sys.executable, str(EXAMPLES / name), *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


def ok(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 0, f"exit {out.returncode}\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    assert "Traceback" not in out.stderr
    return out.stdout


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name.removesuffix('.py')}", EXAMPLES / name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# --- examples/custom_interface.py -------------------------------------------------------------------


def test_custom_interface_passes_the_checker_and_runs_episodes(tmp_path):
    out = ok(run_example("custom_interface.py", "--episodes", "2", "--steps", "15", "--time-step", "0.01",
                         tmp_path=tmp_path))
    assert "interface check: no problem found" in out
    line = r"^episode (\d+): (\d+) steps, return (-?[\d.]+), room (-?[\d.]+) °C, target ([\d.]+) °C$"
    episodes = re.findall(line, out, re.MULTILINE)
    assert [(e[0], e[1]) for e in episodes] == [("1", "15"), ("2", "15")]
    assert all(15.0 <= float(e[4]) <= 25.0 for e in episodes)  # targets drawn in [15, 25] °C
    for key in ("time_step_duration", "get_obs_duration", "inference_duration"):
        assert f"'{key}'" in out  # the benchmarks were printed


def test_the_checker_rejects_a_broken_variant_of_the_example_interface():
    import tmrl.realtime as rt

    example = load_example("custom_interface.py")
    assert rt.check_realtime_interface(example.ThermostatInterface, n_steps=3, clock=rt.FakeClock()) == []

    class TwoValues(example.ThermostatInterface):  # the room temperature as 2 values, 1 declared
        def _obs(self):
            room, target = super()._obs()
            return [np.concatenate((room, room)), target]

    problems = rt.check_realtime_interface(TwoValues, n_steps=3, clock=rt.FakeClock())
    assert problems and "observation element 0" in problems[0]


def test_the_example_heater_warms_up_and_cools_down():
    example = load_example("custom_interface.py")
    heater = example.Heater(heat_rate=40.0, cooling_time=0.5)
    heater.set_power(1.0)
    heater._last -= 1.0  # as if a second had gone by at full power
    warm = heater.read_temperature()
    assert example.OUTSIDE + 15 < warm <= example.OUTSIDE + 20  # 2 time constants towards +20 °C
    heater.set_power(0.0)
    heater._last -= 1.0
    assert example.OUTSIDE <= heater.read_temperature() < warm - 10


# --- examples/vector_env.py -------------------------------------------------------------------------

VEC_LINE = re.compile(r"^(sync|async): 2 envs x 200 steps in [\d.]+ s = (\d+) steps/s \| "
                      r"(\d+) episodes ended, "
                      r"(\d+) laps completed \| mean return [^:]*: (-?[\d.]+)$", re.MULTILINE)


def vector_results(tmp_path: Path, policy: str) -> dict[str, tuple[int, float]]:
    out = ok(run_example("vector_env.py", "--envs", "2", "--steps", "200", "--policy", policy,
                         tmp_path=tmp_path))
    found = {m[0]: (int(m[1]), float(m[4])) for m in VEC_LINE.findall(out)}
    assert set(found) == {"sync", "async"}, out
    assert re.search(r"^async / sync speed: [\d.]+$", out, re.MULTILINE)
    return found


def test_vector_env_sync_and_async_agree_and_the_driver_beats_random(tmp_path):
    driver = vector_results(tmp_path, "driver")
    random = vector_results(tmp_path, "random")
    for found in (driver, random):
        assert all(steps_per_s > 0 for steps_per_s, _ in found.values())
        # the simulator is deterministic: both vector environments see the same returns
        assert found["sync"][1] == found["async"][1]
    assert driver["sync"][1] > random["sync"][1] + 5.0  # the driver makes progress along the track


# --- examples/sb3_simulator.py ----------------------------------------------------------------------

def returns_before_after(out: str, steps: int) -> tuple[float, float]:
    tail = r" (-?[\d.]+) \+/- [\d.]+ \(2 episodes\)$"
    before = re.search(r"^mean return before training:" + tail, out, re.MULTILINE)
    after = re.search(rf"^mean return after {steps} steps:" + tail, out, re.MULTILINE)
    assert before and after, out
    return float(before[1]), float(after[1])


def test_sb3_sac_on_the_simulator(tmp_path):
    out = ok(run_example("sb3_simulator.py", "--env", "sim", "--steps", "300", "--ep-len", "100",
                         "--eval-episodes", "2", tmp_path=tmp_path))
    assert "observation given to SB3: a Box of shape (83,)" in out  # speed 1 + lidar 4x19 + 2 actions x 3
    assert all(math.isfinite(r) for r in returns_before_after(out, 300))
    assert re.search(r"^training: 300 steps in [\d.]+ s", out, re.MULTILINE)


def test_sb3_sac_on_the_real_time_drone(tmp_path):
    out = ok(run_example("sb3_simulator.py", "--env", "drone", "--fast", "--steps", "300",
                         "--eval-episodes", "2", tmp_path=tmp_path))
    assert "observation given to SB3: a Box of shape (12,)" in out  # 4 positions + 4 actions x 2
    before, after = returns_before_after(out, 300)
    assert -200 * 2 < before <= 0 and -200 * 2 < after <= 0  # minus distances, 100 steps per episode
    assert re.search(r"^time steps that came late: \d+$", out, re.MULTILINE)


# --- examples/metrics_plot.py -----------------------------------------------------------------------


def test_metrics_plot_demo_run_then_plot(tmp_path):
    out = ok(run_example("metrics_plot.py", "--demo-data", "--demo-rounds", "2", "--out", "curve.png",
                         tmp_path=tmp_path, timeout=150))
    csv_path = tmp_path / "data" / "logs" / "metrics_plot_demo" / "metrics.csv"
    assert f"demo run: wrote {csv_path}" in out
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["round"] for r in rows] == ["0", "1"]
    assert float(rows[-1]["total_updates"]) == 200
    assert "csv: 2 rows, columns: epoch, round, total_updates, total_samples" in out
    if importlib.util.find_spec("tensorboard") is None:
        assert "tensorboard: not installed" in out
    else:
        assert "tensorboard: " in out and "scalar series" in out
    png = (tmp_path / "curve.png").read_bytes()
    assert png.startswith(PNG_MAGIC) and png[12:16] == b"IHDR"
    width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert (width, height) == (1100, 400)  # two panels, 11 x 4 inches at 100 dpi
    assert len(png) > 20_000  # curves, axes and titles, not a blank image
    # no test episode in so short a run: no test curve
    assert "plot: wrote curve.png (curves: train episodes, loss_actor, loss_critic)" in out

    # the same CSV, found by run name in the data folder, and by path
    again = ok(run_example("metrics_plot.py", "metrics_plot_demo", "--out", "by_name.png", tmp_path=tmp_path))
    assert "csv: 2 rows" in again and (tmp_path / "by_name.png").read_bytes().startswith(PNG_MAGIC)
    by_path = ok(run_example("metrics_plot.py", str(csv_path), "--out", "by_path.png", tmp_path=tmp_path))
    assert "csv: 2 rows" in by_path


def test_metrics_plot_reports_a_missing_run(tmp_path):
    out = run_example("metrics_plot.py", "no_such_run", tmp_path=tmp_path)
    assert out.returncode == 1 and "no metrics file at" in out.stderr
