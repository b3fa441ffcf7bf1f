"""Simulator steps per second, per observation type, in fast mode (no real-time clock).

Usage: python bench/sim_speed.py [--seconds 3] [--track classic]

Prints one line per environment: steps per second with random actions (episodes reset as they
end) and with the centre-line driver, and the physics-only rate of the race without
observations. The full observation includes rendering the 64x64 image; the lidar ones render only
the pixels along the 19 beams. Run it on an idle machine and report `uptime` beside the figures.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def rate(step, reset, seconds: float) -> float:
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="measuring time per case")
    parser.add_argument("--track", default="classic", help="track name or seed")
    args = parser.parse_args()

    from tmrl.sim.interfaces import SimEnv
    from tmrl.sim.race import Race, follow_centre_line
    from tmrl.sim.track import make_track

    rng = np.random.default_rng(0)
    print(f"load average: {os.getloadavg()[0]:.2f} (1 min), cpus: {os.cpu_count()}")
    race = Race(make_track(args.track))
    r = rate(lambda: (race.advance(rng.uniform(-1, 1, 3), 0.05), race.score())[1][1], race.reset, args.seconds)
    print(f"{'race only (physics + reward)':34s} {r:9.0f} steps/s")
    for name in ("SIMLIDAR", "SIMLIDARPROGRESS", "SIMFULL"):
        env = SimEnv(name, track=args.track, img_hist_len=4, act_buf_len=2)

        def random_step() -> bool:
            _, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 3))
            return terminated or truncated

        def driver_step() -> bool:
            _, _, terminated, truncated, _ = env.step(follow_centre_line(env.race))
            return terminated or truncated

        r_rand = rate(random_step, env.reset, args.seconds)
        r_drive = rate(driver_step, env.reset, args.seconds)
        print(f"{name:34s} {r_rand:9.0f} steps/s random, {r_drive:9.0f} steps/s driving")


if __name__ == "__main__":
    main()
