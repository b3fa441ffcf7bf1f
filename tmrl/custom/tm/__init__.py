"""Compatibility package mirroring the original ``tmrl.custom.tm`` (TrackMania); no logic of its own.

The game-facing code lives in :mod:`tmrl.tm` and the pieces shared with the simulator in
:mod:`tmrl.driving`. Importing these modules needs none of the TrackMania extras; using the game
needs ``pip install ".[trackmania]" in the checkout of this project`` (the error says so).
"""
