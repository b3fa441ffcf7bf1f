"""The policy interface that rollout workers call: :class:`ActorModule` and its PyTorch flavour
:class:`TorchActorModule`.

A worker calls ``actor.act_(obs, test)`` once per environment step with one raw observation (a
tuple of arrays, or any nested tuple/list/dict of arrays and numbers) and expects a NumPy action.
The trainer ships weights by calling ``actor.save(path)`` and sending the file's bytes; the
worker writes them to disk and calls ``actor.load(path, device)``. The built-in format is
safetensors (tensors only, nothing executable); a subclass may use its own data-only format
(the tutorial's actor writes JSON) and everything else works unchanged.
"""

from __future__ import annotations

import logging
import os
from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from tmrl.errors import UserError
from tmrl.util import atomic_write_bytes

__all__ = ["ActorModule", "TorchActorModule", "WeightsError", "collate_one"]

logger = logging.getLogger(__name__)


class WeightsError(UserError):
    """A weights file cannot be loaded into this actor (corrupt, foreign, or another model)."""


class ActorModule(ABC):
    """The policy as rollout workers see it.

    Subclasses implement :meth:`act`, and :meth:`save` / :meth:`load` when they hold weights
    that the trainer updates. ``__init__`` must accept ``observation_space`` and
    ``action_space`` (positionally or by keyword) and call ``super().__init__``.

    Args:
        observation_space: the environment's (preprocessed) observation space.
        action_space: the environment's action space.
    """

    def __init__(self, observation_space: Any, action_space: Any) -> None:
        # Cooperative: with TorchActorModule this runs torch.nn.Module.__init__ first, so that
        # the attributes below are set on an initialised module.
        super().__init__()
        self.observation_space = observation_space
        self.action_space = action_space

    @abstractmethod
    def act(self, obs: Any, test: bool = False) -> np.ndarray:
        """Compute an action from an observation.

        Args:
            obs: the observation (collated as a batch of one for :class:`TorchActorModule`).
            test: True in test episodes (act deterministically), False in training episodes.

        Returns:
            The action, a NumPy array.
        """
        raise NotImplementedError

    def act_(self, obs: Any, test: bool = False) -> np.ndarray:
        """What the worker calls each step; here simply :meth:`act`.

        Args:
            obs: one observation, as the environment returns it (after the worker's preprocessor).
            test: act deterministically (test episodes) instead of sampling.
        """
        return self.act(obs, test=test)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the actor's weights to one file at ``path``, in a data-only format.

        Raises:
            UserError: this actor does not implement ``save`` (tmrl never pickles actors).
        """
        raise UserError(
            f"{type(self).__name__} has no save(): implement save(path) and load(path, device) with a "
            "data-only format (for example JSON or safetensors), or subclass TorchActorModule"
        )

    def load(self, path: str | os.PathLike[str], device: Any) -> ActorModule:
        """Load weights written by :meth:`save` and return the loaded actor (usually ``self``).

        Args:
            path: the file written by :meth:`save`.
            device: where the loaded actor runs (``"cpu"``, ``"cuda"``...).

        Raises:
            UserError: this actor does not implement ``load``.
        """
        raise UserError(
            f"{type(self).__name__} has no load(): implement save(path) and load(path, device) with a "
            "data-only format (for example JSON or safetensors), or subclass TorchActorModule"
        )

    def to_device(self, device: Any) -> ActorModule:
        """Move whatever needs moving to ``device`` and return the actor; a no-op here."""
        return self


def collate_one(obs: Any, device: torch.device | str | None = None) -> Any:
    """Turn one observation into a batch of one on ``device``.

    Arrays and tensors get a leading dimension of size 1; Python and NumPy scalars become
    tensors of shape ``(1,)``; tuples, lists and mappings keep their structure.

    Args:
        obs: a nested tuple/list/dict of arrays, tensors and numbers.
        device: where the tensors go (None: stay on the CPU).

    Returns:
        The same structure with batched tensors as leaves.

    Raises:
        UserError: a leaf is not a number, array or tensor.
    """
    if isinstance(obs, torch.Tensor):
        return obs.unsqueeze(0).to(device)
    if isinstance(obs, np.ndarray):
        arr = obs if obs.flags.c_contiguous and obs.flags.writeable else np.array(obs)
        return torch.from_numpy(arr).unsqueeze(0).to(device)
    if isinstance(obs, (bool, int, float, np.number, np.bool_)):
        return torch.as_tensor(np.asarray([obs])).to(device)
    if isinstance(obs, (tuple, list)):
        return type(obs)(collate_one(o, device) for o in obs)
    if isinstance(obs, Mapping):
        mapping_cls: Any = type(obs)
        return mapping_cls((k, collate_one(v, device)) for k, v in obs.items())
    raise UserError(
        f"observation element of type {type(obs).__name__} cannot be fed to a TorchActorModule: "
        "make the obs_preprocessor return arrays, numbers, or tuples/dicts of them"
    )


class TorchActorModule(ActorModule, torch.nn.Module):
    """An :class:`ActorModule` that is a ``torch.nn.Module``.

    :meth:`act_` collates the worker's single observation into a batch of one on ``device`` and
    calls :meth:`act` under ``torch.no_grad()``; :meth:`act` must return a NumPy array.
    ``save``/``load`` store the state dict as safetensors, written atomically.

    Args:
        observation_space: the environment's (preprocessed) observation space.
        action_space: the environment's action space.
        device: where observations are collated for :meth:`act`; it follows the module wherever it
            moves (``to()``, ``cuda()``, ``cpu()``, also when the move is made on a module that holds
            this actor).
    """

    def __init__(self, observation_space: Any, action_space: Any, device: Any = "cpu") -> None:
        super().__init__(observation_space, action_space)
        self.device = device

    def act_(self, obs: Any, test: bool = False) -> np.ndarray:
        """Collate one observation on ``self.device`` and run :meth:`act` without gradients.

        Args:
            obs: one observation (not batched).
            test: act deterministically instead of sampling.
        """
        batch = collate_one(obs, self.device)
        with torch.no_grad():
            return self.act(batch, test=test)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the state dict to ``path`` as safetensors (:meth:`to_bytes`), atomically."""
        atomic_write_bytes(path, self.to_bytes())

    def to_bytes(self) -> bytes:
        """The bytes :meth:`save` writes: the state dict as safetensors. The trainer broadcasts
        them without a file in between when ``save`` is this class's own."""
        from safetensors.torch import save

        # Clone: safetensors refuses tensors that share storage, and parameters handed out by
        # copy_shared or fused optimizers may.
        tensors = {k: v.detach().to("cpu", copy=True).contiguous() for k, v in self.state_dict().items()}
        return save(tensors)

    def load(self, path: str | os.PathLike[str], device: Any) -> TorchActorModule:
        """Load weights written by :meth:`save` into this module, move it to ``device``.

        Args:
            path: the safetensors file written by :meth:`save`.
            device: where the module is moved.

        Returns:
            ``self``.

        Raises:
            WeightsError: the file is not safetensors, or its tensors do not match this model.
        """
        from safetensors import SafetensorError
        from safetensors.torch import load

        with open(path, "rb") as f:
            data = f.read()
        try:
            state = load(data)
        except (SafetensorError, ValueError, OSError) as e:
            raise WeightsError(
                f"weights file {os.fspath(path)} is not a tmrl safetensors file ({e}): "
                "delete it and let the trainer send fresh weights"
            ) from None
        try:
            self.load_state_dict(state)
        except RuntimeError as e:
            first = str(e).strip().splitlines()
            detail = " ".join(line.strip() for line in first[:3])
            raise WeightsError(
                f"weights file {os.fspath(path)} does not fit {type(self).__name__} ({detail[:300]}): "
                "the worker and the trainer must use the same model configuration"
            ) from None
        self.to_device(device)
        return self

    def to(self, *args: Any, **kwargs: Any) -> TorchActorModule:
        """``torch.nn.Module.to`` that also records the new device in ``self.device``."""
        device, _, _, _ = torch._C._nn._parse_to(*args, **kwargs)
        if device is not None:
            self.device = device
        return super().to(*args, **kwargs)

    def _apply(self, fn: Any, *args: Any, **kwargs: Any) -> TorchActorModule:
        # why: torch calls _apply on every module of a tree when any ancestor moves (.to, .cuda,
        # .cpu, to_empty), never `to` on the submodules: an actor inside a moved actor-critic must
        # learn its new device here, or act_() collates observations on the old one.
        out = super()._apply(fn, *args, **kwargs)
        moved = fn(torch.empty(0, device=self.device)).device  # where the move sends our tensors
        if moved != torch.device(self.device):  # a dtype-only move keeps the device as it was given
            self.device = moved
        return out

    def to_device(self, device: Any) -> TorchActorModule:
        """Move the module to ``device`` and return it."""
        return self.to(device)
