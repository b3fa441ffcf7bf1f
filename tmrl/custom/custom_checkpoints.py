"""Compatibility names of the original ``tmrl.custom.custom_checkpoints`` (no logic here).

tmrl 0.7 kept image datasets in a tar file beside a pickled checkpoint; here a checkpoint is a
folder that holds the replay memory itself (:mod:`tmrl.checkpoint`), so the ``*_images_dataset``
functions are the ordinary ones.
"""

from __future__ import annotations

import os
from typing import Any

from tmrl.checkpoint import dump_run_instance as dump_run_instance_images_dataset, update_run_instance

__all__ = ["dump_run_instance_images_dataset", "load_run_instance_images_dataset", "update_run_instance"]


def load_run_instance_images_dataset(checkpoint_path: str | os.PathLike[str]) -> Any:
    """The run saved at ``checkpoint_path``, restored into the configured training class
    (``config_objects.TRAINER``)."""
    from tmrl.checkpoint import load_run_instance
    from tmrl.config import config_objects

    return load_run_instance(checkpoint_path, config_objects.TRAINER)
