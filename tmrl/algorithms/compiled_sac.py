"""``ALG.COMPILE``: every agent's update through :func:`torch.compile` or CUDA graphs, checked
against eager.

Structure. An agent's update is :meth:`~tmrl.algorithms.sac.SACAgent._update_with` over the
functions its class names in ``COMPILED``, each a function of the batch: SAC, REDQ-SAC, DroQ,
TQC and DrQ have one, :meth:`~tmrl.algorithms.sac.SACAgent._update_losses` (the forward passes
of the actor, the critics and the target critics, and the losses, each agent's steps inside:
REDQ's subset, DroQ's dropout critics, TQC's quantiles, DrQ's encoder); CrossQ has two, its
critics' joint pass and loss and, after the critics' step, its policy's losses. With the mode on,
each goes through :func:`torch.compile`, which also compiles its backward graph (AOTAutograd);
the backward calls, the optimizer steps, the non-finite guard, Polyak averaging, the switches of
CrossQ's critics between training and evaluation mode, and the random draws that come from the
CPU generator (DrQ's shifts, REDQ's subset on a GPU: ``_prepare_batch``) stay eager. The
optimizers already update all their tensors in one fused (or ``foreach``) kernel and Polyak
averaging is one ``_foreach_lerp_``, so compiling them would add a long compilation for little:
the loss computation, dozens of small kernels, is what gains.

- ``"compile"``: ``torch.compile(fn, options={"fallback_random": True})``.
- ``"cudagraph"`` (CUDA only): the same with ``triton.cudagraphs`` (what ``mode="reduce-overhead"``
  sets): the forward and backward graphs are captured once and replayed, PyTorch copying each
  batch into the graph's static inputs; ``torch.compiler.cudagraph_mark_step_begin()`` starts
  each call, and the tensors kept after it (the metrics, the kept losses) are cloned out of the
  graph's memory.

Both keep PyTorch's eager random number generator (``fallback_random``), so the actions and the
dropout masks drawn in an update are those of the eager update, which makes the compiled
parameters comparable with the eager ones.

No host synchronisation is left in an update on a GPU: the non-finite guard decides on the device
(:class:`~tmrl.algorithms.guard.GuardedUpdate`), the entropy coefficient's ceiling is held with a
device flag, and the metrics stay tensors until the trainer reads them, once per round.

The check. The first update of each kind (with a policy update and without: REDQ, DroQ and CrossQ
have both) runs the eager update from the current state, restores that state (parameters,
targets, optimizers, ``log_alpha``, running statistics, update counters, the random generators,
the guard's count), runs the compiled update from it, and compares what the compiled functions
decide (:func:`outcome`: the gradients they give, the running statistics they update, the
metrics; rtol 1e-4, atol 1e-5 scaled by each tensor's largest magnitude). On a mismatch or an
exception it restores the state again, logs one warning line and runs this update and the rest of
the run as ``"off"``. Either way the state ends as if only the mode that goes on had run. One
update cannot reveal every error (a difference of the random draws shows in the updates that
follow): tests/test_compile.py compares 10 updates of each agent on the CPU and 50 on a GPU.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import torch

from tmrl.algorithms.guard import copy_state_into

__all__ = [
    "ATOL",
    "RTOL",
    "CompileState",
    "compile_mode_for",
    "compiled_functions",
    "compiled_losses",
    "first_compiled_update",
    "mismatch",
    "outcome",
]

logger = logging.getLogger("tmrl.algorithms.sac")  # the agent's own log

RTOL, ATOL = 1e-4, 1e-5
"""Tolerance of the first update's check (parameters of the compiled vs the eager update)."""

Losses = Callable[..., tuple[Any, ...]]


class CompileState:
    """What ``ALG.COMPILE`` set up for one agent: the mode it runs (``"off"`` after a fallback),
    the compiled functions (built at the first update, one per name of the agent's
    ``COMPILED``) and the kinds of update whose first one passed the check (``True``: with a
    policy update, ``False``: without). A copy (``copy.deepcopy``, pickling) keeps the mode only:
    its compiled functions would read the original agent's parameters, so the copy compiles and
    checks its own."""

    def __init__(self, mode: str) -> None:
        self.mode = mode
        self.fns: dict[str, Losses] | None = None
        self.checked: set[bool] = set()

    def __getstate__(self) -> dict[str, Any]:
        return {"mode": self.mode}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["mode"])  # type: ignore[misc]


def compile_mode_for(agent: Any, requested: str) -> str:
    """The mode ``agent`` runs: ``requested``, or ``"off"`` (with one warning line) when its update
    cannot be compiled (``agent._compile_unsupported()`` says why: a ``train`` of its own, or
    SAC's sequential order, which backpropagates twice through one forward pass)."""
    if requested == "off":
        return "off"
    why = agent._compile_unsupported()
    if why is None:
        return requested
    logger.warning("ALG.COMPILE=%r: %s, which cannot be compiled; the update runs eager", requested, why)
    return "off"


