"""Compatibility package mirroring the original ``tmrl.tools``; no logic of its own.

- :mod:`tmrl.tools.check_environment`: ``check_env_tm20lidar``, ``check_env_tm20full``;
- :mod:`tmrl.tools.record`: ``record_reward_dist``;
- :mod:`tmrl.tools.save_replays`: ``save_replays``.

The commands ``python -m tmrl --check-environment`` and ``--record-reward`` do the same.
"""
