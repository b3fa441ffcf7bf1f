"""Where the memory samples: :class:`SlotSampler` draws the slots of a batch among the valid
transitions of :class:`~tmrl.memory.episodes.EpisodeLinks`, with the memory's generator, and
saves that generator's state in checkpoints.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tmrl.errors import UserError
from tmrl.memory.episodes import EpisodeLinks

__all__ = ["SlotSampler"]


class SlotSampler:
    """Draws batches of slots of valid transitions, uniformly and with replacement, with the
    memory's generator.

    Args:
        links: the links that say which slots are valid.

    Attributes:
        links: those links.
        max_redraws: rounds of redrawing the slots whose history was overwritten before the
            memory is declared too small.
    """

    max_redraws = 64

    def __init__(self, links: EpisodeLinks) -> None:
        self.links = links

    def draw(self, rng: np.random.Generator, batch_size: int, depth: int = 1) -> np.ndarray:
        """Draw ``batch_size`` valid slots whose ``depth`` links are all still held.

        Args:
            rng: the generator to draw with (the memory's ``rng``).
            batch_size: how many slots.
            depth: how many links each transition's observations reach back.

        Returns:
            int64 array of slots.

        Raises:
            ValueError: no valid transition yet.
            UserError: the memory is too small to hold the history its transitions need.
        """
        valid = self.links.valid_slots()
        if len(valid) == 0:
            raise ValueError("cannot sample from a memory that holds no transition yet")
        slots = valid[rng.integers(0, len(valid), size=batch_size)]
        if depth <= 1:
            return slots
        for _ in range(self.max_redraws):
            bad = ~self.links.chain_ok(slots, depth)
            if not bad.any():
                return slots
            slots[bad] = valid[rng.integers(0, len(valid), size=int(bad.sum()))]
        raise UserError(
            f"memory_size={self.links.storage.capacity} is too small for histories of {depth} samples: "
            "increase memory_size"
        )

    # --- checkpoint part -----------------------------------------------------------------------

    @staticmethod
    def meta(rng: np.random.Generator) -> dict[str, Any]:
        """This part's JSON-able checkpoint keys (the state of ``rng``)."""
        return {"rng": rng.bit_generator.state}

    @staticmethod
    def restore(meta: Mapping[str, Any], rng: np.random.Generator) -> None:
        """Put ``rng`` back in its saved state (older checkpoints may lack it)."""
        if meta.get("rng") is not None:
            rng.bit_generator.state = meta["rng"]
