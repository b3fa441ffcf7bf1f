"""A custom real-time interface, from scratch: a heater in a room, controlled in real time.

    python examples/custom_interface.py                      # 3 episodes of 100 steps at 50 Hz
    python examples/custom_interface.py --time-step 0.01 --episodes 2 --steps 50

The "device" is a few lines of physics that follow the wall clock: the room warms up while the
heater is on and cools down towards the outside temperature, whether the policy is thinking or
not. The interface exposes it to tmrl.realtime; the real-time checker validates the interface
before anything runs; then the Gymnasium environment made from the rtgym-style config is driven
by a proportional controller, and the environment's timing benchmarks are printed.

Exit status 1 when the checker finds a problem with the interface.
"""

from __future__ import annotations

import argparse
import pprint
import sys
import time

import gymnasium
import numpy as np
from gymnasium import spaces

import tmrl.realtime as rt
from tmrl.realtime import check

# --8<-- [start:device]
OUTSIDE = 10.0  # °C


class Heater:
    """A room with a heater, simulated against the wall clock (no thread: the temperature is
    brought up to date whenever the device is touched)."""

    def __init__(self, heat_rate: float = 40.0, cooling_time: float = 0.5) -> None:
        self.heat_rate = heat_rate  # °C per second at full power
        self.cooling_time = cooling_time  # seconds: time constant of the losses to the outside
        self.temperature = OUTSIDE
        self.power = 0.0
        self._last = time.perf_counter()

    def _advance(self) -> None:
        now = time.perf_counter()
        dt, self._last = now - self._last, now
        equilibrium = OUTSIDE + self.heat_rate * self.cooling_time * self.power
        self.temperature = equilibrium + (self.temperature - equilibrium) * np.exp(-dt / self.cooling_time)

    def set_power(self, power: float) -> None:
        self._advance()
        self.power = float(np.clip(power, 0.0, 1.0))

    def read_temperature(self) -> float:
        self._advance()
        return round(self.temperature, 1)  # a thermometer with 0.1 °C resolution
# --8<-- [end:device]


# --8<-- [start:interface]
class ThermostatInterface(rt.RealTimeGymInterface):
    """Observation: (room temperature, target temperature) in °C; action: heater power in [0, 1];
    reward: minus the distance to the target. Episodes never terminate (ep_max_length truncates)."""

    def __init__(self, seed: int | None = None) -> None:
        self.heater = Heater()
        self.rng = np.random.default_rng(seed)
        self.target = 20.0

    def get_observation_space(self) -> spaces.Tuple:
        temperature = spaces.Box(-50.0, 100.0, shape=(1,), dtype=np.float32)
        return spaces.Tuple((temperature, temperature))  # room, target

    def get_action_space(self) -> spaces.Box:
        return spaces.Box(0.0, 1.0, shape=(1,), dtype=np.float32)

    def get_default_action(self) -> np.ndarray:
        return np.zeros(1, dtype=np.float32)  # heater off

    def _obs(self) -> list[np.ndarray]:
        room = np.array([self.heater.read_temperature()], dtype=np.float32)
        return [room, np.array([self.target], dtype=np.float32)]

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[list, dict]:
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.heater.temperature = OUTSIDE  # a cold room (the real thing would wait() for it)
        self.target = float(self.rng.uniform(15.0, 25.0))
        return self._obs(), {}

    def send_control(self, control: np.ndarray | None) -> None:
        if control is not None:  # must return at once: the time step is running
            self.heater.set_power(float(control[0]))

    def get_obs_rew_terminated_info(self) -> tuple[list, float, bool, dict]:
        obs = self._obs()
        return obs, -abs(float(obs[0][0]) - self.target), False, {}

    def wait(self) -> None:
        self.heater.set_power(0.0)  # between episodes: heater off
# --8<-- [end:interface]


def controller(obs: tuple) -> np.ndarray:
    """Proportional control of the power around a fixed bias (obs = room, target, last action)."""
    room, target = float(obs[0][0]), float(obs[1][0])
    return np.clip([0.5 + 0.25 * (target - room)], 0.0, 1.0).astype(np.float32)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--steps", type=int, default=100, help="steps per episode (ep_max_length)")
    parser.add_argument("--time-step", type=float, default=0.02, help="time step duration in seconds")
    args = parser.parse_args()

    # --8<-- [start:config]
    config = dict(
        rt.DEFAULT_CONFIG_DICT,
        interface=ThermostatInterface,
        interface_kwargs={"seed": 0},
        time_step_duration=args.time_step,
        start_obs_capture=args.time_step,  # capture at the end of the time step
        ep_max_length=args.steps,
        act_buf_len=1,
        benchmark=True,
    )
    # --8<-- [end:config]

    # --8<-- [start:check]
    # Everything at once, on virtual time so that a busy machine cannot make it fail: methods,
    # spaces, reset, send_control, capture, then 10 steps of the real environment.
    problems = rt.check_realtime_interface(config, n_steps=10, clock=rt.FakeClock())
    # One check alone, on the real clock: does a capture fit in the time step?
    interface = ThermostatInterface()
    interface.reset()
    timing = check.check_capture(interface, interface.get_observation_space(), config)
    # --8<-- [end:check]
    for problem in problems:
        print("interface check:", problem)
    if problems:
        return 1
    print("interface check: no problem found")
    for problem in timing:  # a real-clock measurement: a busy machine can make it fail
        print("capture timing:", problem)
    if not timing:
        print("capture timing: a capture fits in the time step")

    # --8<-- [start:run]
    env = gymnasium.make("real-time-gym-v1", config=config)
    try:
        for episode in range(1, args.episodes + 1):
            obs, _ = env.reset(seed=episode)
            ret, steps, done = 0.0, 0, False
            while not done:
                obs, rew, terminated, truncated, _ = env.step(controller(obs))
                ret += rew
                steps += 1
                done = terminated or truncated
            print(f"episode {episode}: {steps} steps, return {ret:.2f}, "
                  f"room {obs[0][0]:.1f} °C, target {obs[1][0]:.1f} °C")
        print("benchmarks (average, average deviation) in seconds:")
        pprint.pprint(env.unwrapped.benchmarks())
    finally:
        env.close()
    # --8<-- [end:run]
    return 0


if __name__ == "__main__":
    sys.exit(main())
