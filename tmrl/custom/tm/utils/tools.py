"""Compatibility names of the original ``tmrl.custom.tm.utils.tools``.

- ``TM2020OpenPlanetClient``: :class:`tmrl.tm.openplanet.OpenPlanetClient`, whose
  ``retrieve_data`` returns the frame as a NumPy array as the original's did;
- ``Lidar``: :class:`tmrl.driving.lidar.Lidar` built from an image, as the original's;
- ``save_ghost``: the request to the TMRL_SaveGhost plugin (:func:`tmrl.tm.openplanet.request_replay`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tmrl.driving.lidar import Lidar as _Lidar
from tmrl.errors import UserError
from tmrl.tm.openplanet import OpenPlanetClient, request_replay

__all__ = ["Lidar", "TM2020OpenPlanetClient", "save_ghost"]


class TM2020OpenPlanetClient(OpenPlanetClient):
    """The OpenPlanet telemetry client with tmrl 0.7's arguments (``struct_str`` is accepted and
    unused: the frame layout is the plugin's)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 9000, struct_str: str | None = None) -> None:
        super().__init__(host=host, port=port)

    def retrieve_data(self, sleep_if_empty: float = 0.01, timeout: float | None = 10.0) -> Any:  # type: ignore[override]
        """The newest telemetry frame as a float array (``sleep_if_empty`` is unused: the client
        waits on the frame itself)."""
        return np.asarray(super().retrieve_data(timeout), dtype=np.float64)


class Lidar(_Lidar):
    """The 19-beam lidar for images of the size of ``im`` (tmrl 0.7's constructor)."""

    def __init__(self, im: np.ndarray, *args: Any, **kwargs: Any) -> None:
        if isinstance(im, np.ndarray):
            super().__init__(im.shape[0], im.shape[1], *args, **kwargs)
        else:  # called again by measure() with (height, width, threshold)
            super().__init__(im, *args, **kwargs)


def save_ghost(host: str = "127.0.0.1", port: int = 10000) -> None:
    """Ask the TMRL_SaveGhost plugin to save the last race as a replay (a bare connection, as the
    original's).

    Raises:
        UserError: the plugin does not answer (the message says how to install it).
    """
    problem = request_replay(host, port)
    if problem is not None:
        raise UserError(problem)
