"""The fused SAC update (tmrl/algorithms/fused_sac.py) against the autograd update it replaces.

Both agents start from the same weights, see the same batches and the same Gaussian noise; after
every update each parameter, target parameter, optimizer state and loss must agree to float32
rounding. The autograd path is itself checked against a SAC written from the equations in
tests/test_sac_exact.py-style references (test_algorithms.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gymnasium import spaces

from tmrl.algorithms.fused_sac import fused_unsupported_reason
from tmrl.algorithms.redq import REDQSACAgent
from tmrl.algorithms.sac import SACAgent
from tmrl.models import MLPActorCritic
from tmrl.util import partial


def _spaces(obs_dims=(3,), act_dim=1, high=2.0):
    obs = spaces.Tuple(tuple(spaces.Box(-1.0, 1.0, (k,), np.float32) for k in obs_dims))
    return obs, spaces.Box(-high, high, (act_dim,), np.float32)


def _batch(obs_dims, act_dim, rows, gen, terminated_share=0.3):
    o = tuple(torch.randn(rows, k, generator=gen) for k in obs_dims)
    o2 = tuple(torch.randn(rows, k, generator=gen) for k in obs_dims)
    a = torch.rand(rows, act_dim, generator=gen) * 2 - 1
    r = torch.randn(rows, generator=gen)
    d = (torch.rand(rows, generator=gen) < terminated_share).float()
    return o, a, r, o2, d, torch.zeros(rows)


def _pair(obs_dims=(3,), act_dim=1, hidden=(32, 32), **kw):
    obs, act = _spaces(obs_dims, act_dim)
    model = partial(MLPActorCritic, hidden_sizes=hidden)
    agents = []
    for fused in (True, False):
        torch.manual_seed(0)
        agents.append(SACAgent(obs, act, device="cpu", model_cls=model, fused=fused, **kw))
    fused_agent, ref = agents
    assert fused_agent.fused_update is not None and ref.fused_update is None
    # targets away from the online weights, so that bootstrapping from the wrong ones shows
    for agent in agents:
        gen = torch.Generator().manual_seed(1)
        with torch.no_grad():
            for p in agent.model_target.parameters():
                p.add_(0.05 * torch.randn(p.shape, generator=gen))
    return fused_agent, ref


def _step_both(fused_agent, ref, batch, seed, act_dim):
    torch.manual_seed(seed)
    m_ref = ref.train(batch)
    rows = batch[1].shape[0]
    torch.manual_seed(seed)  # the autograd actor draws the noise of o, then of o'
    eps = torch.cat((torch.randn(rows, act_dim), torch.randn(rows, act_dim)))
    m_fused = fused_agent.fused_update(batch, eps=eps)
    return m_fused, m_ref


def _assert_same_state(fused_agent, ref, rtol=2e-4, atol=2e-6):
    sd_f, sd_r = fused_agent.state_dict(), ref.state_dict()
    for part in ("model", "model_target"):
        for k, v in sd_r[part].items():
            torch.testing.assert_close(sd_f[part][k], v, rtol=rtol, atol=atol, msg=f"{part}.{k}")
    for part in ("optimizer_actor", "optimizer_critic", "optimizer_entropy"):
        if sd_r[part] is None:
            continue
        for idx, st in sd_r[part]["state"].items():
            for k, v in st.items():
                torch.testing.assert_close(sd_f[part]["state"][idx][k], v, rtol=rtol, atol=atol,
                                           msg=f"{part}[{idx}].{k}")
    if sd_r["log_alpha"] is not None:
        torch.testing.assert_close(sd_f["log_alpha"], sd_r["log_alpha"], rtol=rtol, atol=atol)


@pytest.mark.parametrize(
    "case",
    [
        {},
        {"obs_dims": (2, 5), "act_dim": 3, "hidden": (24, 16, 8)},
        {"learn_entropy_coef": False, "alpha": 0.1},
        {"optimizer_critic": "adamw", "l2_critic": 0.01, "optimizer_actor": "sgd", "lr_actor": 0.01},
        {"l2_actor": 0.001, "betas_critic": [0.5, 0.9]},
    ],
    ids=["default", "tuple-obs-3-actions-3-layers", "fixed-alpha", "adamw-and-sgd", "weight-decay-betas"],
)
def test_fused_update_equals_the_autograd_update(case):
    case = dict(case)
    obs_dims, act_dim = case.pop("obs_dims", (3,)), case.pop("act_dim", 1)
    fused_agent, ref = _pair(obs_dims, act_dim, case.pop("hidden", (32, 32)), **case)
    gen = torch.Generator().manual_seed(2)
    for step in range(4):  # the first step creates the optimizers' state, the next ones reuse it
        batch = _batch(obs_dims, act_dim, 64, gen)
        m_fused, m_ref = _step_both(fused_agent, ref, batch, 100 + step, act_dim)
        for key, value in m_ref.items():
            assert math.isclose(float(m_fused[key]), float(value), rel_tol=2e-4, abs_tol=1e-6), key
        _assert_same_state(fused_agent, ref)


def test_fused_update_passes_gradients_through_the_log_std_clamp_like_autograd():
    """Half the log-std pre-activations above LOG_STD_MAX: their gradient must be zero."""
    fused_agent, ref = _pair(act_dim=2)
    for agent in (fused_agent, ref):
        with torch.no_grad():
            agent.model.actor.log_std_layer.bias.fill_(2.0)
    gen = torch.Generator().manual_seed(3)
    for step in range(3):
        _step_both(fused_agent, ref, _batch((3,), 2, 64, gen), 7 + step, 2)
        _assert_same_state(fused_agent, ref)


def test_fused_training_state_resumes_on_the_autograd_path_and_back():
    fused_agent, ref = _pair()
    gen = torch.Generator().manual_seed(4)
    for step in range(3):
        _step_both(fused_agent, ref, _batch((3,), 1, 32, gen), step, 1)
    obs, act = _spaces()
    torch.manual_seed(9)
    resumed = SACAgent(obs, act, device="cpu", model_cls=partial(MLPActorCritic, hidden_sizes=(32, 32)))
    resumed.load_state_dict(fused_agent.state_dict())
    batch = _batch((3,), 1, 32, gen)
    torch.manual_seed(5)
    ref.train(batch)
    torch.manual_seed(5)
    resumed.train(batch)
    _assert_same_state(resumed, ref)


def test_fused_update_is_used_only_where_it_computes_the_same_update():
    obs, act = _spaces()
    assert fused_unsupported_reason(SACAgent(obs, act, device="cpu")) is None
    assert SACAgent(obs, act, device="cpu", update_order="sequential").fused_update is None
    assert REDQSACAgent(obs, act, device="cpu").fused_update is None
    assert SACAgent(obs, act, device="cpu", model_cls=partial(MLPActorCritic, critic_dtype="bfloat16")).fused_update \
        is None
    assert SACAgent(obs, act, device="cpu", model_cls=partial(MLPActorCritic, activation=torch.nn.Tanh)).fused_update \
        is None

    class MyActorCritic(MLPActorCritic):
        pass

    class MyActor(type(SACAgent(obs, act, device="cpu").model.actor)):
        pass

    agent = SACAgent(obs, act, device="cpu", model_cls=MyActorCritic)
    assert agent.fused_update is not None  # same actor and critics: the subclass changes nothing they use
    agent.model.actor.__class__ = MyActor
    assert "SquashedGaussianMLPActor" in str(fused_unsupported_reason(agent))


def test_fused_update_skips_a_non_finite_batch_and_changes_nothing():
    fused_agent, _ = _pair()
    gen = torch.Generator().manual_seed(6)
    fused_agent.train(_batch((3,), 1, 32, gen))
    before = {k: v.clone() for k, v in fused_agent.model.state_dict().items()}
    target_before = {k: v.clone() for k, v in fused_agent.model_target.state_dict().items()}
    bad = list(_batch((3,), 1, 32, gen))
    bad[2][5] = float("nan")
    metrics = fused_agent.train(tuple(bad))
    assert math.isnan(metrics["loss_critic"]) and fused_agent.skipped_updates == 1
    for k, v in fused_agent.model.state_dict().items():
        assert torch.equal(v, before[k]), k
    for k, v in fused_agent.model_target.state_dict().items():
        assert torch.equal(v, target_before[k]), k
    fused_agent.train(_batch((3,), 1, 32, gen))
    assert any(not torch.equal(v, before[k]) for k, v in fused_agent.model.state_dict().items())


def test_fused_update_follows_a_batch_size_change():
    fused_agent, ref = _pair()
    gen = torch.Generator().manual_seed(8)
    for step, rows in enumerate((64, 16, 64)):
        _step_both(fused_agent, ref, _batch((3,), 1, rows, gen), step, 1)
        _assert_same_state(fused_agent, ref)


def test_a_copied_agent_trains_its_own_parameters():
    fused_agent, _ = _pair()
    gen = torch.Generator().manual_seed(10)
    fused_agent.train(_batch((3,), 1, 32, gen))
    copy_agent = __import__("copy").deepcopy(fused_agent)
    before = {k: v.clone() for k, v in fused_agent.model.state_dict().items()}
    copy_agent.train(_batch((3,), 1, 32, gen))
    assert copy_agent.fused_update is not None and copy_agent.fused_update.agent is copy_agent
    for k, v in fused_agent.model.state_dict().items():
        assert torch.equal(v, before[k]), k  # the original is untouched
    assert any(not torch.equal(v, before[k]) for k, v in copy_agent.model.state_dict().items())


def test_the_sequential_order_guards_the_actor_step_too():
    """The sequential order back-propagates the actor loss on its own, after the critics' step:
    a non-finite actor gradient there must not reach the actor."""
    obs, act = _spaces()
    torch.manual_seed(0)
    agent = SACAgent(obs, act, device="cpu", update_order="sequential",
                     model_cls=partial(MLPActorCritic, hidden_sizes=(16, 16)))
    before = [p.detach().clone() for p in agent.model.actor.parameters()]
    handle = agent.model.actor.mu_layer.weight.register_hook(lambda g: g * float("nan"))
    metrics = agent.train(_batch((3,), 1, 32, torch.Generator().manual_seed(11)))
    handle.remove()
    assert agent.skipped_updates == 1 and math.isnan(metrics["loss_actor"])
    for p, b in zip(agent.model.actor.parameters(), before):
        assert torch.equal(p.detach(), b)
