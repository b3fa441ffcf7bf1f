"""Fly the simulated drone in real time (the rtgym tutorial, on tmrl.realtime).

    python examples/realtime_drone.py            # 20 Hz, 3 episodes of up to 100 steps
    python examples/realtime_drone.py --fast     # 200 Hz, for a quick check

The policy is a proportional controller on the delayed observation; the action buffer in the
observation lets a learned policy do better. Prints each episode's return and the environment's
duration benchmarks.
"""

from __future__ import annotations

import argparse
import pprint

import gymnasium
import numpy as np

import tmrl.realtime as rt
from tmrl.realtime.timeouts import summarised_timeouts


def controller(obs: tuple) -> np.ndarray:
    """Head for the target: velocity proportional to the observed offset."""
    offset = np.concatenate((obs[2] - obs[0], obs[3] - obs[1]))
    return np.clip(offset * 5.0, -2.0, 2.0).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--fast", action="store_true", help="10x shorter time steps and delays")
    parser.add_argument("--ts", action="store_true", help="use real-time-gym-ts-v1 (one interface thread)")
    args = parser.parse_args()

    config = rt.drone_config(fast=args.fast, benchmark=True)
    problems = rt.check_realtime_interface(config, n_steps=3)
    for problem in problems:  # timing problems can come from a busy machine: report, go on
        print("interface check:", problem)

    env = gymnasium.make("real-time-gym-ts-v1" if args.ts else "real-time-gym-v1", config=config)
    print("observation space:", env.observation_space)
    print("action space:", env.action_space)
    try:
        # a busy machine makes time steps late: one line per 10 s says how many, not one per step
        with summarised_timeouts():
            for episode in range(1, args.episodes + 1):
                obs, _ = env.reset(seed=episode)
                ret, steps, terminated, truncated = 0.0, 0, False, False
                while not (terminated or truncated):
                    obs, rew, terminated, truncated, _ = env.step(controller(obs))
                    ret += rew
                    steps += 1
                outcome = "reached the target" if terminated else "truncated"
                print(f"episode {episode}: {steps} steps, return {ret:.3f}, {outcome}")
        print("benchmarks (average, average deviation) in seconds:")
        pprint.pprint(env.unwrapped.benchmarks())
    finally:
        env.close()


if __name__ == "__main__":
    main()
