"""``ALG.COMPILE``: SAC's update through :func:`torch.compile` or CUDA graphs, checked against eager.

Structure. :meth:`SACAgent._sac_losses <tmrl.algorithms.sac.SACAgent._sac_losses>` (the forward
passes of the actor, the critics and the target critics, and the three losses) goes through
:func:`torch.compile`, which also compiles its backward graph (AOTAutograd); the backward call,
the optimizer steps, the non-finite guard and Polyak averaging stay eager
(:meth:`SACAgent._update_with <tmrl.algorithms.sac.SACAgent._update_with>`). The optimizers
already update all their tensors in one fused (or ``foreach``) kernel and Polyak averaging is one
``_foreach_lerp_``, so compiling them would add a long compilation for little: the loss
computation, dozens of small kernels, is what gains.

- ``"compile"``: ``torch.compile(losses, options={"fallback_random": True})``.
- ``"cudagraph"`` (CUDA only): the same with ``triton.cudagraphs`` (what ``mode="reduce-overhead"``
  sets): the forward and backward graphs are captured once and replayed, PyTorch copying each
  batch into the graph's static inputs; ``torch.compiler.cudagraph_mark_step_begin()`` starts
  each update, and the tensors kept after it (the metrics) are cloned out of the graph's memory.

Both keep PyTorch's eager random number generator (``fallback_random``), so the actions sampled in
an update are those of the eager update, which makes the compiled parameters comparable with the
eager ones.

Host synchronisation left in a compiled update: the non-finite guard reads one boolean per update
(:class:`~tmrl.algorithms.guard.NonFiniteGuard`) and, with ``alpha_max`` set, the entropy
coefficient is read once before its step. The metrics stay tensors until the trainer reads them.

The check. The first update runs the eager update from the current state, restores that state
(parameters, targets, optimizers, ``log_alpha``, the random generators, the guard's count), runs
the compiled update from it, and compares the parameters (rtol 1e-4, atol 1e-5). On a mismatch or
an exception it restores the state again, logs one warning line and runs this update and the rest
of the run as ``"off"``. Either way the state ends as if only the mode that goes on had run. One
update cannot reveal every error (a compiled update that skipped Polyak averaging would move the
targets by about 1e-6 less, under the tolerance): tests/test_compile.py compares 50 updates.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import torch

from tmrl.algorithms.guard import copy_state_into

__all__ = [
    "ATOL",
    "RTOL",
    "CompileState",
    "compile_mode_for",
    "compiled_losses",
    "first_compiled_update",
    "mismatch",
]

logger = logging.getLogger("tmrl.algorithms.sac")  # the agent's own log

RTOL, ATOL = 1e-4, 1e-5
"""Tolerance of the first update's check (parameters of the compiled vs the eager update)."""

Losses = Callable[[Any], tuple[Any, ...]]


class CompileState:
    """What ``ALG.COMPILE`` set up for one agent: the mode it runs (``"off"`` after a fallback),
    the compiled loss function (built at the first update) and whether the first update's check
    passed. A copy (``copy.deepcopy``, pickling) keeps the mode only: its compiled function would
    read the original agent's parameters, so the copy compiles and checks its own."""

    def __init__(self, mode: str) -> None:
        self.mode = mode
        self.fn: Losses | None = None
        self.checked = False

    def __getstate__(self) -> dict[str, Any]:
        return {"mode": self.mode}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["mode"])  # type: ignore[misc]


def compile_mode_for(agent: Any, requested: str) -> str:
    """The mode ``agent`` runs: ``requested``, or ``"off"`` (with one warning line) when its update
    cannot be compiled yet (a step of ``SACAgent.STEPS`` overridden, or the sequential order,
    which backpropagates twice through one forward pass)."""
    if requested == "off":
        return "off"
    steps = agent.overridden_steps()
    why = None
    if steps:
        why = f"{type(agent).__name__} overrides {', '.join(steps)}"
    elif agent.update_order != "simultaneous":
        why = "update_order='sequential' backpropagates twice through one forward pass"
    if why is None:
        return requested
    logger.warning("ALG.COMPILE=%r: %s, which cannot be compiled yet; the update runs eager", requested, why)
    return "off"


def compiled_losses(losses: Losses, mode: str) -> Losses:
    """``losses`` through :func:`torch.compile` for ``mode`` (compiled lazily, at its first call)."""
    options: dict[str, Any] = {"fallback_random": True}
    if mode == "cudagraph":
        options["triton.cudagraphs"] = True
    compiled = torch.compile(losses, options=options)
    if mode != "cudagraph":
        return compiled

    def replay(batch: Any) -> tuple[Any, ...]:
        torch.compiler.cudagraph_mark_step_begin()
        return compiled(batch)

    return replay


def mismatch(got: list[torch.Tensor], expected: list[torch.Tensor], rtol: float = RTOL,
             atol: float = ATOL) -> str | None:
    """None when every tensor of ``got`` is close to its twin in ``expected``, else what differs."""
    for i, (g, e) in enumerate(zip(got, expected)):
        if not torch.allclose(g.detach(), e, rtol=rtol, atol=atol):
            worst = float((g.detach() - e).abs().max())
            return f"differs from the eager update (tensor {i}, max abs difference {worst:.3g})"
    return None


def first_compiled_update(agent: Any, batch: tuple) -> dict[str, Any]:
    """The first compiled update of ``agent``, checked against the eager one (module docstring)."""
    st: CompileState = agent._compile_state
    snapshot = _snapshot(agent)
    agent._update_with(agent._sac_losses, batch)
    eager = [t.detach().clone() for t in agent._checked_tensors()]
    _restore(agent, snapshot)
    try:
        metrics = agent._update_with(st.fn, batch)
        problem = mismatch(agent._checked_tensors(), eager)
    except Exception as e:  # noqa: BLE001 - any failure of the compiled update means eager
        problem = f"failed ({type(e).__name__}: {' '.join(str(e).split())[:160]})"
    if problem is None:
        st.checked = True
        return metrics
    logger.warning("ALG.COMPILE=%r: the compiled update %s; the update falls back to eager", st.mode, problem)
    _restore(agent, snapshot)
    st.mode, st.fn = "off", None
    return agent.train(batch)


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
