"""What a memory's ``dataset_path`` means: the one place where a memory reads a checkpoint while it
is built (tmrl 0.7 scripts rely on the memory pre-filling itself, so this stays in the memory
rather than in the training loop).

* Every memory refuses a folder holding a pickled ``data.pkl`` (pickle can run code).
* The built-in memories (:class:`tmrl.memory.GenericTorchMemory` and its subclasses) load the
  samples of a tmrl checkpoint folder with :func:`tmrl.checkpoint.load_memory`, or start empty
  when the folder does not exist.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from tmrl.errors import UserError

__all__ = ["load_dataset", "refuse_pickled_dataset"]

# The memory package logs under one name, "tmrl.memory", as the single module it was before.
logger = logging.getLogger("tmrl.memory")


def refuse_pickled_dataset(dataset_path: str) -> None:
    """Refuse a ``dataset_path`` that holds a pickled ``data.pkl`` (tmrl 0.7's dataset format).

    Args:
        dataset_path: the memory's ``dataset_path`` (empty: nothing to check).

    Raises:
        UserError: ``dataset_path/data.pkl`` is a file.
    """
    if dataset_path and Path(dataset_path, "data.pkl").is_file():
        raise UserError(
            f"{Path(dataset_path, 'data.pkl')} is a pickled dataset, which tmrl never loads "
            "(pickle can run code): point dataset_path to a tmrl checkpoint folder or leave it empty"
        )


def load_dataset(memory: Any, dataset_path: str) -> None:
    """Pre-fill a built-in memory from the checkpoint folder ``dataset_path``; log and leave the
    memory empty when the folder does not exist.

    Args:
        memory: the memory, its parts already built.
        dataset_path: the memory's ``dataset_path`` (empty: nothing to load).

    Raises:
        tmrl.checkpoint.CheckpointError: the folder is not a readable checkpoint of this memory.
    """
    if not dataset_path:
        return
    if Path(dataset_path).exists():
        from tmrl.checkpoint import load_memory

        load_memory(memory, dataset_path)
    else:
        logger.info("no dataset at %s: starting with an empty memory", dataset_path)
