"""``python -m tmrl --help trackmania``: the TrackMania setup guide, as the command prints it.

The documentation site's TrackMania page says the same at length; this text travels with the
package, so that a user who installed it has the steps without the repository.
"""

from __future__ import annotations

__all__ = ["TEXT"]

TEXT = """\
TrackMania 2020 with tmrl, from a clean Windows PC
==================================================

1. The game and OpenPlanet. Install TrackMania 2020 (free: Ubisoft Connect, Steam or the Epic
   Games Store) and OpenPlanet (https://openplanet.dev), start the game once (OpenPlanet then
   creates %USERPROFILE%\\OpenplanetNext), and install the ViGEmBus driver for the virtual gamepad
   (https://github.com/nefarius/ViGEmBus/releases).

2. This project with its trackmania extra, from its checkout (the PyPI name "tmrl" is another
   project, the original tmrl):
       pip install torch==2.13.0
       pip install ".[trackmania]"

3. The game side:
       python -m tmrl --install --env tm20lidar
   fetches the original tmrl's public resources (its release v0.6.0, resources.zip; the
   environment variable TMRL_RESOURCES_URL replaces the address), checks the archive, copies the
   signed plugins TMRL_GrabData.op and TMRL_SaveGhost.op into OpenplanetNext\\Plugins, writes the
   reward of the map tmrl-test and imports the pretrained weights. Offline, it says in one line
   what to download and where to save it; run it again afterwards. Your config.json edits are
   kept. OPENPLANET_FOLDER in config.json names the OpenplanetNext folder if it is elsewhere.

4. Start the game, load the map tmrl-test (windowed, 256x128 is set by tmrl), then
       python -m tmrl --doctor
   Each problem is one line with its fix; the exit code is 0 when nothing failed.

5. The pretrained weights drive:
       python -m tmrl --worker --test

6. Training: set RUN_NAME in config.json to a name of your own, then in three terminals (or on
   three machines with the same PASSWORD):
       python -m tmrl --server
       python -m tmrl --trainer
       python -m tmrl --worker

Another map: drive it once with `python -m tmrl --record-reward`, which writes reward\\reward.npy.
`python -m tmrl --help` lists every command; `python -m tmrl --help config` every setting.
"""