def compiled_losses(losses: Losses, mode: str) -> Losses:
    """``losses`` through :func:`torch.compile` for ``mode`` (compiled lazily, at its first call)."""
    options: dict[str, Any] = {"fallback_random": True}
    if mode == "cudagraph":
        options["triton.cudagraphs"] = True
    compiled = torch.compile(losses, options=options)
    if mode != "cudagraph":
        return compiled

    def replay(*args: Any) -> tuple[Any, ...]:
        torch.compiler.cudagraph_mark_step_begin()
        return compiled(*args)

    return replay


def compiled_functions(agent: Any, mode: str) -> dict[str, Losses]:
    """Each method of ``agent.COMPILED`` through :func:`compiled_losses`."""
    return {name: compiled_losses(getattr(agent, name), mode) for name in agent.COMPILED}


def mismatch(got: list[tuple[str, torch.Tensor | None]], expected: list[tuple[str, torch.Tensor | None]],
             rtol: float = RTOL, atol: float = ATOL) -> str | None:
    """None when every named tensor of ``got`` is close to its twin in ``expected`` (``atol``
    scaled by the largest magnitude of the expected tensor when above 1; NaN equal to NaN; None
    equal to None only), else what differs."""
    for (name, g), (_, e) in zip(got, expected):
        if g is None or e is None:
            if g is not e:
                return f"differs from the eager update ({name}: {'none' if g is None else 'one'} where eager has " \
                       f"{'none' if e is None else 'one'})"
            continue
        scale = max(1.0, float(e.abs().nan_to_num(0.0, 0.0, 0.0).max())) if e.numel() else 1.0
        if g.shape != e.shape or not torch.allclose(g, e, rtol=rtol, atol=atol * scale, equal_nan=True):
            worst = float((g - e).abs().max()) if g.shape == e.shape else math.inf
            return f"differs from the eager update ({name}, max abs difference {worst:.3g})"
    return None


def outcome(agent: Any, metrics: dict[str, Any]) -> list[tuple[str, torch.Tensor | None]]:
    """What an update's compiled functions decide, as named copies: the gradients they gave each
    parameter (and log(alpha)), the model's floating-point buffers (running statistics, which
    their forward passes update) and the update's tensor metrics. The optimizer steps and Polyak
    averaging that follow are the same eager code in every mode, so these are what the first
    update's check compares, rather than the parameters after the steps: Adam turns gradients
    that are zero up to rounding (the bias of a unit that batch normalisation makes irrelevant,
    in CrossQ's critics) into steps of +-lr whose sign is the rounding's."""
    out: list[tuple[str, torch.Tensor | None]] = []
    named = list(agent.model.named_parameters())
    if agent.log_alpha is not None:
        named.append(("log_alpha", agent.log_alpha))
    for name, p in named:
        out.append((f"gradient of {name}", None if p.grad is None else p.grad.detach().clone()))
    out += [(f"buffer {name}", b.detach().clone()) for name, b in agent.model.named_buffers() if b.is_floating_point()]
    out += [(f"metric {k}", v.detach().float().clone()) for k, v in metrics.items() if isinstance(v, torch.Tensor)]
    return out


def first_compiled_update(agent: Any, batch: tuple, update_policy: bool) -> dict[str, Any]:
    """The first compiled update of ``agent`` of its kind (``update_policy``), checked against the
    eager one (module docstring)."""
    st: CompileState = agent._compile_state
    assert st.fns is not None
    snapshot = _snapshot(agent)
    eager = outcome(agent, agent._update_with(agent._eager_functions(), batch, update_policy))
    _restore(agent, snapshot)
    try:
        metrics = agent._update_with(st.fns, batch, update_policy)
        problem = mismatch(outcome(agent, metrics), eager)
    except Exception as e:  # noqa: BLE001 - any failure of the compiled update means eager
        problem = f"failed ({type(e).__name__}: {' '.join(str(e).split())[:160]})"
    if problem is None:
        st.checked.add(update_policy)
        return metrics
    logger.warning("ALG.COMPILE=%r: the compiled update %s; the update falls back to eager", st.mode, problem)
    _restore(agent, snapshot)
    st.mode, st.fns = "off", None
    return agent._update_off(batch, update_policy)


def _snapshot(agent: Any) -> dict[str, Any]:
    rng: dict[str, Any] = {"cpu": torch.get_rng_state()}
    if agent.device.type == "cuda":
        rng["cuda"] = torch.cuda.get_rng_state(agent.device)
    return {"state": copy_state_into(None, agent.state_dict()), "rng": rng, "skipped": agent.guard.skipped,
            "losses": (agent.loss_pi, agent.loss_alpha)}


def _restore(agent: Any, snapshot: dict[str, Any]) -> None:
    # A fresh copy each time: an optimizer's load_state_dict keeps the tensors it is given.
    agent.load_state_dict(copy_state_into(None, snapshot["state"]))
    torch.set_rng_state(snapshot["rng"]["cpu"])
    if "cuda" in snapshot["rng"]:
        torch.cuda.set_rng_state(snapshot["rng"]["cuda"], agent.device)
    agent.guard.skipped = snapshot["skipped"]
    agent.loss_pi, agent.loss_alpha = snapshot["losses"]
