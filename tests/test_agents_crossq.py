"""CrossQ (tmrl/algorithms/crossq.py): one update against a step written here from the paper's
equations and Batch Renormalization's (plain SGD, tiny networks, normalisation statistics moved
away from their initial values), the joint pass, the policy delay, learning on probe problems,
checkpoint round trips (running statistics included), determinism, the non-finite guard and its
selection and validation through the config."""

from __future__ import annotations

import copy
import inspect

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from gymnasium import spaces
from test_agents_droq_tqc import GYM, config_objects, flat, sgd, sgd_update  # noqa: F401 (config_objects: fixture)

# the probe problems, spaces and helpers of SAC's and REDQ's tests, shared
from test_algorithms import (  # noqa: F401 (_one_thread: the autouse fixture, one torch thread)
    ACT,
    ACT2,
    OBS,
    OBS2,
    OBS3,
    _one_thread,
    first_step_error,
    policy_error,
    probe_batch,
    random_batch,
    two_step_batch,
)

from tmrl.algorithms import ALGORITHMS, CrossQAgent, agent_class
from tmrl.algorithms.crossq import PAPER_BETAS, BatchRenorm1d, CrossQActorCritic
from tmrl.algorithms.fused_sac import fused_unsupported_reason
from tmrl.config import loader, schema
from tmrl.config.loader import ConfigError
from tmrl.errors import UserError
from tmrl.models import MLPActorCritic
from tmrl.util import partial

SMALL = (16, 16)
EPS, R_MAX, D_MAX = 1e-3, 3.0, 5.0


def crossq(**kwargs) -> CrossQAgent:
    hidden = kwargs.pop("hidden", SMALL)
    obs, act = kwargs.pop("spaces", (OBS3, ACT2))
    kwargs.setdefault("critic_width", hidden[0])
    return CrossQAgent(obs, act, "cpu", model_cls=partial(CrossQActorCritic, hidden_sizes=hidden), **kwargs)


def norm_layers(agent) -> list[BatchRenorm1d]:
    return [m for m in agent.model.modules() if isinstance(m, BatchRenorm1d)]


