"""Compatibility name of the original ``tmrl.tools.save_replays``.

``save_replays(nb_replays)`` runs the worker's current weights, standalone, with the
interface's ``save_replays`` on: TrackMania saves a replay of every finished run, the simulator a
JSON file and a PNG of every completed lap (in ``replays/`` of the data folder).
"""

from __future__ import annotations

import math

__all__ = ["save_replays"]


def save_replays(nb_replays: float = math.inf) -> None:
    """Run ``nb_replays`` test episodes of the configured worker with replays saved."""
    from tmrl.roles import worker_from_config

    worker = worker_from_config(standalone=True, save_replays=True)
    try:
        worker.run_episodes(10000, nb_episodes=nb_replays)
    finally:
        worker.close()
