"""The critics of an actor-critic behind one interface (:class:`CriticSet`): an
:class:`~tmrl.models.EnsembleQFunction`, separate critics evaluated together
(:class:`~tmrl.models.StackedCritics`) or one by one. The agents of :mod:`tmrl.algorithms` read
their critics through it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any, cast

import torch

from tmrl.errors import UserError
from tmrl.models import EnsembleQFunction, StackedCritics

__all__ = ["CriticSet"]


class CriticSet:
    """Uniform access to the critics of an actor-critic model.

    The fast path is a model whose ``qs`` is an :class:`EnsembleQFunction`. Separate critic
    modules (``q1`` and ``q2``, or a ``ModuleList`` ``qs``: DroQ's, TQC's, CrossQ's critics, a
    model written like the tutorial's) of one MLP architecture are evaluated together by
    :class:`~tmrl.models.StackedCritics` on a GPU, one batched product per layer (fewer, larger
    kernels); on a CPU one at a time, which is faster there (stacking copies the weights at each
    call: DroQ's, TQC's and CrossQ's critic passes took 10 to 15 % longer stacked). Any other
    critics (the CNN critics, a user's own) are evaluated one at a time.

    Args:
        model: the actor-critic module.
        stack: evaluate separate critics together when they allow it; None: when their
            parameters are not on a CPU.

    Raises:
        UserError: the model has neither ``qs`` nor ``q1``/``q2``.
    """

    def __init__(self, model: torch.nn.Module, stack: bool | None = None) -> None:
        qs = getattr(model, "qs", None)
        self.ensemble: EnsembleQFunction | None = qs if isinstance(qs, EnsembleQFunction) else None
        if self.ensemble is not None:
            self.modules: list[torch.nn.Module] = []
        elif qs is not None:
            self.modules = list(qs)
        elif hasattr(model, "q1") and hasattr(model, "q2"):
            self.modules = [cast(torch.nn.Module, model.q1), cast(torch.nn.Module, model.q2)]
        else:
            raise UserError(
                f"{type(model).__name__} has no critics: an actor-critic model needs `qs` "
                "(tmrl.models.EnsembleQFunction or a ModuleList) or `q1` and `q2`"
            )
        self._params = [p for m in self.modules for p in m.parameters()]
        if stack is None:
            stack = bool(self._params) and self._params[0].device.type != "cpu"
        # Separate critics of one MLP architecture, evaluated together (None: one by one).
        self.stacked: StackedCritics | None = StackedCritics.of(self.modules) if self.modules and stack else None
        # Critics split into observation features and a head on (features, action) (the CNN
        # critics) let Q(obs, act) and Q(obs, pi) share one pass over the observation.
        self._split = bool(self.modules) and all(
            callable(getattr(m, "features", None)) and callable(getattr(m, "head", None)) for m in self.modules
        )

    def __len__(self) -> int:
        return self.ensemble.n if self.ensemble is not None else len(self.modules)

    def parameters(self) -> list[torch.nn.Parameter]:
        """The critics' parameters."""
        return list(self.ensemble.parameters()) if self.ensemble is not None else list(self._params)

    def __call__(
        self,
        obs: Any,
        act: torch.Tensor,
        members: torch.Tensor | None = None,
        detach_params: bool = False,
    ) -> torch.Tensor:
        """Q values ``(k, B)`` of the selected critics (all when ``members`` is None); with
        ``detach_params`` no gradient reaches the critics' parameters."""
        if self.ensemble is not None:
            return self.ensemble(obs, act, members=members, detach_params=detach_params)
        if self.stacked is not None:
            return self.stacked(obs, act, members=members, detach_params=detach_params)
        chosen = self.modules if members is None else [self.modules[int(i)] for i in members]
        with self._frozen() if detach_params else contextlib.nullcontext():
            return torch.stack([q(obs, act) for q in chosen])

    @contextlib.contextmanager
    def _frozen(self) -> Iterator[None]:
        flags = [p.requires_grad for p in self._params]
        for p in self._params:
            p.requires_grad_(False)
        try:
            yield
        finally:
            for p, f in zip(self._params, flags):
                p.requires_grad_(f)

    def with_policy_values(
        self, obs: Any, act: torch.Tensor, pi: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(self(obs, act), self(obs, pi, detach_params=True))`` in one go (the second is None
        when ``pi`` is None).

        Critics that expose ``features(obs)`` and ``head(features, act)`` (the CNN critics)
        compute the features of ``obs`` once for both: same values and gradients, one image pass
        per critic instead of two. The policy values see the features detached, which is exact:
        the features depend on the critic's own parameters and ``obs`` only, never on ``pi``.
        """
        if pi is None:
            return self(obs, act), None
        if not self._split:
            return self(obs, act), self(obs, pi, detach_params=True)
        feats = [m.features(obs) for m in self.modules]
        q = torch.stack([m.head(f, act) for m, f in zip(self.modules, feats)])
        with self._frozen():
            q_pi = torch.stack([m.head(f.detach(), pi) for m, f in zip(self.modules, feats)])
        return q, q_pi
