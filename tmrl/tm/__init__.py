"""TrackMania 2020: the game-facing pieces of the pipeline.

Submodules (each imported on demand; importing ``tmrl.tm`` imports none of ``mss``, ``vgamepad``
or ``cv2``):

- :mod:`tmrl.tm.openplanet`: TCP client of the TMRL_GrabData OpenPlanet plugin (telemetry).
- :mod:`tmrl.tm.capture`: screen capture of the game window (mss, real window geometry).
- :mod:`tmrl.tm.control`: virtual Xbox 360 gamepad (vgamepad) and keyboard fallback.
- :mod:`tmrl.tm.record`: reward-trajectory recording, resampling and safe loading.
- :mod:`tmrl.tm.doctor`: setup checks behind ``--doctor``.
- :mod:`tmrl.tm.resources`, :mod:`tmrl.tm.plugins`, :mod:`tmrl.tm.install`: ``--install --env
  tm20lidar|tm20full``: the original's resources archive, the OpenPlanet plugins, the game side.
- :mod:`tmrl.tm.guide`: the text of ``python -m tmrl --help trackmania``.
- :mod:`tmrl.tm.tools`: entry functions for the CLI (``--doctor``, ``--record-reward``, ...).

Nothing in the generic pipeline imports this package.
"""

from __future__ import annotations

TRACKMANIA_EXTRA_HINT = 'pip install ".[trackmania]" in this project\'s checkout (PyPI\'s "tmrl" is another project)'

__all__ = ["TRACKMANIA_EXTRA_HINT"]
