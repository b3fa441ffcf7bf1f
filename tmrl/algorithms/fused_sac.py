"""The SAC update of the standard MLP actor-critic, with the gradients written out by hand.

:class:`~tmrl.algorithms.sac.SACAgent` computes exactly the same update with autograd (the
reference: ``tests/test_fused_sac.py`` compares the two, parameter by parameter, and both with a
plain autograd SAC written from the equations). What changes is the work around the matrix
products, which on a CPU costs as much as the products themselves in an eager autograd update
of a 256x256 MLP:

- the actor runs once on ``[o; o']`` (2B rows) and the online critics once on
  ``[(o, a); (o, pi)]`` (2B rows): one product per layer instead of two;
- backward passes are products into preallocated gradient buffers; the weight gradients of the
  critics use the ``(o, a)`` rows only (the actor's loss moves the actor only), the input
  gradient of their first layer the ``pi`` rows only;
- the gradients of each optimizer live in one flat buffer: the non-finite guard is one sum per
  buffer, and PyTorch's fused Adam/AdamW kernel is called directly on the optimizer's own state
  (``state_dict()`` is unchanged), without the optimizer's Python wrapper.

It applies when the model is a :class:`~tmrl.models.MLPActorCritic` as built here (a
:class:`~tmrl.models.SquashedGaussianMLPActor` of Linear+ReLU layers and a float32
:class:`~tmrl.models.EnsembleQFunction` with ReLU), the update order is ``"simultaneous"`` and the
agent's class does not override ``train``. Any other model takes the autograd path.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from tmrl.algorithms.guard import stepped_tensors
from tmrl.models import (
    _HALF_LOG_2PI,
    LOG_STD_MAX,
    LOG_STD_MIN,
    EnsembleQFunction,
    SquashedGaussianMLPActor,
    flatten_obs,
)

__all__ = ["FusedSACUpdate", "fused_unsupported_reason"]


def fused_unsupported_reason(agent: Any) -> str | None:
    """Why ``agent`` cannot take the fused update (None: it can)."""
    overridden_steps = getattr(type(agent), "overridden_steps", None)
    if not callable(overridden_steps):
        return f"{type(agent).__name__} is not a SACAgent"
    steps = overridden_steps()
    if steps:
        return f"{type(agent).__name__} has its own {steps[0]}()"
    if agent.update_order != "simultaneous":
        return "update_order is not 'simultaneous'"
    actor = getattr(agent.model, "actor", None)
    if type(actor) is not SquashedGaussianMLPActor:
        return "the actor is not a SquashedGaussianMLPActor"
    mods = list(actor.net)
    if not mods or len(mods) % 2 or not all(
        type(m) is (nn.Linear if i % 2 == 0 else nn.ReLU) for i, m in enumerate(mods)
    ):
        return "the actor's hidden layers are not Linear+ReLU"
    ens = agent.critics.ensemble
    if type(ens) is not EnsembleQFunction:
        return "the critics are not an EnsembleQFunction"
    if type(ens.activation) is not nn.ReLU or ens.compute_dtype is not None or len(ens.weights) < 2:
        return "the critics are not float32 ReLU MLPs with a hidden layer"
    params = list(agent.model.parameters()) + list(agent.model_target.parameters())
    if agent.log_alpha is not None:
        params.append(agent.log_alpha)
    if any(p.dtype != torch.float32 or p.device != params[0].device for p in params):
        return "the parameters are not float32 on one device"
    return None


class _Grads:
    """One flat gradient buffer for the parameters of an optimizer, with a view per parameter.

    ``layout`` lists the parameters in the order they are laid out in the buffer (which may
    differ from the optimizer's); :attr:`grads` follows the optimizer's order.
    """

    def __init__(self, optimizer: torch.optim.Optimizer, layout: list[torch.Tensor]) -> None:
        self.optimizer = optimizer
        self.params: list[torch.Tensor] = [p for g in optimizer.param_groups for p in g["params"]]
        if {id(p) for p in layout} != {id(p) for p in self.params} or len(layout) != len(self.params):
            raise ValueError("the layout does not list the optimizer's parameters")
        ref = self.params[0]
        self.flat = torch.zeros(sum(p.numel() for p in layout), dtype=ref.dtype, device=ref.device)
        views: dict[int, torch.Tensor] = {}
        offset = 0
        for p in layout:
            views[id(p)] = self.flat[offset:offset + p.numel()].view_as(p)
            offset += p.numel()
        self.grads = [views[id(p)] for p in self.params]
        self._view = views
        self._direct = self._can_step_directly()

    def __getitem__(self, p: torch.Tensor) -> torch.Tensor:
        return self._view[id(p)]

    def _can_step_directly(self) -> bool:
        opt = self.optimizer
        if not isinstance(opt, torch.optim.Adam | torch.optim.AdamW) or len(opt.param_groups) != 1:
            return False
        g = opt.param_groups[0]
        return bool(g.get("fused")) and not g.get("differentiable") and not isinstance(g["lr"], torch.Tensor)

    def step(self) -> None:
        """The optimizer's step on these gradients (the same arithmetic as ``optimizer.step()``)."""
        opt = self.optimizer
        state = [opt.state.get(p) for p in self.params]
        if not self._direct or any(not s for s in state):
            # First step (the optimizer creates its state) or an optimizer without a fused kernel.
            for p, grad in zip(self.params, self.grads):
                p.grad = grad
            opt.step()
            for p in self.params:
                p.grad = None
            return
        g = opt.param_groups[0]
        steps = [s["step"] for s in state]  # type: ignore[index]
        amsgrad = bool(g["amsgrad"])
        decoupled = bool(g.get("decoupled_weight_decay", isinstance(opt, torch.optim.AdamW)))
        torch._foreach_add_(steps, 1)
        kernel = torch._fused_adamw_ if decoupled else torch._fused_adam_
        kernel(
            self.params,
            self.grads,
            [s["exp_avg"] for s in state],  # type: ignore[index]
            [s["exp_avg_sq"] for s in state],  # type: ignore[index]
            [s["max_exp_avg_sq"] for s in state] if amsgrad else [],  # type: ignore[index]
            steps,
            lr=float(g["lr"]),
            beta1=float(g["betas"][0]),
            beta2=float(g["betas"][1]),
            weight_decay=float(g["weight_decay"]),
            eps=float(g["eps"]),
            amsgrad=amsgrad,
            maximize=bool(g["maximize"]),
        )


class FusedSACUpdate:
    """The update of :meth:`SACAgent.train` for the standard MLP actor-critic (see the module's
    docstring). Build it with :meth:`for_agent`; call it like ``train``.

    Args:
        agent: the SAC agent (checked by :func:`fused_unsupported_reason`).
    """

    def __init__(self, agent: Any) -> None:
        self.agent = agent
        actor: SquashedGaussianMLPActor = agent.model.actor
        self.actor = actor
        linears = [m for m in actor.net if isinstance(m, nn.Linear)]
        self.actor_layers = [(m.weight, m.bias) for m in linears]
        self.mu, self.log_std = actor.mu_layer, actor.log_std_layer
        self.act_dim = self.mu.out_features
        ens: EnsembleQFunction = agent.critics.ensemble
        self.critic_w = list(ens.weights)
        self.critic_b = list(ens.biases)
        tens: EnsembleQFunction = agent.critics_target.ensemble
        self.target_w = list(tens.weights)
        self.target_b = list(tens.biases)
        self.n = ens.n
        self.actor_grads = self._actor_grads(agent.pi_optimizer)
        critic_layout = self.critic_w + self.critic_b
        self.critic_grads = _Grads(agent.q_optimizer, critic_layout)
        self.alpha_grads = (
            _Grads(agent.alpha_optimizer, [agent.log_alpha]) if agent.alpha_optimizer is not None else None
        )
        self._bufs: dict[str, torch.Tensor] = {}
        self._rows = -1

    def __deepcopy__(self, memo: dict) -> FusedSACUpdate:
        # A copied agent has parameters of its own: SACAgent.train rebuilds its fused update
        # when it finds one that belongs to another agent (this one).
        return self

    def _follow_optimizers(self) -> None:
        """Rebuild a gradient buffer whose optimizer the agent replaced since the last call."""
        agent = self.agent
        if self.critic_grads.optimizer is not agent.q_optimizer:
            self.critic_grads = _Grads(agent.q_optimizer, self.critic_w + self.critic_b)
        if self.actor_grads.optimizer is not agent.pi_optimizer:
            self.actor_grads = self._actor_grads(agent.pi_optimizer)
        if self.alpha_grads is not None and self.alpha_grads.optimizer is not agent.alpha_optimizer:
            self.alpha_grads = _Grads(agent.alpha_optimizer, [agent.log_alpha])

    def _actor_grads(self, optimizer: torch.optim.Optimizer) -> _Grads:
        # The head's weights (mean, then log-std) side by side in the buffer, so that one
        # product fills both gradients; likewise their biases.
        head = [self.mu.weight, self.log_std.weight, self.mu.bias, self.log_std.bias]
        grads = _Grads(optimizer, [t for wb in self.actor_layers for t in wb] + head)
        self.head_w_grad = _span(grads.flat, grads[self.mu.weight], 2 * self.mu.weight.numel()).view(
            2 * self.act_dim, -1)
        self.head_b_grad = _span(grads.flat, grads[self.mu.bias], 2 * self.act_dim)
        return grads

    @classmethod
    def for_agent(cls, agent: Any) -> FusedSACUpdate | None:
        """The fused update of ``agent``, or None when its model or settings need autograd."""
        if fused_unsupported_reason(agent) is not None:
            return None
        try:
            return cls(agent)
        except ValueError:
            return None

    def _buffers(self, rows: int, obs_dim: int) -> dict[str, torch.Tensor]:
        """Activation buffers for a batch of ``rows`` (reallocated when the batch size changes)."""
        if rows == self._rows and self._bufs["ax"].shape[1] == obs_dim:
            return self._bufs
        dev = self.critic_w[0].device
        n, b2 = self.n, 2 * rows
        bufs: dict[str, torch.Tensor] = {"ax": torch.empty(b2, obs_dim, device=dev)}
        for i, (w, _) in enumerate(self.actor_layers):
            bufs[f"ah{i}"] = torch.empty(b2, w.shape[0], device=dev)
        for i, w in enumerate(self.critic_w[:-1]):
            bufs[f"ch{i}"] = torch.empty(n, b2, w.shape[2], device=dev)
            bufs[f"cg{i}"] = torch.empty(n, b2, w.shape[2], device=dev)
            bufs[f"th{i}"] = torch.empty(n, rows, w.shape[2], device=dev)
        self._bufs, self._rows = bufs, rows
        return bufs

    def _critic_forward(self, weights: list[torch.Tensor], biases: list[torch.Tensor], x: torch.Tensor,
                        hidden: list[torch.Tensor]) -> torch.Tensor:
        """Q values ``(n, rows)`` of ``x`` (``(rows, in)``, shared by all members); the hidden
        activations (after ReLU) go to ``hidden``."""
        h = x.unsqueeze(0).expand(self.n, -1, -1)
        for w, b, out in zip(weights[:-1], biases[:-1], hidden):
            torch.baddbmm(b, h, w, out=out)
            h = out.relu_()
        # The output layer (width -> 1), one matrix-vector product per critic: a batched product
        # with one output column is slow on CPU BLAS, and a dot product over the last axis
        # materialises the whole elementwise product first.
        w_out, b_out = weights[-1], biases[-1]
        q = torch.empty(self.n, h.shape[1], dtype=h.dtype, device=h.device)
        for k in range(self.n):
            torch.addmv(b_out[k, 0], h[k], w_out[k, :, 0], out=q[k])
        return q

    @torch.no_grad()
    def __call__(self, batch: tuple, eps: torch.Tensor | None = None) -> dict[str, Any]:
        """One SAC update; ``eps`` (``(2B, act_dim)``: the policy's Gaussian noise for ``o``,
        then for ``o'``) replaces the random draw (for tests)."""
        agent = self.agent
        self._follow_optimizers()
        o, a, r, o2, d, _ = batch  # the truncated flag is deliberately unused
        o, o2 = flatten_obs(o), flatten_obs(o2)
        rows, obs_dim, act_dim, n = o.shape[0], o.shape[1], self.act_dim, self.n
        a = a.reshape(rows, -1).to(torch.float32)
        r, d = r.reshape(-1), d.reshape(-1)
        buf = self._buffers(rows, obs_dim)
        alpha = agent._entropy_coef()

        # --- actor on [o; o'] -------------------------------------------------------------------
        x = torch.cat((o, o2), 0, out=buf["ax"])
        acts = [x]
        for i, (w, b) in enumerate(self.actor_layers):
            x = torch.addmm(b, x, w.t(), out=buf[f"ah{i}"]).relu_()
            acts.append(x)
        head_w = torch.cat((self.mu.weight, self.log_std.weight))
        head = torch.addmm(torch.cat((self.mu.bias, self.log_std.bias)), x, head_w.t())
        mu, log_std_raw = head[:, :act_dim], head[:, act_dim:]
        log_std = log_std_raw.clamp(LOG_STD_MIN, LOG_STD_MAX)
        std = log_std.exp()
        if eps is None:
            # two draws, like the autograd actor's (o, then o'): the same noise for the same seed
            eps = torch.cat((torch.randn(rows, act_dim, device=mu.device), torch.randn(rows, act_dim, device=mu.device)))
        u = torch.addcmul(mu, std, eps)
        t = u.tanh()
        action = torch.addcmul(self.actor.act_offset, t, self.actor.act_scale)
        # log N(u; mu, std) - log(1 - tanh(u)^2), as in SquashedGaussianMLPActor.forward
        squash = (math.log(2.0) - u - torch.nn.functional.softplus(-2.0 * u)).mul_(2.0)
        logp = -(0.5 * eps.square() + log_std + squash).sum(-1) - act_dim * _HALF_LOG_2PI
        pi, logp_pi, a2, logp_a2 = action[:rows], logp[:rows], action[rows:], logp[rows:]

        # --- target ------------------------------------------------------------------------------
        hidden_t = [buf[f"th{i}"] for i in range(len(self.critic_w) - 1)]
        q_targ = self._critic_forward(self.target_w, self.target_b, torch.cat((o2, a2), 1), hidden_t)
        backup = r + agent.gamma * (1.0 - d) * (q_targ.amin(0) - alpha * logp_a2)

        # --- online critics on [(o, a); (o, pi)] -------------------------------------------------
        xq = torch.cat((torch.cat((o, a), 1), torch.cat((o, pi), 1)), 0)
        hidden = [buf[f"ch{i}"] for i in range(len(self.critic_w) - 1)]
        q = self._critic_forward(self.critic_w, self.critic_b, xq, hidden)
        q_a, q_pi = q[:, :rows], q[:, rows:]
        diff = q_a - backup
        loss_critic = diff.square().mean()
        q_pi_min, q_pi_arg = q_pi.min(0)
        loss_actor = (alpha * logp_pi - q_pi_min).mean()

        # --- critic gradients: rows :B from the critic loss, rows B: from the actor loss --------
        gq = torch.zeros_like(q)
        gq[:, :rows] = diff * (2.0 / diff.numel())
        gq[:, rows:].scatter_(0, q_pi_arg.unsqueeze(0), -1.0 / rows)
        cg = self.critic_grads
        w_out = self.critic_w[-1]
        h = hidden[-1]
        torch.bmm(gq[:, None, :rows], h[:, :rows], out=cg[w_out].view(n, 1, -1))
        torch.sum(gq[:, :rows], 1, out=cg[self.critic_b[-1]].view(n))
        g = torch.mul(gq.unsqueeze(-1), w_out.transpose(1, 2), out=buf[f"cg{len(hidden) - 1}"])
        for i in range(len(hidden) - 1, -1, -1):
            g = torch.ops.aten.threshold_backward.grad_input(g, hidden[i], 0.0, grad_input=g)
            w, b = self.critic_w[i], self.critic_b[i]
            torch.sum(g[:, :rows], 1, keepdim=True, out=cg[b])
            if i > 0:
                torch.bmm(hidden[i - 1][:, :rows].transpose(1, 2), g[:, :rows], out=cg[w])
                g = torch.bmm(g, w.transpose(1, 2), out=buf[f"cg{i - 1}"])
        x0 = xq[:rows].t().unsqueeze(0).expand(n, -1, -1)
        torch.bmm(x0, g[:, :rows], out=cg[self.critic_w[0]])
        # dQ/d(pi): the action columns of the first layer, summed over the critics
        g_pi = torch.matmul(g[:, rows:], self.critic_w[0][:, obs_dim:].transpose(1, 2)).sum(0)

        # --- actor gradients ----------------------------------------------------------------------
        g_logp = alpha / rows  # d loss_actor / d logp_pi, every row
        t_pi = t[:rows]
        # d action / d u = scale (1 - tanh^2); d logp / d u = 2 tanh (the log-density's own
        # u-dependence cancels: u - mu = std * eps with eps fixed)
        g_u = g_pi * self.actor.act_scale * (1.0 - t_pi.square()) + (2.0 * g_logp) * t_pi
        g_ls = (g_u * std[:rows] * eps[:rows] - g_logp) * (
            (log_std_raw[:rows] >= LOG_STD_MIN) & (log_std_raw[:rows] <= LOG_STD_MAX))
        g_head = torch.cat((g_u, g_ls), 1)
        ag = self.actor_grads
        torch.mm(g_head.t(), acts[-1][:rows], out=self.head_w_grad)
        torch.sum(g_head, 0, out=self.head_b_grad)
        g = torch.mm(g_head, head_w)
        for i in range(len(self.actor_layers) - 1, -1, -1):
            g = torch.ops.aten.threshold_backward.grad_input(g, acts[i + 1][:rows], 0.0, grad_input=g)
            w, b = self.actor_layers[i]
            torch.mm(g.t(), acts[i][:rows], out=ag[w])
            torch.sum(g, 0, out=ag[b])
            if i > 0:
                g = torch.mm(g, w)

        # --- entropy coefficient, guard, steps ----------------------------------------------------
        check = loss_critic + loss_actor + cg.flat.sum() + ag.flat.sum()
        loss_alpha = None
        if self.alpha_grads is not None:
            shifted = logp_pi + agent.target_entropy
            loss_alpha = -(agent.log_alpha.detach() * shifted).mean()
            torch.neg(shifted.mean(), out=self.alpha_grads.grads[0])
            check = check + loss_alpha
        g = agent._begin_update(True)
        if not g.check_sum(check):
            return agent.guard.skipped_metrics()
        if g.on_device:  # what the steps and Polyak averaging change, put back unless finite
            stepping = [cg.optimizer, ag.optimizer] + ([self.alpha_grads.optimizer] if self.alpha_grads else [])
            g.keep(stepped_tensors(stepping) + agent._target_params)
        cg.step()
        if self.alpha_grads is not None:
            held = agent._at_alpha_max(g.on_device)
            self.alpha_grads.step()
            agent._hold_alpha(held)
        ag.step()
        agent._update_targets()
        metrics: dict[str, Any] = {
            "loss_actor": loss_actor,
            "loss_critic": loss_critic,
            "entropy_coef": alpha,
            "debug_log_pi": logp_pi.mean(),
            "debug_q": q_a.mean(),
            "debug_backup": backup.mean(),
        }
        if loss_alpha is not None:
            metrics["loss_entropy_coef"] = loss_alpha
        return g.finish(metrics)


def _span(flat: torch.Tensor, view: torch.Tensor, numel: int) -> torch.Tensor:
    """``numel`` elements of ``flat`` from where ``view`` (a view of it) starts."""
    offset = view.storage_offset() - flat.storage_offset()
    return flat[offset:offset + numel]
