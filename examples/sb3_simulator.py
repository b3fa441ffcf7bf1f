"""tmrl's environments trained by another RL library: Stable-Baselines3's SAC.

    python examples/sb3_simulator.py --env sim --steps 20000      # the built-in racing simulator
    python examples/sb3_simulator.py --env drone --steps 5000     # the real-time drone, 20 Hz
    python examples/sb3_simulator.py --env drone --fast           # the drone at 200 Hz (quick check)

tmrl's environments are ordinary Gymnasium environments whose observations are Tuples (the
interface's elements, then the action buffer). SB3 refuses Tuple observation spaces, so each
environment is wrapped in Gymnasium's FlattenObservation (one float vector), with the lidar
and speed scaled down for the simulator. Prints the mean return of the policy before and after
training (deterministic actions). Needs ``pip install stable-baselines3``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import gymnasium
import numpy as np
from gymnasium.wrappers import FlattenObservation, TransformObservation
from stable_baselines3 import SAC
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor

import tmrl.realtime as rt


# --8<-- [start:wrap]
def flatten_for_sb3(env: gymnasium.Env, scales: list[float] | None = None) -> gymnasium.Env:
    """Tuple observation -> one float32 vector (what SB3's MlpPolicy takes), element ``i`` of the
    Tuple multiplied by ``scales[i]`` (default: no scaling)."""
    space = env.observation_space
    env = FlattenObservation(env)
    if scales is not None:
        factor = gymnasium.spaces.flatten(
            space, tuple(np.full(sub.shape, k, dtype=np.float32) for sub, k in zip(space.spaces, scales))
        )
        box = env.observation_space
        scaled = gymnasium.spaces.Box(box.low * factor, box.high * factor, dtype=np.float32)
        env = TransformObservation(env, lambda obs: (obs * factor).astype(np.float32), scaled)
    return Monitor(env)  # SB3's episode statistics (evaluate_policy reads them)
# --8<-- [end:wrap]


def make_env(name: str, args: argparse.Namespace) -> tuple[gymnasium.Env, dict]:
    """The wrapped environment and the SAC arguments that suit it."""
    if name == "sim":
        # --8<-- [start:sim]
        env = gymnasium.make("tmrl.sim:tmrl/SimLidar-v0", track=args.track, img_hist_len=4, act_buf_len=2,
                             ep_max_length=args.ep_len)
        # speed (km/h) and lidar (pixels, up to ~400) x 0.01; the two past actions as they are
        env = flatten_for_sb3(env, scales=[0.01, 0.01, 1.0, 1.0])
        sac_kwargs = {"learning_starts": min(1000, args.steps // 2)}  # SAC steps the env, then learns
        # --8<-- [end:sim]
        return env, sac_kwargs
    # --8<-- [start:drone]
    config = rt.drone_config(fast=args.fast, wait_on_done=True)
    env = flatten_for_sb3(gymnasium.make("real-time-gym-v1", config=config))
    # The drone does not wait for the learner: learn between episodes (after each episode, as many
    # gradient steps as it had steps), never during one. wait_on_done marks the pause, so the late
    # first step of the next episode restarts the clock without a timeout warning.
    sac_kwargs = {"train_freq": (1, "episode"), "gradient_steps": -1,
                  "learning_starts": min(200, args.steps // 2)}
    # --8<-- [end:drone]
    return env, sac_kwargs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=("sim", "drone"), default="sim")
    parser.add_argument("--steps", type=int, default=None,
                        help="training steps (default: sim 20000, drone 5000)")
    parser.add_argument("--eval-episodes", type=int, default=3)
    parser.add_argument("--track", default="oval", help="sim: track name or seed")
    parser.add_argument("--ep-len", type=int, default=500, help="sim: steps per episode")
    parser.add_argument("--fast", action="store_true", help="drone: 10x shorter time steps")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.steps is None:
        args.steps = 20000 if args.env == "sim" else 5000

    env, sac_kwargs = make_env(args.env, args)
    print("observation given to SB3: a Box of shape", env.observation_space.shape)
    late = 0
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", rt.TimeStepTimeoutWarning)
            # --8<-- [start:train]
            model = SAC("MlpPolicy", env, seed=args.seed, verbose=0, **sac_kwargs)
            before, before_std = evaluate_policy(model, env, n_eval_episodes=args.eval_episodes)
            print(f"mean return before training: {before:.2f} +/- {before_std:.2f} "
                  f"({args.eval_episodes} episodes)")
            t0 = time.perf_counter()
            model.learn(total_timesteps=args.steps)
            elapsed = time.perf_counter() - t0
            after, after_std = evaluate_policy(model, env, n_eval_episodes=args.eval_episodes)
            print(f"mean return after {args.steps} steps: {after:.2f} +/- {after_std:.2f} "
                  f"({args.eval_episodes} episodes)")
            # --8<-- [end:train]
        late = sum(issubclass(w.category, rt.TimeStepTimeoutWarning) for w in caught)
    finally:
        env.close()
    print(f"training: {args.steps} steps in {elapsed:.1f} s ({args.steps / elapsed:.0f} steps/s)")
    if args.env == "drone":
        print(f"time steps that came late: {late}")


if __name__ == "__main__":
    main()
