"""The built-in 2-D racing simulator: tracks, car dynamics, cameras and interfaces with
TrackMania's observation and action spaces.

Importing ``tmrl.sim`` registers three Gymnasium environments that step as fast as the CPU
allows (nothing is registered unless this package is imported)::

    import gymnasium
    env = gymnasium.make("tmrl.sim:tmrl/SimLidar-v0")          # or SimLidarProgress-v0, SimFull-v0
    env = gymnasium.make("tmrl.sim:tmrl/SimLidar-v0", track="technical", img_hist_len=1)

The submodules: :mod:`.track`, :mod:`.car`, :mod:`.render`, :mod:`.race`, :mod:`.interfaces`,
:mod:`.reference` (each track's physical limit and reference lap time).
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

ENV_IDS = {
    "tmrl/SimLidar-v0": "tmrl.sim.interfaces:SimLidarEnv",
    "tmrl/SimLidarProgress-v0": "tmrl.sim.interfaces:SimLidarProgressEnv",
    "tmrl/SimFull-v0": "tmrl.sim.interfaces:SimFullEnv",
}

for _env_id, _entry_point in ENV_IDS.items():
    if _env_id not in registry:
        register(id=_env_id, entry_point=_entry_point)
