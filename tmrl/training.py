"""The training-algorithm interface: :class:`TrainingAgent`.

The training loop (:mod:`tmrl.training_offline`) calls ``agent.train(batch)`` once per update and
``agent.get_actor()`` whenever it broadcasts weights; the checkpoint module calls
``agent.state_dict()`` / ``agent.load_state_dict(state)``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import torch

from tmrl.actor import ActorModule
from tmrl.util import cached_property

__all__ = ["TrainingAgent"]


class TrainingAgent(ABC):
    """A training algorithm.

    Subclasses implement :meth:`train` and :meth:`get_actor`, take at least
    ``observation_space``, ``action_space`` and ``device`` in ``__init__`` and call
    ``super().__init__``.

    Args:
        observation_space: the (preprocessed) observation space.
        action_space: the action space.
        device: where training happens and batches live (``"cpu"``, ``"cuda:0"``, ...).
    """

    def __init__(self, observation_space: Any, action_space: Any, device: Any) -> None:
        self.observation_space = observation_space
        self.action_space = action_space
        self.device = device

    @abstractmethod
    def train(self, batch: tuple) -> dict[str, Any]:
        """Run one training step.

        Args:
            batch: ``(obs, act, rew, next_obs, terminated, truncated)`` collated on the device;
                bootstrap on ``terminated`` only.

        Returns:
            Metrics to log, one entry per name (numbers or 0-dim tensors).
        """
        raise NotImplementedError

    @abstractmethod
    def get_actor(self) -> ActorModule:
        """Return the current actor, to be saved and broadcast to the workers."""
        raise NotImplementedError

    # --- checkpointing ------------------------------------------------------------------------

    def _stateful_attributes(self) -> dict[str, Any]:
        cached = {
            name
            for klass in type(self).__mro__
            for name, value in vars(klass).items()
            if isinstance(value, cached_property)
        }
        return {
            name: value
            for name, value in vars(self).items()
            if name not in cached
            and isinstance(value, (torch.nn.Module, torch.optim.Optimizer, torch.Tensor))
        }

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume training.

        This default collects every attribute that is a module, an optimizer or a tensor (a user
        agent written like the tutorial's is covered without extra code), skipping cached
        properties such as ``model_nograd``, which share memory with ``model``. Built-in agents
        override it.

        Returns:
            A dict of state dicts and tensors, keyed by attribute name.
        """
        out: dict[str, Any] = {}
        for name, value in self._stateful_attributes().items():
            out[name] = value.detach().clone() if isinstance(value, torch.Tensor) else value.state_dict()
        return out

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned, in place (shared actors stay shared).

        Raises:
            KeyError: ``state`` lacks an attribute this agent has.
        """
        for name, value in self._stateful_attributes().items():
            saved = state[name]
            if isinstance(value, torch.Tensor):
                with torch.no_grad():
                    value.copy_(saved)
            else:
                value.load_state_dict(saved)
