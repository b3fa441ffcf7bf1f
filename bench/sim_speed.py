"""Simulator steps per second (ours), per observation type, in fast mode (no real-time clock).

    python -m bench sim_speed [--seconds 3] [--track classic] [--rounds 3]

One figure per environment: steps per second with random actions (episodes reset as they end)
and with the centre-line driver, and the physics-only rate of the race without observations.
The full observation includes rendering the 64x64 image; the lidar ones render only the pixels
along the 19 beams.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

from bench import harness


def rate(step: Callable[[], bool], reset: Callable[[], object], seconds: float) -> float:
    """Steps per second of ``step`` (True when the episode ended) over ``seconds``."""
    reset()
    n = 0
    t0 = time.perf_counter()
    while True:
        for _ in range(100):
            if step():
                reset()
        n += 100
        elapsed = time.perf_counter() - t0
        if elapsed >= seconds:
            return n / elapsed


def one_round(args: argparse.Namespace, rnd: int, rec: harness.Recorder) -> None:
    import numpy as np

    from tmrl.sim.interfaces import SimEnv
    from tmrl.sim.race import Race, follow_centre_line
    from tmrl.sim.track import make_track

    rng = np.random.default_rng(rnd)
    race = Race(make_track(args.track))
    rec.add("race only (physics + reward)", "steps_per_s", "ours",
            rate(lambda: (race.advance(rng.uniform(-1, 1, 3), 0.05), race.score())[1][1], race.reset, args.seconds),
            round=rnd, unit="1/s")
    for name in ("SIMLIDAR", "SIMLIDARPROGRESS", "SIMFULL"):
        env = SimEnv(name, track=args.track, img_hist_len=4, act_buf_len=2)
        drivers = {"random": lambda: rng.uniform(-1, 1, 3), "centre line": lambda: follow_centre_line(env.race)}
        for label, driver in drivers.items():
            def step() -> bool:
                _, _, terminated, truncated, _ = env.step(driver())  # noqa: B023 (used in this iteration)
                return terminated or truncated

            rec.add(f"{name}, {label} driver", "steps_per_s", "ours", rate(step, env.reset, args.seconds),
                    round=rnd, unit="1/s")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench sim_speed", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="measuring time per figure")
    ap.add_argument("--track", default="classic", help="track name or seed")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    rec = harness.Recorder("sim_speed", vars(args))
    for rnd in range(args.rounds):
        one_round(args, rnd, rec)
    rec.print_table(ratios=())
    rec.close()
