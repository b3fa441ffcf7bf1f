"""Real-time Gymnasium environments (the rtgym 0.16 semantics, with a better clock).

Implement :class:`RealTimeGymInterface` for your device, copy :data:`DEFAULT_CONFIG_DICT`, set its
``"interface"``, and make the environment::

    import gymnasium, tmrl.realtime
    config = dict(tmrl.realtime.DEFAULT_CONFIG_DICT, interface=MyInterface)
    env = gymnasium.make("real-time-gym-v1", config=config)

Importing this package registers four Gymnasium ids (and does nothing else):

* ``real-time-gym-v1`` and ``real-time-gym-ts-v1``, unless already registered (by the rtgym
  package, when it was imported first: then those ids give rtgym's environments);
* ``tmrl/real-time-gym-v1`` and ``tmrl/real-time-gym-ts-v1``, always tmrl's.

The checks of :func:`check_realtime_interface` can also be called one by one from
:mod:`tmrl.realtime.check`. See docs/realtime.md.
"""

from __future__ import annotations

from tmrl.realtime.benchmark import (
    BenchmarkObserver,
    NullObserver,
    PolyakBenchmark,
    StepObserver,
    TraceBenchmark,
)
from tmrl.realtime.check import check_realtime_interface
from tmrl.realtime.clock import Clock, FakeClock, PerfCounterClock
from tmrl.realtime.drone import DroneInterface, DummyRCDrone, drone_config
from tmrl.realtime.env import (
    BenchmarkDisabledError,
    RealTimeEnv,
    RealTimeEnvTS,
    StepAfterDoneError,
    TimeStepTimeoutWarning,
)
from tmrl.realtime.interface import CONFIG_KEYS, DEFAULT_CONFIG_DICT, RealTimeGymInterface

__all__ = [
    "CONFIG_KEYS",
    "DEFAULT_CONFIG_DICT",
    "ENV_IDS",
    "BenchmarkDisabledError",
    "BenchmarkObserver",
    "Clock",
    "DroneInterface",
    "DummyRCDrone",
    "FakeClock",
    "NullObserver",
    "PerfCounterClock",
    "PolyakBenchmark",
    "RealTimeEnv",
    "RealTimeEnvTS",
    "RealTimeGymInterface",
    "StepAfterDoneError",
    "StepObserver",
    "TimeStepTimeoutWarning",
    "TraceBenchmark",
    "check_realtime_interface",
    "drone_config",
]

ENV_IDS: dict[str, str] = {
    "real-time-gym-v1": "tmrl.realtime.env:RealTimeEnv",
    "real-time-gym-ts-v1": "tmrl.realtime.env:RealTimeEnvTS",
    "tmrl/real-time-gym-v1": "tmrl.realtime.env:RealTimeEnv",
    "tmrl/real-time-gym-ts-v1": "tmrl.realtime.env:RealTimeEnvTS",
}
"""Gymnasium id -> entry point registered by this package."""


def _register() -> None:
    from gymnasium.envs.registration import register, registry

    for env_id, entry_point in ENV_IDS.items():
        if env_id not in registry:
            register(id=env_id, entry_point=entry_point)


_register()