def move_statistics_away(agent, seed: int) -> None:
    """Running statistics far from (0, 1), so that Batch Renormalization's r and d are not 1 and
    0 and some of them are clipped."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in norm_layers(agent):
            m.running_mean.copy_(torch.randn(m.num_features, generator=gen) * 2)
            m.running_var.copy_(torch.rand(m.num_features, generator=gen) * 2 + 0.005)
            m.weight.copy_(1 + 0.3 * torch.randn(m.num_features, generator=gen))
            m.bias.copy_(0.3 * torch.randn(m.num_features, generator=gen))


# --- the reference step (Bhatt et al. 2024; Ioffe 2017) -------------------------------------------


def brn(x, w, b, mean, var, training: bool, renorm: bool, momentum: float, clipped: list):
    """Batch Renormalization of ``x`` written from Ioffe (2017), Algorithm 1. Returns the output
    and the new running statistics."""
    if not training:
        return (x - mean) / torch.sqrt(var + EPS) * w + b, mean, var
    mu_b = x.mean(0)
    var_b = ((x - mu_b) ** 2).mean(0)
    sigma_b = torch.sqrt(var_b + EPS)
    x_hat = (x - mu_b) / sigma_b
    if renorm:
        sigma = torch.sqrt(var + EPS)
        r_raw, d_raw = (sigma_b / sigma).detach(), ((mu_b - mean) / sigma).detach()
        r, d = r_raw.clamp(1 / R_MAX, R_MAX), d_raw.clamp(-D_MAX, D_MAX)
        clipped.append(bool((r != r_raw).any() or (d != d_raw).any()))
        x_hat = x_hat * r + d
    new_mean = (1 - momentum) * mean + momentum * mu_b.detach()
    new_var = (1 - momentum) * var + momentum * var_b.detach()
    return x_hat * w + b, new_mean, new_var


def critic(params: dict, stats: dict, i: int, x, training: bool, renorm: bool, momentum: float, clipped: list):
    """Critic ``i``: BRN, Linear, ReLU, BRN, Linear, ReLU, BRN, Linear (indices 0..7 of its
    ``net``). Returns Q ``(B,)`` and the new statistics of its normalisation layers."""
    new = {}
    h = x
    for layer in range(len(SMALL) + 1):
        k = f"{i}.net.{3 * layer}"
        h, new[f"{k}.running_mean"], new[f"{k}.running_var"] = brn(
            h, params[f"{k}.weight"], params[f"{k}.bias"], stats[f"{k}.running_mean"], stats[f"{k}.running_var"],
            training, renorm, momentum, clipped)
        lin = f"{i}.net.{3 * layer + 1}"
        h = F.linear(h, params[f"{lin}.weight"], params[f"{lin}.bias"])
        if layer < len(SMALL):
            h = torch.relu(h)
    return h.squeeze(-1), new


def reference_crossq_step(ag: CrossQAgent, batch: tuple, lr: float, renorm: bool) -> dict:
    """No target network: a' ~ pi(o'); the critics in training mode over the concatenation
    [(o, a); (o', a')], split; y = r + gamma (1 - d) (min_i Q_i(o', a') - alpha log pi(a'|o')) with
    the second half detached; SGD on the mean squared error; then the actor against the *updated*
    critics in *evaluation* mode (their new running statistics), min over critics; SAC v2's alpha.
    Random numbers: a' at o', then pi at o."""
    o, a, r, o2, d, _ = batch
    n, size, mom = len(ag.model.qs), a.shape[0], ag.bn_momentum
    params = dict(ag.model.qs.named_parameters())
    stats = {k: v.clone() for k, v in ag.model.qs.named_buffers() if "running" in k}
    alpha = ag.log_alpha.detach().exp()
    clipped: list = []
    with torch.no_grad():
        a2, logp_a2 = ag.model.actor(o2)
    x = flat(tuple(torch.cat((u, v)) for u, v in zip(o, o2)), torch.cat((a, a2)))
    q_all, new_stats = [], {}
    for i in range(n):
        qi, st = critic(params, stats, i, x, True, renorm, mom, clipped)
        q_all.append(qi)
        new_stats.update(st)
    q = [qi[:size] for qi in q_all]
    q_next = torch.stack([qi[size:] for qi in q_all]).detach()
    y = r + ag.gamma * (1 - d) * (q_next.min(0).values - alpha * logp_a2)
    loss_q = sum(((qi - y) ** 2).mean() for qi in q) / n
    new_q: dict = {}
    sgd_update(new_q, params, loss_q, lr)
    pi, logp_pi = ag.model.actor(o)
    q_pi = torch.stack([critic(new_q, new_stats, i, flat(o, pi), False, renorm, mom, clipped)[0] for i in range(n)])
    loss_pi = (alpha * logp_pi - q_pi.min(0).values).mean()
    out = {name: p.detach().clone() for name, p in ag.model.named_parameters()}
    out.update({f"qs.{k}": v for k, v in new_q.items()})
    new_actor: dict = {}
    sgd_update(new_actor, dict(ag.model.actor.named_parameters()), loss_pi, lr)
    out.update({f"actor.{k}": v for k, v in new_actor.items()})
    loss_alpha = -(ag.log_alpha * (logp_pi.detach() + ag.target_entropy)).mean()
    (g,) = torch.autograd.grad(loss_alpha, [ag.log_alpha])
    out["log_alpha"] = ag.log_alpha.detach() - lr * g
    out["stats"] = {f"qs.{k}": v for k, v in new_stats.items()}
    out["loss_critic"], out["loss_actor"], out["y"] = loss_q.detach(), loss_pi.detach(), y
    out["clipped"] = any(clipped)
    return out


@pytest.mark.parametrize("renorm", [True, False], ids=["renorm", "warmup"])
def test_one_update_matches_the_paper_step(renorm):
    torch.manual_seed(0)
    lr = 0.05
    agent = sgd(crossq(policy_delay=1, gamma=0.9, bn_momentum=0.2, renorm_warmup_steps=0 if renorm else 10), lr)
    move_statistics_away(agent, seed=3)
    batch = random_batch(torch.Generator().manual_seed(2))
    assert 0 < float(batch[4].sum()) < len(batch[4])  # terminal and bootstrapped transitions
    before = copy.deepcopy(agent)
    torch.manual_seed(5)
    expected = reference_crossq_step(before, batch, lr, renorm)
    assert expected["clipped"] == renorm  # r or d clipped somewhere: the clipping is exercised
    torch.manual_seed(5)
    metrics = agent.train(batch)
    for name, p in agent.model.named_parameters():
        torch.testing.assert_close(p.detach(), expected[name], rtol=1e-5, atol=1e-6, msg=name)
    torch.testing.assert_close(agent.log_alpha.detach(), expected["log_alpha"])
    buffers = dict(agent.model.named_buffers())
    for name, value in expected["stats"].items():
        torch.testing.assert_close(buffers[name], value, msg=name)
    assert all(int(m.num_batches_tracked) == 1 for m in norm_layers(agent))  # one pass in training mode
    torch.testing.assert_close(metrics["loss_critic"], expected["loss_critic"])
    torch.testing.assert_close(metrics["loss_actor"], expected["loss_actor"])
    torch.testing.assert_close(metrics["debug_backup"], expected["y"].mean())
    assert {"loss_actor", "loss_critic", "entropy_coef", "loss_entropy_coef", "debug_q", "debug_log_pi"} <= set(metrics)
    assert agent.fused_update is None and fused_unsupported_reason(agent) is not None


def test_batch_renorm_layer_matches_batch_norm_during_warmup_and_in_eval_mode():
    torch.manual_seed(0)
    x = torch.randn(32, 5) * 3 + 1
    ours = BatchRenorm1d(5, momentum=0.1, eps=1e-3, warmup_steps=2)
    theirs = torch.nn.BatchNorm1d(5, momentum=0.1, eps=1e-3)
    torch.testing.assert_close(ours(x), theirs(x))
    torch.testing.assert_close(ours.running_mean, theirs.running_mean)
    ours.eval()
    theirs.eval()
    theirs.running_var.copy_(ours.running_var)  # torch's running variance is unbiased, ours biased
    torch.testing.assert_close(ours(x), theirs(x))
    assert set(dict(ours.named_buffers())) == {"running_mean", "running_var", "num_batches_tracked"}
    with pytest.raises(UserError, match="ALG.CROSSQ_BN_MOMENTUM"):
        BatchRenorm1d(3, momentum=0.0)


def test_the_target_half_is_detached_and_the_statistics_are_those_of_both_halves():
    torch.manual_seed(0)
    agent = crossq()
    b = random_batch(torch.Generator().manual_seed(1))
    from tmrl.batch import Batch

    first = agent.model.qs[0].net[0]
    old = first.running_mean.clone()
    q, y = agent.joint_critic_pass(Batch(*b), agent._entropy_coef())
    assert q.requires_grad and not y.requires_grad and q.shape == (2, 16) and y.shape == (16,)
    # The input layer's statistics moved toward the mean over (o, a) AND (o', a'), not (o, a) alone.
    both = torch.cat([torch.cat([u, v]) for u, v in zip(b[0], b[3])], dim=1)  # the observations of both halves
    expected_obs_mean = (1 - agent.bn_momentum) * old[:5] + agent.bn_momentum * both.mean(0)
    torch.testing.assert_close(first.running_mean[:5], expected_obs_mean)


def test_policy_updates_once_every_policy_delay_critic_updates():
    torch.manual_seed(0)
    agent = crossq()
    assert agent.policy_delay == 3
    gen = torch.Generator().manual_seed(1)

    def actor_state():
        return [p.detach().clone() for p in agent.model.actor.parameters()] + [agent.log_alpha.detach().clone()]

    for step in range(1, 7):
        old_actor = actor_state()
        old_critics = [p.detach().clone() for p in agent.critics.parameters()]
        agent.train(random_batch(gen))
        moved = not all(torch.equal(x, y) for x, y in zip(old_actor, actor_state()))
        assert moved == (step % 3 == 0), step
        assert not all(torch.equal(x, y) for x, y in zip(old_critics, agent.critics.parameters()))
        # One pass in training mode per update: the actor's loss reads the critics in evaluation mode.
        assert all(int(m.num_batches_tracked) == step for m in norm_layers(agent))
        assert all(m.training for m in norm_layers(agent))


def test_no_target_networks_so_polyak_changes_nothing():
    def run(polyak: float) -> list[torch.Tensor]:
        torch.manual_seed(0)
        agent = crossq(polyak=polyak, policy_delay=1)
        gen = torch.Generator().manual_seed(1)
        for _ in range(3):
            agent.train(random_batch(gen))
        assert list(agent.model_target.parameters()) == [] and agent.state_dict()["model_target"] == {}
        return [p.detach().clone() for p in agent.model.parameters()]

    assert all(torch.equal(x, y) for x, y in zip(run(0.5), run(0.999)))


def test_refuses_critics_without_batch_norm_and_bad_settings():
    with pytest.raises(UserError, match="batch normalisation"):
        CrossQAgent(OBS3, ACT2, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=SMALL))
    with pytest.raises(UserError, match="ALG.CROSSQ_POLICY_DELAY"):
        crossq(policy_delay=0)
    with pytest.raises(UserError, match="ALG.CROSSQ_CRITIC_WIDTH"):
        crossq(critic_width=0)
    with pytest.raises(UserError, match="ALG.CROSSQ_BN_MOMENTUM"):
        crossq(bn_momentum=1.5)
    with pytest.raises(UserError, match="ALG.CROSSQ_RENORM_WARMUP_STEPS"):
        crossq(renorm_warmup_steps=-1)
    agent = crossq(bn_momentum=0.3, renorm_warmup_steps=7, critic_width=8)  # the settings reach the model
    assert {(m.momentum, m.warmup_steps) for m in norm_layers(agent)} == {(0.3, 7)}
    assert agent.model.qs[1].net[1].out_features == 8


def test_a_non_finite_update_is_skipped_and_leaves_the_statistics_alone():
    torch.manual_seed(0)
    agent = crossq(policy_delay=1)
    o, a, r, o2, d, t = random_batch(torch.Generator().manual_seed(1))
    before = copy.deepcopy(agent.model.state_dict())
    metrics = agent.train((o, a, r * float("nan"), o2, d, t))
    assert np.isnan(metrics["loss_critic"]) and agent.skipped_updates == 1
    after = agent.model.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # weights and running statistics


# --- learning, checkpoints, determinism -----------------------------------------------------------

LEARN = {"lr_actor": 3e-3, "lr_critic": 3e-3, "lr_entropy": 3e-3, "alpha": 0.05}


def make(obs=OBS, **kwargs) -> CrossQAgent:
    return crossq(spaces=(obs, ACT), hidden=(64, 64), renorm_warmup_steps=100, **LEARN, **kwargs)


def test_learns_the_probe_problem():
    torch.manual_seed(0)
    agent = make()
    gen = torch.Generator().manual_seed(1)
    assert policy_error(agent) > 0.2
    for _ in range(400):
        metrics = agent.train(probe_batch(gen))
    assert policy_error(agent) < 0.1
    assert float(metrics["entropy_coef"]) < 0.05  # learned down toward the target entropy


def test_learns_a_probe_that_needs_bootstrapping():
    torch.manual_seed(0)
    agent = make(obs=OBS2, gamma=0.9)
    gen = torch.Generator().manual_seed(1)
    assert first_step_error(agent) > 0.2
    for _ in range(500):
        agent.train(two_step_batch(gen))
    assert first_step_error(agent) < 0.1


def small() -> CrossQAgent:
    return crossq(renorm_warmup_steps=2)


def test_state_dict_round_trip_resumes_identically():
    gen = torch.Generator().manual_seed(5)
    batches = [random_batch(gen) for _ in range(7)]
    torch.manual_seed(0)
    a = small()
    for b in batches[:4]:
        a.train(b)
    state = copy.deepcopy(a.state_dict())
    assert {"qs.0.net.0.running_mean", "qs.0.net.0.running_var", "qs.1.net.6.num_batches_tracked"} <= set(state["model"])
    torch.manual_seed(1)
    b = small()
    actor_b = b.get_actor()
    b.load_state_dict(state)
    assert b.i_update == 4 and torch.equal(b.loss_pi, a.loss_pi)
    for (name, x), y in zip(a.model.named_buffers(), b.model.buffers()):
        assert torch.equal(x, y), name  # running statistics and the renormalisation step counts
    for batch in batches[4:]:
        torch.manual_seed(42)
        ma = a.train(batch)
        torch.manual_seed(42)
        mb = b.train(batch)
        assert {k: float(v) for k, v in ma.items()} == {k: float(v) for k, v in mb.items()}
    for x, y in zip(a.model.state_dict().values(), b.model.state_dict().values()):
        assert torch.equal(x, y)
    assert torch.equal(a.log_alpha, b.log_alpha)
    assert a.q_optimizer.state_dict()["state"][0]["step"] == b.q_optimizer.state_dict()["state"][0]["step"]
    assert all(torch.equal(x, y) for x, y in zip(actor_b.parameters(), b.model.actor.parameters()))


def test_state_dict_from_another_configuration_is_refused():
    with pytest.raises(UserError, match="same algorithm and model settings"):
        crossq(critic_width=8).load_state_dict(small().state_dict())


def test_same_seed_same_parameters():
    def run():
        torch.manual_seed(123)
        agent = small()
        gen = torch.Generator().manual_seed(4)
        for _ in range(8):
            agent.train(random_batch(gen))
        return list(agent.model.state_dict().values()) + [agent.log_alpha.detach().clone()]

    assert all(torch.equal(x, y) for x, y in zip(run(), run()))


def test_default_model_and_settings_are_the_papers_but_the_width():
    obs, act = spaces.Box(-1.0, 1.0, (3,), np.float32), spaces.Box(-1.0, 1.0, (2,), np.float32)
    agent = CrossQAgent(obs, act, "cpu")
    assert len(agent.critics) == 2 and agent.policy_delay == 3 and agent.lr_critic == agent.lr_actor == 1e-3
    q = agent.model.qs[0].net
    kinds = [type(m) for m in q]
    assert kinds == [BatchRenorm1d, torch.nn.Linear, torch.nn.ReLU] * 2 + [BatchRenorm1d, torch.nn.Linear]
    assert [m.out_features for m in q if isinstance(m, torch.nn.Linear)] == [1024, 1024, 1]
    assert {(m.momentum, m.eps, m.warmup_steps) for m in norm_layers(agent)} == {(0.01, 1e-3, 100_000)}
    widths = [m.out_features for m in agent.model.actor.net if isinstance(m, torch.nn.Linear)]
    assert widths == [256, 256] and not any(isinstance(m, BatchRenorm1d) for m in agent.model.actor.modules())
    for opt in (agent.pi_optimizer, agent.q_optimizer):
        assert opt.param_groups[0]["betas"] == PAPER_BETAS
    # Betas given, or an optimizer without betas, are left alone.
    assert crossq(betas_critic=[0.9, 0.99]).q_optimizer.param_groups[0]["betas"] == (0.9, 0.99)
    assert crossq(optimizer_critic="sgd").betas_critic is None


# --- selection and validation through the config --------------------------------------------------


def test_crossq_is_selected_through_the_config(config_objects):  # noqa: F811 (the imported fixture)
    o = config_objects({"ENV": GYM, "ALG": {"ALGORITHM": "crossq", "CROSSQ_POLICY_DELAY": 2,
                                            "CROSSQ_CRITIC_WIDTH": 32, "CROSSQ_BN_MOMENTUM": 0.05,
                                            "CROSSQ_RENORM_WARMUP_STEPS": 10, "LR_ACTOR": 0.002}})
    assert o.AGENT.func is CrossQAgent and o.TRAIN_MODEL is CrossQActorCritic
    kw = o.AGENT.keywords
    assert (kw["policy_delay"], kw["critic_width"], kw["bn_momentum"], kw["renorm_warmup_steps"], kw["lr_actor"]) == \
        (2, 32, 0.05, 10, 0.002)
    assert "dropout_rate" not in kw and "update_order" not in kw
    env = o.ENV_CLS()
    try:
        agent = o.AGENT(env.observation_space, env.action_space, "cpu")
    finally:
        env.close()
    assert agent.model.qs[0].net[1].out_features == 32 and agent.policy_delay == 2
    assert {(m.momentum, m.warmup_steps) for m in norm_layers(agent)} == {(0.05, 10)}
    # The worker's policy class loads the trained actor's weights.
    policy = o.POLICY(env.observation_space, env.action_space)
    policy.load_state_dict(agent.get_actor().state_dict())


@pytest.mark.parametrize("key, value, expected", [
    ("CROSSQ_POLICY_DELAY", 0, "ALG.CROSSQ_POLICY_DELAY must be"),
    ("CROSSQ_CRITIC_WIDTH", 0, "ALG.CROSSQ_CRITIC_WIDTH must be"),
    ("CROSSQ_BN_MOMENTUM", 0, "ALG.CROSSQ_BN_MOMENTUM must be"),
    ("CROSSQ_BN_MOMENTUM", 1.5, "ALG.CROSSQ_BN_MOMENTUM must be"),
    ("CROSSQ_RENORM_WARMUP_STEPS", -1, "ALG.CROSSQ_RENORM_WARMUP_STEPS must be"),
    ("CROSSQ_POLICY_DELAY", "3", "ALG.CROSSQ_POLICY_DELAY must be"),
])
def test_bad_settings_are_one_line_config_errors(key, value, expected):
    base = loader.validate({"ALG": {"ALGORITHM": "CROSSQ"}})
    with pytest.raises(ConfigError, match=expected) as err:
        loader.apply_override(base, {"ALG": {key: value}})
    assert "\n" not in str(err.value)


def test_the_table_registry_and_signature_agree_for_crossq():
    assert agent_class("CrossQ") is CrossQAgent and agent_class("cross-q") is CrossQAgent
    assert "CROSSQ" in ALGORITHMS and tuple(ALGORITHMS) == schema.ALGORITHMS
    fed = schema.fed_arguments()
    not_settings = {"self", "observation_space", "action_space", "device", "model_cls"}
    params = dict(inspect.signature(CrossQAgent.__init__).parameters)
    assert set(params) - not_settings == set(fed["CrossQAgent"])
    for arg, (key, class_default) in fed["CrossQAgent"].items():
        if class_default is not schema.NO_CLASS_DEFAULT:
            assert params[arg].default == class_default, key
    cfg = schema.defaults()["ALG"]
    assert (cfg["CROSSQ_POLICY_DELAY"], cfg["CROSSQ_CRITIC_WIDTH"], cfg["CROSSQ_BN_MOMENTUM"],
            cfg["CROSSQ_RENORM_WARMUP_STEPS"]) == (3, 1024, 0.01, 100_000)
