"""Several simulators at once: a Gymnasium vector environment of tmrl.sim environments.

    python examples/vector_env.py                          # 4 tracks, 1000 steps each, sync then async
    python examples/vector_env.py --policy random --envs 2 --steps 300
    python examples/vector_env.py --mode async --envs 8

Each sub-environment drives another track (the three named tracks, then random tracks from
seeds). The actions come from the simulator's hand-written driver (``--policy driver``, the
default), which completes laps, or are random. The same loop runs with SyncVectorEnv (all
environments in this process, one after the other) and AsyncVectorEnv (one process each), and
prints the environment steps per second of each on this machine.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import gymnasium
import numpy as np

import tmrl.sim  # noqa: F401  (registers the tmrl/Sim* ids, so that they can be made without the prefix)
from tmrl.sim.race import follow_centre_line

NAMED_TRACKS = ("oval", "classic", "technical")


# --8<-- [start:driver]
class DriverHint(gymnasium.Wrapper):
    """Puts the hand-written driver's action for the current state in ``info["driver_action"]``.

    The driver reads the car's state, which lives in the sub-environment (in another process with
    AsyncVectorEnv): computing the action there and returning it in ``info`` works for both
    vector environments, which stack each info key across sub-environments.
    """

    def _hint(self, info: dict[str, Any]) -> dict[str, Any]:
        info["driver_action"] = follow_centre_line(self.unwrapped.race)
        return info

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        return obs, self._hint(info)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, rew, terminated, truncated, info = self.env.step(action)
        return obs, rew, terminated, truncated, self._hint(info)
# --8<-- [end:driver]


# --8<-- [start:make]
def make_env(track: str | int, ep_max_length: int) -> gymnasium.Env:
    env = gymnasium.make("tmrl/SimLidar-v0", track=track, ep_max_length=ep_max_length)
    return DriverHint(env)


def env_fns(n: int, ep_max_length: int) -> list:
    """One function per sub-environment (vector environments call them, in their process)."""
    tracks = [NAMED_TRACKS[i] if i < len(NAMED_TRACKS) else 100 + i for i in range(n)]
    return [lambda t=t: make_env(t, ep_max_length) for t in tracks]
# --8<-- [end:make]


# --8<-- [start:loop]
def run(vec_env: gymnasium.vector.VectorEnv, steps: int, policy: str, seed: int = 0) -> dict[str, float]:
    """Step ``vec_env`` ``steps`` times; returns steps/s and episode statistics."""
    rng = np.random.default_rng(seed)
    n = vec_env.num_envs
    _, info = vec_env.reset(seed=seed)
    returns, finished, laps = np.zeros(n), [], 0
    t0 = time.perf_counter()
    for _ in range(steps):
        if policy == "driver":
            actions = np.asarray(info["driver_action"], dtype=np.float32)
        else:
            actions = rng.uniform(-1.0, 1.0, size=(n, 3)).astype(np.float32)
        _, rew, terminated, truncated, info = vec_env.step(actions)
        returns += rew
        # Gymnasium autoresets a finished sub-environment at its next step() (whose reward is 0).
        for i in np.flatnonzero(terminated | truncated):
            finished.append(returns[i])
            returns[i] = 0.0
        if "lap_completed" in info:
            laps += int(np.sum(info["lap_completed"] & info["_lap_completed"]))
    elapsed = time.perf_counter() - t0
    return {
        "steps_per_s": n * steps / elapsed,
        "elapsed": elapsed,
        "episodes": len(finished),
        "laps": laps,
        "mean_return": float(np.mean(finished)) if finished else float(np.mean(returns)),
    }
# --8<-- [end:loop]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=4, help="number of sub-environments")
    parser.add_argument("--steps", type=int, default=1000,
                        help="vector steps (each steps every sub-environment)")
    parser.add_argument("--policy", choices=("driver", "random"), default="driver")
    parser.add_argument("--mode", choices=("sync", "async", "both"), default="both")
    parser.add_argument("--ep-max-length", type=int, default=1000)
    args = parser.parse_args()

    fns = env_fns(args.envs, args.ep_max_length)
    modes = ("sync", "async") if args.mode == "both" else (args.mode,)
    results = {}
    for mode in modes:
        # --8<-- [start:vector]
        if mode == "sync":
            vec_env = gymnasium.vector.SyncVectorEnv(fns)  # one after the other, in this process
        else:
            vec_env = gymnasium.vector.AsyncVectorEnv(fns)  # one process each, stepped in parallel
        try:
            result = run(vec_env, args.steps, args.policy)
        finally:
            vec_env.close()
        # --8<-- [end:vector]
        results[mode] = result
        ret = ("mean return of the finished episodes" if result["episodes"]
               else "mean return so far (none finished)")
        print(f"{mode}: {args.envs} envs x {args.steps} steps in {result['elapsed']:.1f} s = "
              f"{result['steps_per_s']:.0f} steps/s | {result['episodes']} episodes ended, "
              f"{result['laps']} laps completed | {ret}: {result['mean_return']:.1f}")
    if len(results) == 2:
        print(f"async / sync speed: {results['async']['steps_per_s'] / results['sync']['steps_per_s']:.2f}")


if __name__ == "__main__":
    main()
