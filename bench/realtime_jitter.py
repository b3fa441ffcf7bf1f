"""Timing precision of the real-time environment: tmrl.realtime against rtgym 0.16.

Runs a 20 Hz environment (an interface that records when each control is sent and returns a
constant observation at once) for a few hundred steps, with a simulated inference between steps,
and prints mean, standard deviation and 99th percentile of

* the interval between two step() returns (what the policy sees), and
* the time-step duration (the interval between two send_control calls: what the device sees),

for both implementations in the same run, and the ratios ours / rtgym (below 1 is better).
Each implementation runs in its own subprocess: ours with this Python, rtgym's with the
interpreter of a venv where it is installed (``--rtgym-python``; by default the one
``bench/anchors/install_tmrl.sh`` makes, which installs rtgym 0.16 beside tmrl 0.7.1)::

    python -m bench realtime_jitter                      # idle machine
    python -m bench realtime_jitter --busy               # a busy process on the other core
    python -m bench realtime_jitter --both               # both, one table each
    python -m bench realtime_jitter --semantics          # same episodes as rtgym? (no timing)

Rounds alternate between the implementations in ABBA order, so that a change in the machine's load
during the run favours neither; the intervals of all rounds are pooled for the first table, and
each round's figures go through the harness (medians over rounds, load average beside them).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
import time

from bench import harness


# child: one implementation --------------------------------------------------------------------
def child(impl: str, steps: int, warmup: int, inference_ms: float, period: float) -> None:
    import gymnasium
    import numpy as np
    from gymnasium import spaces

    if impl == "rtgym":
        import rtgym

        base, defaults, env_id = rtgym.RealTimeGymInterface, rtgym.DEFAULT_CONFIG_DICT, "real-time-gym-v1"
    else:
        import tmrl.realtime

        base, defaults, env_id = (
            tmrl.realtime.RealTimeGymInterface,
            tmrl.realtime.DEFAULT_CONFIG_DICT,
            "tmrl/real-time-gym-v1",
        )
    controls: list[float] = []

    class Recorder(base):  # type: ignore[misc, valid-type]
        def get_observation_space(self):
            return spaces.Tuple((spaces.Box(-1.0, 1.0, (1,), np.float32),))

        def get_action_space(self):
            return spaces.Box(-1.0, 1.0, (1,), np.float32)

        def get_default_action(self):
            return np.zeros(1, np.float32)

        def send_control(self, control):
            controls.append(time.perf_counter())

        def reset(self, seed=None, options=None):
            return [np.zeros(1, np.float32)], {}

        def get_obs_rew_terminated_info(self):
            return [np.zeros(1, np.float32)], 0.0, False, {}

        def wait(self):
            pass

    config = dict(defaults)
    config.update(
        interface=Recorder,
        time_step_duration=period,
        start_obs_capture=period,
        time_step_timeout_factor=1.0,
        ep_max_length=np.inf,
        act_buf_len=1,
        benchmark=False,
    )
    env = gymnasium.make(env_id, config=config, disable_env_checker=True)
    act = np.zeros(1, np.float32)
    returns: list[float] = []
    env.reset()
    for _ in range(steps + warmup):
        # simulated inference: Python work holding the GIL, as a policy's pre/post-processing does
        deadline = time.perf_counter() + inference_ms / 1000.0
        while time.perf_counter() < deadline:
            pass
        env.step(act)
        returns.append(time.perf_counter())
    env.close()
    print(json.dumps({"returns": returns[warmup:], "controls": controls[warmup + 1 :]}))


def child_semantics(impl: str) -> None:
    """Print, as JSON, what each configuration of the episode rules produces (no timing)."""

    import gymnasium
    import numpy as np
    from gymnasium import spaces

    if impl == "rtgym":
        import rtgym

        base, defaults, env_id = rtgym.RealTimeGymInterface, rtgym.DEFAULT_CONFIG_DICT, "real-time-gym{}-v1"
    else:
        import tmrl.realtime

        base, defaults = tmrl.realtime.RealTimeGymInterface, tmrl.realtime.DEFAULT_CONFIG_DICT
        env_id = "tmrl/real-time-gym{}-v1"
    log: list[list] = []

    class Counter(base):  # type: ignore[misc, valid-type]
        """Observation k is the k-th capture of the episode; terminates every 7th capture."""

        def __init__(self):
            self.k, self.total = 0, 0

        def get_observation_space(self):
            return spaces.Tuple((spaces.Box(-1e9, 1e9, (1,), np.float32),))

        def get_action_space(self):
            return spaces.Box(-1e3, 1e3, (1,), np.float32)

        def get_default_action(self):
            return np.full(1, -1.0, np.float32)

        def send_control(self, control):
            log.append(["send", float(control[0])])

        def reset(self, seed=None, options=None):
            log.append(["reset"])
            self.k = 0
            return [np.full(1, 100.0 + self.total, np.float32)], {}

        def get_obs_rew_terminated_info(self):
            self.k += 1
            self.total += 1
            return [np.full(1, float(self.k), np.float32)], float(self.k), self.total % 7 == 0, {}

        def wait(self):
            log.append(["wait"])

    out = []
    for rab, laor, wod, ts in itertools.product([True, False], [True, False], [True, False], ["", "-ts"]):
        log.clear()
        config = dict(defaults)
        config.update(
            interface=Counter,
            time_step_duration=0.01,
            start_obs_capture=0.005,
            ep_max_length=4,
            act_buf_len=3,
            reset_act_buf=rab,
            last_act_on_reset=laor,
            wait_on_done=wod,
        )
        env = gymnasium.make(env_id.format(ts), config=config, disable_env_checker=True)
        rec: list = []
        x = 0.0
        for _ in range(3):
            obs, _ = env.reset()
            rec.append(["reset", [float(v[0]) for v in obs]])
            done = False
            while not done:
                x += 1
                obs, rew, terminated, truncated, _ = env.step(np.full(1, x, np.float32))
                rec.append(["step", [float(v[0]) for v in obs], rew, bool(terminated), bool(truncated)])
                done = terminated or truncated
            try:
                env.step(np.full(1, 99.0, np.float32))
                rec.append("no error after done")
            except RuntimeError:
                rec.append("RuntimeError after done")
        env.unwrapped.stop()
        time.sleep(0.05)  # rtgym sends the reset's control from a thread it does not join
        out.append({"config": [rab, laor, wod, ts], "steps": rec, "interface_calls": list(log)})
        env.close()
    print(json.dumps(out))


def _sides(args: argparse.Namespace) -> dict[str, harness.Side]:
    return {"tmrl": harness.ours_side(), "rtgym": harness.rtgym_side(args.rtgym_python)}


def compare_semantics(args: argparse.Namespace) -> None:
    results = {}
    for impl, side in _sides(args).items():
        out = subprocess.run(side.command("realtime_jitter", "--child-semantics", impl), capture_output=True,
                             text=True, env=side.env, cwd=side.cwd, check=True)
        results[impl] = json.loads(out.stdout.strip().splitlines()[-1])
    same = 0
    for ours, theirs in zip(results["tmrl"], results["rtgym"]):
        if ours == theirs:
            same += 1
        else:
            print("differs for reset_act_buf, last_act_on_reset, wait_on_done, variant =", ours["config"])
    print(
        f"episode rules: {same} of {len(results['tmrl'])} configurations give the same observations, rewards, "
        "flags, errors and interface calls as rtgym"
    )


# parent -------------------------------------------------------------------------------------------
def intervals(timestamps: list[float]) -> list[float]:
    """Milliseconds between consecutive timestamps."""
    return [1000.0 * (b - a) for a, b in itertools.pairwise(timestamps)]


def stats(values: list[float]) -> tuple[float, float, float]:
    """Mean, standard deviation and 99th percentile."""
    import numpy as np

    d = np.asarray(values)
    return float(d.mean()), float(d.std()), float(np.percentile(d, 99))


def run_child(
    side: harness.Side, impl: str, args: argparse.Namespace, cpus: set[int] | None
) -> dict[str, list[float]]:
    cmd = side.command(
        "realtime_jitter",
        "--child",
        impl,
        "--steps",
        str(args.steps),
        "--warmup",
        str(args.warmup),
        "--inference-ms",
        str(args.inference_ms),
        "--period",
        str(args.period),
    )
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=side.env,
                            cwd=side.cwd)
    if cpus and hasattr(os, "sched_setaffinity"):  # (cpus is empty where it is missing)
        os.sched_setaffinity(proc.pid, cpus)
    out, err = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"{impl} run failed:\n{err}")
    return json.loads(out.strip().splitlines()[-1])


def measure(args: argparse.Namespace, busy: bool, rec: harness.Recorder) -> None:
    ncpu = os.cpu_count() or 1
    hog = None
    cpus = None
    if busy:
        hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        if ncpu >= 2 and hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(hog.pid, {ncpu - 1})
            cpus = set(range(ncpu - 1))
    try:
        load_before = harness.load_averages()
        pooled: dict[str, dict[str, list[float]]] = {
            impl: {"returns": [], "controls": []} for impl in ("tmrl", "rtgym")
        }
        sides = _sides(args)
        title = "busy process on the other core" if busy else "no extra load"
        for r, impl in harness.alternate(["tmrl", "rtgym"], args.rounds):
            res = run_child(sides[impl], impl, args, cpus)
            for key, label in (("returns", "step() return interval"), ("controls", "time-step duration")):
                pooled[impl][key] += intervals(res[key])
                for name, value in zip(("mean", "std", "p99"), stats(intervals(res[key]))):
                    rec.add(f"{label}, {title}", f"{name}_ms", "ours" if impl == "tmrl" else impl, value,
                            round=r, higher_is_better=False, unit="ms", echo=False)
        load_after = harness.load_averages()
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()

    print(
        f"\n{1 / args.period:.0f} Hz, {args.steps} steps x {args.rounds} round(s), "
        f"inference {args.inference_ms} ms, {title}; load average {load_before[0]:.2f} -> {load_after[0]:.2f}"
        f" ({ncpu} CPUs)"
    )
    print(f"{'figure (ms)':<34}{'tmrl':>10}{'rtgym':>10}{'ratio':>8}")
    for key, label in (("returns", "step() return interval"), ("controls", "time-step duration")):
        ours, theirs = stats(pooled["tmrl"][key]), stats(pooled["rtgym"][key])
        for i, name in enumerate(("mean", "std", "p99")):
            ratio = ours[i] / theirs[i] if theirs[i] else float("nan")
            print(f"{label + ' ' + name:<34}{ours[i]:>10.3f}{theirs[i]:>10.3f}{ratio:>8.3f}")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m bench realtime_jitter", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument(
        "--rounds", type=int, default=2, help="runs per implementation, in ABBA order (intervals pooled)"
    )
    parser.add_argument("--period", type=float, default=0.05, help="time-step duration in seconds")
    parser.add_argument("--inference-ms", type=float, default=5.0)
    parser.add_argument(
        "--rtgym-python",
        default=harness.DEFAULT_RTGYM_PYTHON,
        help="interpreter of the venv where rtgym==0.16 is installed",
    )
    parser.add_argument("--busy", action="store_true", help="run a busy process on the other core")
    parser.add_argument("--both", action="store_true", help="measure without and with the busy process")
    parser.add_argument(
        "--semantics",
        action="store_true",
        help="instead of timing, compare episode rules with rtgym on 16 configurations",
    )
    parser.add_argument("--child", choices=["tmrl", "rtgym"], help=argparse.SUPPRESS)
    parser.add_argument("--child-semantics", choices=["tmrl", "rtgym"], help=argparse.SUPPRESS)
    return parser


def main(argv: list[str] | None = None) -> None:
    args = _parser().parse_args(argv)
    if args.semantics:
        compare_semantics(args)
        return
    rec = harness.Recorder("realtime_jitter", {k: v for k, v in vars(args).items() if k != "rtgym_python"})
    for busy in [False, True] if args.both else [args.busy]:
        measure(args, busy, rec)
    rec.print_table(ratios=[("ours", "rtgym")])
    rec.close()


def child_main(argv: list[str]) -> None:
    """``--child IMPL ...`` (one timing run) or ``--child-semantics IMPL``."""
    args = _parser().parse_args(argv)
    if args.child:
        child(args.child, args.steps, args.warmup, args.inference_ms, args.period)
    elif args.child_semantics:
        child_semantics(args.child_semantics)

