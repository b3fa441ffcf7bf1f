"""SAC and REDQ-SAC: learning on a probe problem, exact update semantics, determinism,
checkpoint state, optimizer settings and the models they train."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from gymnasium import spaces

from tmrl.actor import TorchActorModule
from tmrl.algorithms import REDQSACAgent, SACAgent, SpinupSacAgent, agent_class
from tmrl.custom.custom_algorithms import REDQSACAgent as CompatREDQ
from tmrl.custom.custom_algorithms import SpinupSacAgent as CompatSAC
from tmrl.errors import UserError
from tmrl.models import EnsembleQFunction, MLPActorCritic, REDQMLPActorCritic
from tmrl.util import partial

OBS = spaces.Tuple((spaces.Box(-1.0, 1.0, (1,), np.float32),))
ACT = spaces.Box(-1.0, 1.0, (1,), np.float32)
OBS3 = spaces.Tuple((spaces.Box(-1.0, 1.0, (2,), np.float32), spaces.Box(0.0, 1.0, (3,), np.float32)))
ACT2 = spaces.Box(np.array([-2.0, 0.0], np.float32), np.array([2.0, 1.0], np.float32))
SMALL = (32, 32)


@pytest.fixture(autouse=True)
def _one_thread():
    # Reproducible timings and results on a shared 2-core machine.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def probe_batch(gen: torch.Generator, size: int = 128) -> tuple:
    """One-step episodes: obs uniform in [-1, 1], reward -(a - obs)^2, always terminated."""
    o = torch.rand(size, 1, generator=gen) * 2 - 1
    a = torch.rand(size, 1, generator=gen) * 2 - 1
    r = -(a - o).square().sum(-1)
    return (o,), a, r, (o,), torch.ones(size), torch.zeros(size)


def random_batch(gen: torch.Generator, size: int = 16, obs_space=OBS3, act_dim: int = 2) -> tuple:
    def obs():
        return tuple(torch.rand(size, *s.shape, generator=gen) for s in obs_space)

    a = torch.rand(size, act_dim, generator=gen)
    r = torch.randn(size, generator=gen)
    d = (torch.rand(size, generator=gen) < 0.2).float()
    return obs(), a, r, obs(), d, torch.zeros(size)


def policy_error(agent) -> float:
    o = torch.linspace(-0.9, 0.9, 19).reshape(-1, 1)
    with torch.no_grad():
        a, _ = agent.get_actor()((o,), test=True)
    return (a - o).abs().mean().item()


@pytest.mark.parametrize(
    "make",
    [
        lambda: SACAgent(
            OBS,
            ACT,
            "cpu",
            model_cls=partial(MLPActorCritic, hidden_sizes=(64, 64)),
            lr_actor=3e-3,
            lr_critic=3e-3,
            lr_entropy=3e-3,
            alpha=0.05,
        ),
        lambda: REDQSACAgent(
            OBS,
            ACT,
            "cpu",
            model_cls=partial(REDQMLPActorCritic, hidden_sizes=(64, 64)),
            lr_actor=3e-3,
            lr_critic=3e-3,
            lr_entropy=3e-3,
            alpha=0.05,
            n=5,
        ),
        lambda: REDQSACAgent(
            OBS,
            ACT,
            "cpu",
            lr_actor=3e-3,
            lr_critic=3e-3,
            lr_entropy=3e-3,
            alpha=0.05,
            n=5,
            model_cls=partial(REDQMLPActorCritic, hidden_sizes=(64, 64), critic_dtype="bfloat16"),
        ),
    ],
    ids=["sac", "redq", "redq-bf16"],
)
def test_learns_the_probe_problem(make):
    torch.manual_seed(0)
    agent = make()
    gen = torch.Generator().manual_seed(1)
    assert policy_error(agent) > 0.2
    for _ in range(400):
        metrics = agent.train(probe_batch(gen))
    assert policy_error(agent) < 0.1
    assert float(metrics["loss_critic"]) < 0.01
    assert float(metrics["entropy_coef"]) < 0.05  # learned down toward the target entropy


OBS2 = spaces.Tuple((spaces.Box(-1.0, 1.0, (2,), np.float32),))


def two_step_batch(gen: torch.Generator, size: int = 128) -> tuple:
    """Two-step episodes, observation ``(x, phase)``. Phase 0: reward 0, next observation
    ``(clip(a + x/2), 1)``, *not* terminal. Phase 1 at ``y``: reward ``-4 y^2``, terminal. The best
    first action, ``-x/2``, can only be learned by bootstrapping through the next state's value."""
    half = size // 2
    x, a0 = (torch.rand(half, 1, generator=gen) * 2 - 1 for _ in range(2))
    y, a1 = (torch.rand(half, 1, generator=gen) * 2 - 1 for _ in range(2))
    zeros, ones = torch.zeros(half, 1), torch.ones(half, 1)
    o = torch.cat((torch.cat((x, zeros), 1), torch.cat((y, ones), 1)))
    o2 = torch.cat((torch.cat(((a0 + x / 2).clamp(-1, 1), ones), 1), torch.cat((y, ones), 1)))
    r = torch.cat((torch.zeros(half), -4 * y.squeeze(1) ** 2))
    d = torch.cat((torch.zeros(half), torch.ones(half)))
    return (o,), torch.cat((a0, a1)), r, (o2,), d, torch.zeros(size)


def first_step_error(agent) -> float:
    x = torch.linspace(-0.9, 0.9, 19).reshape(-1, 1)
    with torch.no_grad():
        a, _ = agent.get_actor()((torch.cat((x, torch.zeros_like(x)), 1),), test=True)
    return (a + x / 2).abs().mean().item()


@pytest.mark.parametrize("algo", ["sac-simultaneous", "sac-sequential", "redq"])
def test_learns_a_probe_that_needs_bootstrapping(algo):
    torch.manual_seed(0)
    kwargs = dict(lr_actor=3e-3, lr_critic=3e-3, lr_entropy=3e-3, alpha=0.05, gamma=0.9)
    if algo == "redq":
        agent = REDQSACAgent(OBS2, ACT, "cpu", model_cls=partial(REDQMLPActorCritic, hidden_sizes=(64, 64)),
                             n=5, **kwargs)
    else:
        agent = SACAgent(OBS2, ACT, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=(64, 64)),
                         update_order=algo.split("-")[1], **kwargs)
    gen = torch.Generator().manual_seed(1)
    assert first_step_error(agent) > 0.2
    for _ in range(500):
        agent.train(two_step_batch(gen))
    assert first_step_error(agent) < 0.1


def _sgd_step(named: dict[str, torch.Tensor], params, grads, lr: float, prefix: str) -> None:
    """``named[prefix.name] -= lr * grad`` for each ``(name, param)`` of ``params``."""
    for (name, _), g in zip(params, grads):
        named[f"{prefix}.{name}"] = named[f"{prefix}.{name}"] - lr * g


def _move_targets_away(agent: SACAgent, seed: int) -> None:
    """Target critics that differ from the online ones, so that bootstrapping from the wrong
    set shows in the update."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in agent.model_target.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=gen))


def _reference_sac_step(ag: SACAgent, batch: tuple, lr: float, order: str) -> dict[str, torch.Tensor]:
    """Textbook SAC step with plain SGD, losses kept apart: critics from the critic loss only
    (bootstrapped from the *target* critics), actor from the actor loss with critics frozen,
    log_alpha from its own loss. ``order="sequential"``: the actor loss reads the critics after
    their step (the original tmrl SAC); ``"simultaneous"``: before it."""
    o, a, r, o2, d, _ = batch
    alpha = ag.log_alpha.detach().exp()
    pi, logp_pi = ag.model.actor(o)
    with torch.no_grad():
        a2, logp_a2 = ag.model.actor(o2)
        q1t, q2t = ag.model_target.q1(o2, a2), ag.model_target.q2(o2, a2)
        backup = r + ag.gamma * (1 - d) * (torch.min(q1t, q2t) - alpha * logp_a2)
    loss_q = (((ag.model.q1(o, a) - backup) ** 2).mean() + ((ag.model.q2(o, a) - backup) ** 2).mean()) / 2
    critic_named = list(ag.model.qs.named_parameters())
    g_critic = torch.autograd.grad(loss_q, [p for _, p in critic_named])
    out = {name: p.detach().clone() for name, p in ag.model.named_parameters()}
    _sgd_step(out, critic_named, g_critic, lr, "qs")
    critics = ag.model
    if order == "sequential":
        critics = copy.deepcopy(ag.model)
        with torch.no_grad():
            for name, p in critics.qs.named_parameters():
                p.copy_(out[f"qs.{name}"])
    q_pi = torch.min(critics.q1(o, pi), critics.q2(o, pi))
    loss_pi = (alpha * logp_pi - q_pi).mean()
    actor_named = list(ag.model.actor.named_parameters())
    g_actor = torch.autograd.grad(loss_pi, [p for _, p in actor_named])
    _sgd_step(out, actor_named, g_actor, lr, "actor")
    loss_alpha = -(ag.log_alpha * (logp_pi.detach() + ag.target_entropy)).mean()
    (g_alpha,) = torch.autograd.grad(loss_alpha, [ag.log_alpha])
    out["log_alpha"] = ag.log_alpha.detach() - lr * g_alpha
    return out


def _sgd_agent(cls: type, lr: float, **kwargs) -> SACAgent:
    model = REDQMLPActorCritic if cls is REDQSACAgent else MLPActorCritic
    agent = cls(
        OBS3,
        ACT2,
        "cpu",
        model_cls=partial(model, hidden_sizes=SMALL),
        optimizer_actor="sgd",
        optimizer_critic="sgd",
        lr_actor=lr,
        lr_critic=lr,
        **kwargs,
    )
    agent.alpha_optimizer = torch.optim.SGD([agent.log_alpha], lr=lr)
    return agent


def _assert_matches(agent: SACAgent, reference: SACAgent, expected: dict[str, torch.Tensor]) -> None:
    for name, p in agent.model.named_parameters():
        torch.testing.assert_close(p.detach(), expected[name], rtol=1e-5, atol=1e-6, msg=name)
    torch.testing.assert_close(agent.log_alpha.detach(), expected["log_alpha"])
    # Targets moved by Polyak averaging toward the *updated* online weights.
    for (name, p), pt, p0 in zip(
        agent.model.named_parameters(), agent.model_target.parameters(), reference.model_target.parameters()
    ):
        torch.testing.assert_close(pt, agent.polyak * p0 + (1 - agent.polyak) * p.detach(), msg=name)


@pytest.mark.parametrize("order", ["simultaneous", "sequential"])
def test_one_update_matches_the_textbook_sac_step(order):
    torch.manual_seed(0)
    lr = 0.05
    agent = _sgd_agent(SACAgent, lr, update_order=order, gamma=0.9)
    _move_targets_away(agent, seed=3)
    batch = random_batch(torch.Generator().manual_seed(2))
    assert 0 < float(batch[4].sum()) < len(batch[4])  # terminal and bootstrapped transitions
    reference = copy.deepcopy(agent)
    torch.manual_seed(5)
    expected = _reference_sac_step(reference, batch, lr, order)
    torch.manual_seed(5)
    agent.train(batch)
    _assert_matches(agent, reference, expected)


def test_the_two_update_orders_differ_and_unknown_orders_are_refused():
    # Same batch, same seed: only the critics the actor loss reads differ.
    batch = random_batch(torch.Generator().manual_seed(2))
    actors = []
    for order in ("simultaneous", "sequential"):
        torch.manual_seed(0)
        agent = _sgd_agent(SACAgent, 0.05, update_order=order)
        torch.manual_seed(5)
        agent.train(batch)
        actors.append([p.detach().clone() for p in agent.model.actor.parameters()])
    assert not all(torch.equal(x, y) for x, y in zip(*actors))
    with pytest.raises(UserError, match="ALG.UPDATE_ORDER") as err:
        SACAgent(OBS3, ACT2, "cpu", update_order="actor-first")
    assert "\n" not in str(err.value)


def _reference_redq_step(ag: REDQSACAgent, batch: tuple, lr: float) -> dict[str, torch.Tensor]:
    """REDQ-SAC with plain SGD, drawing its random numbers in the agent's order (the policy's
    actions, then the target actions, then the subset): the target is the minimum over a
    random subset of ``m`` *target* critics; every critic regresses on it; the actor maximises
    the mean of all ``n`` critics (before their step)."""
    o, a, r, o2, d, _ = batch
    alpha = ag.log_alpha.detach().exp()
    pi, logp_pi = ag.model.actor(o)
    with torch.no_grad():
        a2, logp_a2 = ag.model.actor(o2)
        subset = torch.randperm(ag.n)[: ag.m]
        q_targ = torch.stack([ag.model_target.qs[int(i)](o2, a2) for i in subset]).min(0).values
        backup = r + ag.gamma * (1 - d) * (q_targ - alpha * logp_a2)
    q = torch.stack([ag.model.qs[i](o, a) for i in range(ag.n)])
    loss_q = ((q - backup) ** 2).mean(1).mean()
    critic_named = list(ag.model.qs.named_parameters())
    g_critic = torch.autograd.grad(loss_q, [p for _, p in critic_named])
    out = {name: p.detach().clone() for name, p in ag.model.named_parameters()}
    _sgd_step(out, critic_named, g_critic, lr, "qs")
    q_pi = torch.stack([ag.model.qs[i](o, pi) for i in range(ag.n)]).mean(0)
    loss_pi = (alpha * logp_pi - q_pi).mean()
    actor_named = list(ag.model.actor.named_parameters())
    g_actor = torch.autograd.grad(loss_pi, [p for _, p in actor_named])
    _sgd_step(out, actor_named, g_actor, lr, "actor")
    loss_alpha = -(ag.log_alpha * (logp_pi.detach() + ag.target_entropy)).mean()
    (g_alpha,) = torch.autograd.grad(loss_alpha, [ag.log_alpha])
    out["log_alpha"] = ag.log_alpha.detach() - lr * g_alpha
    out["subset"] = subset
    return out


def test_one_update_matches_the_redq_step_with_a_seeded_subset():
    torch.manual_seed(0)
    lr = 0.05
    agent = _sgd_agent(REDQSACAgent, lr, n=5, m=3, gamma=0.9)
    _move_targets_away(agent, seed=4)
    batch = random_batch(torch.Generator().manual_seed(2))
    reference = copy.deepcopy(agent)
    torch.manual_seed(6)
    expected = _reference_redq_step(reference, batch, lr)
    # A subset that is neither the first m critics nor all of them.
    assert sorted(expected["subset"].tolist()) not in ([0, 1, 2], list(range(5)))
    torch.manual_seed(6)
    agent.train(batch)
    _assert_matches(agent, reference, expected)


@pytest.mark.parametrize("cls", [SACAgent, REDQSACAgent])
def test_bootstraps_on_terminated_never_on_truncated(cls):
    torch.manual_seed(0)
    kwargs = {"n": 3} if cls is REDQSACAgent else {}
    agent = cls(
        OBS3,
        ACT2,
        "cpu",
        model_cls=partial(REDQMLPActorCritic, hidden_sizes=SMALL)
        if cls is REDQSACAgent
        else partial(MLPActorCritic, hidden_sizes=SMALL),
        gamma=0.9,
        **kwargs,
    )
    o, a, r, o2, _, _ = random_batch(torch.Generator().manual_seed(3))
    ones, zeros = torch.ones_like(r), torch.zeros_like(r)
    with torch.no_grad():
        q = agent.critics(o, a)
    no_bootstrap = (q - r).square().mean()

    def critic_loss(d, t):
        ag = copy.deepcopy(agent)
        torch.manual_seed(9)
        return float(ag.train((o, a, r, o2, d, t))["loss_critic"])

    assert critic_loss(ones, zeros) == pytest.approx(float(no_bootstrap), rel=1e-6)
    assert critic_loss(ones, ones) == pytest.approx(float(no_bootstrap), rel=1e-6)
    bootstrapped = critic_loss(zeros, zeros)
    assert bootstrapped != pytest.approx(float(no_bootstrap), rel=1e-3)
    assert critic_loss(zeros, ones) == bootstrapped  # truncation changes nothing


@pytest.mark.parametrize("cls", [SACAgent, REDQSACAgent])
def test_same_seed_same_parameters(cls):
    def run():
        torch.manual_seed(123)
        model = REDQMLPActorCritic if cls is REDQSACAgent else MLPActorCritic
        agent = cls(OBS3, ACT2, "cpu", model_cls=partial(model, hidden_sizes=SMALL))
        gen = torch.Generator().manual_seed(4)
        for _ in range(15):
            agent.train(random_batch(gen))
        return [p.detach().clone() for p in agent.model.parameters()], agent.log_alpha.detach().clone()

    (p1, a1), (p2, a2) = run(), run()
    assert all(torch.equal(x, y) for x, y in zip(p1, p2))
    assert torch.equal(a1, a2)


@pytest.mark.parametrize("cls", [SACAgent, REDQSACAgent])
def test_state_dict_round_trip_resumes_identically(cls):
    extra = {"n": 4, "q_updates_per_policy_update": 2} if cls is REDQSACAgent else {}
    model = partial(REDQMLPActorCritic if cls is REDQSACAgent else MLPActorCritic, hidden_sizes=SMALL)
    gen = torch.Generator().manual_seed(5)
    batches = [random_batch(gen) for _ in range(6)]
    torch.manual_seed(0)
    a = cls(OBS3, ACT2, "cpu", model_cls=model, **extra)
    for b in batches[:3]:
        a.train(b)
    state = copy.deepcopy(a.state_dict())
    torch.manual_seed(1)
    b = cls(OBS3, ACT2, "cpu", model_cls=model, **extra)
    actor_b = b.get_actor()
    b.load_state_dict(state)
    for batch in batches[3:]:
        torch.manual_seed(42)
        ma = a.train(batch)
        torch.manual_seed(42)
        mb = b.train(batch)
        assert float(ma["loss_critic"]) == float(mb["loss_critic"])
    for x, y in zip(a.model.parameters(), b.model.parameters()):
        assert torch.equal(x, y)
    for x, y in zip(a.model_target.parameters(), b.model_target.parameters()):
        assert torch.equal(x, y)
    assert torch.equal(a.log_alpha, b.log_alpha)
    # The actor handed out before loading still shares memory with the trained model.
    assert all(torch.equal(x, y) for x, y in zip(actor_b.parameters(), b.model.actor.parameters()))


def test_state_dict_from_another_configuration_is_refused():
    a = SACAgent(OBS3, ACT2, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=SMALL))
    b = SACAgent(OBS3, ACT2, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=(16, 16)))
    with pytest.raises(UserError, match="same algorithm and model settings") as err:
        b.load_state_dict(a.state_dict())
    assert "\n" not in str(err.value)
    c = SACAgent(
        OBS3, ACT2, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=SMALL), learn_entropy_coef=False
    )
    with pytest.raises(UserError):
        c.load_state_dict(a.state_dict())


def test_get_actor_shares_parameters_without_copying():
    agent = SACAgent(OBS3, ACT2, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=SMALL))
    actor = agent.get_actor()
    assert isinstance(actor, TorchActorModule)
    assert agent.get_actor() is actor
    for p, q in zip(actor.parameters(), agent.model.actor.parameters()):
        assert p.data_ptr() == q.data_ptr()
        assert not p.requires_grad and q.requires_grad
    obs = tuple(np.full(s.shape, 0.3, np.float32) for s in OBS3)
    before = actor.act_(obs, test=True)
    agent.train(random_batch(torch.Generator().manual_seed(6)))
    after = actor.act_(obs, test=True)
    assert not np.array_equal(before, after)
    assert np.all(after >= ACT2.low) and np.all(after <= ACT2.high)


def test_fixed_entropy_coefficient_is_sac_v1():
    agent = SACAgent(
        OBS3,
        ACT2,
        "cpu",
        model_cls=partial(MLPActorCritic, hidden_sizes=SMALL),
        alpha=0.3,
        learn_entropy_coef=False,
    )
    gen = torch.Generator().manual_seed(7)
    for _ in range(3):
        metrics = agent.train(random_batch(gen))
    assert agent.log_alpha is None
    assert float(metrics["entropy_coef"]) == pytest.approx(0.3)
    assert "loss_entropy_coef" not in metrics
    assert {"loss_actor", "loss_critic", "entropy_coef"} <= set(metrics)


def test_optimizer_settings_are_really_applied():
    agent = SACAgent(
        OBS3,
        ACT2,
        "cpu",
        model_cls=partial(MLPActorCritic, hidden_sizes=SMALL),
        optimizer_actor="AdamW",
        optimizer_critic="adam",
        betas_actor=[0.997, 0.998],
        betas_critic=(0.5, 0.6),
        l2_actor=0.01,
        l2_critic=0.02,
        lr_actor=1e-4,
        lr_critic=2e-4,
    )
    assert isinstance(agent.pi_optimizer, torch.optim.AdamW)
    assert isinstance(agent.q_optimizer, torch.optim.Adam)
    pg, qg = agent.pi_optimizer.param_groups[0], agent.q_optimizer.param_groups[0]
    assert pg["betas"] == (0.997, 0.998) and qg["betas"] == (0.5, 0.6)
    assert pg["weight_decay"] == 0.01 and qg["weight_decay"] == 0.02
    assert pg["lr"] == 1e-4 and qg["lr"] == 2e-4
    assert pg["fused"] or pg["foreach"]
    sgd = SACAgent(
        OBS3,
        ACT2,
        "cpu",
        model_cls=partial(MLPActorCritic, hidden_sizes=SMALL),
        optimizer_critic="sgd",
        l2_critic=0.1,
    )
    assert (
        isinstance(sgd.q_optimizer, torch.optim.SGD)
        and sgd.q_optimizer.param_groups[0]["weight_decay"] == 0.1
    )
    with pytest.raises(UserError, match="'adam', 'adamw', 'sgd'"):
        SACAgent(OBS3, ACT2, "cpu", optimizer_actor="rmsprop")
    with pytest.raises(UserError, match="two numbers"):
        SACAgent(OBS3, ACT2, "cpu", betas_critic=[0.9])


def test_redq_n_reaches_the_model_and_is_checked():
    agent = REDQSACAgent(
        OBS3, ACT2, "cpu", model_cls=partial(REDQMLPActorCritic, hidden_sizes=SMALL), n=4, m=3
    )
    assert len(agent.model.qs) == 4 and agent.model.qs.weights[0].shape[0] == 4

    class FixedThree(REDQMLPActorCritic):
        def __init__(self, observation_space, action_space):  # takes no `n`
            super().__init__(observation_space, action_space, hidden_sizes=SMALL, n=3)

    with pytest.raises(UserError, match="n=5 critics"):
        REDQSACAgent(OBS3, ACT2, "cpu", model_cls=FixedThree, n=5)
    with pytest.raises(UserError, match="m <= n"):
        REDQSACAgent(OBS3, ACT2, "cpu", n=2, m=3)


def test_redq_learned_entropy_with_several_critic_updates_per_policy_update():
    torch.manual_seed(0)
    agent = REDQSACAgent(
        OBS3,
        ACT2,
        "cpu",
        model_cls=partial(REDQMLPActorCritic, hidden_sizes=SMALL),
        n=3,
        learn_entropy_coef=True,
        q_updates_per_policy_update=3,
    )
    gen = torch.Generator().manual_seed(8)
    actor_changes, alpha_changes = [], []
    for _ in range(6):
        actor0 = [p.detach().clone() for p in agent.model.actor.parameters()]
        alpha0 = agent.log_alpha.detach().clone()
        critic0 = agent.model.qs.weights[1].detach().clone()
        agent.train(random_batch(gen))
        actor_changes.append(
            not all(torch.equal(a, b) for a, b in zip(actor0, agent.model.actor.parameters()))
        )
        alpha_changes.append(not torch.equal(alpha0, agent.log_alpha))
        assert not torch.equal(critic0, agent.model.qs.weights[1])  # critics learn every step
    assert actor_changes == [False, False, True, False, False, True]
    assert alpha_changes == actor_changes


def test_ensemble_matches_independent_mlps():
    torch.manual_seed(0)
    ens = EnsembleQFunction(OBS3, ACT2, hidden_sizes=(8, 8), n=3)
    gen = torch.Generator().manual_seed(9)
    o, a, *_ = random_batch(gen, size=5)
    x = torch.cat((*o, a), -1)
    expected = []
    for i in range(3):
        h = x
        for layer, (w, b) in enumerate(zip(ens.weights, ens.biases)):
            h = h @ w[i] + b[i, 0]
            if layer < len(ens.weights) - 1:
                h = torch.relu(h)
        expected.append(h.squeeze(-1))
    out = ens(o, a)
    assert out.shape == (3, 5)
    torch.testing.assert_close(out, torch.stack(expected))
    torch.testing.assert_close(
        ens(o, a, members=torch.tensor([2, 0])), torch.stack([expected[2], expected[0]])
    )
    torch.testing.assert_close(ens[1](o, a), expected[1])
    assert [q.index for q in ens] == [0, 1, 2]
    model = MLPActorCritic(OBS3, ACT2, hidden_sizes=(8, 8))
    torch.testing.assert_close(model.q2(o, a), model.qs(o, a)[1])
    # Detached weights: gradients reach the action, not the parameters.
    a.requires_grad_(True)
    ens(o, a, detach_params=True).sum().backward()
    assert a.grad is not None and all(p.grad is None for p in ens.parameters())


def baddbmm_ensemble(ens: EnsembleQFunction, x: torch.Tensor, members=None) -> torch.Tensor:
    """Q values ``(k, B)`` of the selected members, every layer a plain ``baddbmm``."""
    idx = torch.arange(ens.n) if members is None else torch.tensor(members)
    h = x.unsqueeze(0).expand(len(idx), -1, -1)
    for layer, (w, b) in enumerate(zip(ens.weights, ens.biases)):
        h = torch.baddbmm(b[idx], h, w[idx])
        if layer < len(ens.weights) - 1:
            h = torch.relu(h)
    return h.squeeze(-1)


@pytest.mark.parametrize("members", [None, [3, 1]])
def test_ensemble_output_layer_gradients_equal_a_batched_matrix_product(members):
    # The last layer (width -> 1) runs as vector operations instead of baddbmm; values and every
    # gradient must be those of the plain batched product.
    torch.manual_seed(0)
    ens = EnsembleQFunction(OBS3, ACT2, hidden_sizes=(16, 8), n=4)
    gen = torch.Generator().manual_seed(11)
    o, a, *_ = random_batch(gen, size=7)
    a.requires_grad_(True)
    q = ens(o, a, members=members)
    weight = torch.randn(q.shape, generator=gen)
    (q * weight).sum().backward()
    got = [p.grad.clone() for p in ens.parameters()] + [a.grad.clone()]

    for p in ens.parameters():
        p.grad = None
    a.grad = None
    expected_q = baddbmm_ensemble(ens, torch.cat((*o, a), -1), members)
    (expected_q * weight).sum().backward()
    expected = [p.grad for p in ens.parameters()] + [a.grad]

    torch.testing.assert_close(q, expected_q)
    for g, e in zip(got, expected):
        torch.testing.assert_close(g, e)
    # Weights used as constants: the action still gets its gradient through the output layer.
    a.grad = None
    for p in ens.parameters():
        p.grad = None
    ens(o, a, members=members, detach_params=True).sum().backward()
    assert a.grad is not None and a.grad.abs().sum() > 0
    assert all(p.grad is None for p in ens.parameters())


def test_ensemble_runs_under_bfloat16_autocast_like_a_batched_matrix_product():
    # Under autocast the hidden layers come out in bfloat16 while the output weights are
    # float32: the output layer must accept that mix and give float32 gradients.
    torch.manual_seed(0)
    ens = EnsembleQFunction(OBS3, ACT2, hidden_sizes=(16, 8), n=3)
    o, a, *_ = random_batch(torch.Generator().manual_seed(12), size=6)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        q = ens(o, a)
        expected = baddbmm_ensemble(ens, torch.cat((*o, a), -1))
    torch.testing.assert_close(q.float(), expected.float(), atol=0.02, rtol=0.02)
    q.float().sum().backward()
    assert all(p.grad is not None and p.grad.dtype == torch.float32 for p in ens.parameters())


def test_actor_respects_asymmetric_bounds_and_log_prob_is_finite():
    model = MLPActorCritic(OBS3, ACT2, hidden_sizes=(8, 8))
    o, *_ = random_batch(torch.Generator().manual_seed(10), size=64)
    with torch.no_grad():
        model.actor.mu_layer.bias.fill_(30.0)  # saturate tanh
        act, logp = model.actor(o)
    assert torch.all(act[:, 0] <= 2.0) and torch.all(act[:, 0] >= -2.0)
    assert torch.all(act[:, 1] <= 1.0) and torch.all(act[:, 1] >= 0.0)
    assert torch.all(torch.isfinite(logp))
    a1 = model.act(tuple(x[:1] for x in o), test=True)
    assert a1.shape == (2,) and isinstance(a1, np.ndarray)


def test_tutorial_style_model_with_separate_critics_trains():
    class Critic(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.q = torch.nn.Sequential(torch.nn.Linear(7, 16), torch.nn.ReLU(), torch.nn.Linear(16, 1))

        def forward(self, obs, act):
            return self.q(torch.cat((*obs, act), -1)).squeeze(-1)

    class ActorCritic(torch.nn.Module):
        def __init__(self, observation_space, action_space):
            super().__init__()
            self.actor = MLPActorCritic(observation_space, action_space, hidden_sizes=(16, 16)).actor
            self.q1, self.q2 = Critic(), Critic()

    agent = SACAgent(OBS3, ACT2, "cpu", model_cls=ActorCritic)
    q1_before = [p.detach().clone() for p in agent.model.q1.parameters()]
    metrics = agent.train(random_batch(torch.Generator().manual_seed(11)))
    assert torch.isfinite(metrics["loss_actor"])
    assert not all(torch.equal(a, b) for a, b in zip(q1_before, agent.model.q1.parameters()))
    assert all(p.requires_grad for p in agent.model.q1.parameters())


def test_names_and_compat_aliases():
    assert SpinupSacAgent is SACAgent is CompatSAC and CompatREDQ is REDQSACAgent
    assert agent_class("SAC") is SACAgent and agent_class("redqsac") is REDQSACAgent
    with pytest.raises(UserError, match="ALG.ALGORITHM"):
        agent_class("PPO")
    from tmrl.custom import custom_models

    assert custom_models.REDQMLPActorCritic is REDQMLPActorCritic
    assert len(custom_models.REDQMLPActorCritic(OBS, ACT, hidden_sizes=(4,)).qs) == 10


def test_bfloat16_critics_keep_float32_parameters_and_close_values():
    torch.manual_seed(0)
    ens = EnsembleQFunction(OBS3, ACT2, hidden_sizes=(64, 64), n=3)
    low = EnsembleQFunction(OBS3, ACT2, hidden_sizes=(64, 64), n=3, compute_dtype="bfloat16")
    low.load_state_dict(ens.state_dict())
    o, a, *_ = random_batch(torch.Generator().manual_seed(12), size=32)
    ref, out = ens(o, a), low(o, a)
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, ref, rtol=0.05, atol=0.02)
    out.sum().backward()
    assert all(
        p.dtype == torch.float32 and p.grad is not None and p.grad.dtype == torch.float32
        for p in low.parameters()
    )
    with pytest.raises(UserError, match="bfloat16"):
        EnsembleQFunction(OBS3, ACT2, compute_dtype="float16")


@pytest.mark.parametrize("alg, extra", [("SAC", {}), ("SAC", {"fused": False, "update_order": "sequential"}),
                                        ("REDQSAC", {}), ("DROQ", {"q_updates_per_policy_update": 1}),
                                        ("TQC", {}), ("CROSSQ", {"policy_delay": 1, "critic_width": 64})])
def test_alpha_max_holds_a_learned_coefficient_once_it_has_come_down_to_it(alg, extra):
    """``alpha_max`` (``ALG.ALPHA_MAX``): the coefficient falls freely from ``alpha`` past the
    ceiling, then no update lifts it above; without it the same updates lift it well above."""
    from tmrl.config import loader
    from tmrl.config.schema import AGENT_CLASSES, arguments

    cfg = loader.validate({"ALG": {"ALGORITHM": alg, "ALPHA_MAX": 0.01}})
    fed = arguments(cfg, AGENT_CLASSES[alg])["alpha_max"]
    assert fed == 0.01

    def drive(agent, target, n, gen):
        agent.target_entropy = target  # far below the policy's entropy: alpha falls; far above: it rises
        out = []
        for _ in range(n):
            agent.train(random_batch(gen))
            out.append(float(agent.log_alpha.detach().exp()))
        return out

    peaks = {}
    for ceiling in (fed, None):
        torch.manual_seed(0)
        agent = agent_class(alg)(OBS3, ACT2, "cpu", alpha=0.2, lr_entropy=0.3, alpha_max=ceiling, **extra)
        if alg == "SAC":
            assert (agent.fused_update is not None) == extra.get("fused", True)
        gen = torch.Generator().manual_seed(1)
        falling = drive(agent, -100.0, 12, gen)
        assert 0.01 < falling[0] < 0.2 and falling[-1] < 0.01, (ceiling, falling)
        peaks[ceiling] = max(drive(agent, 100.0, 40, gen))
    assert peaks[fed] <= 0.01 * (1 + 1e-6) and peaks[None] > 0.02, peaks


@pytest.mark.parametrize("ceiling", [0.07, 0.01, 0.03])
def test_alpha_max_holds_whatever_the_rounding_of_its_logarithm(ceiling):
    """log(0.07) rounds up in float32: a ceiling compared in float64 would let the coefficient
    go after its first cut."""
    agent = SACAgent(OBS3, ACT2, "cpu", alpha=0.2, lr_entropy=0.3, alpha_max=ceiling)
    gen = torch.Generator().manual_seed(1)
    seen = []
    for target in [-100.0] * 12 + [100.0] * 40:
        agent.target_entropy = target
        agent.train(random_batch(gen))
        seen.append(float(agent.log_alpha.detach().exp()))
    assert min(seen) < ceiling and max(seen[seen.index(min(seen)):]) <= ceiling * (1 + 1e-6), seen


def test_alpha_max_must_be_positive_or_null():
    from tmrl.config import loader
    from tmrl.config.loader import ConfigError

    with pytest.raises(ConfigError, match="ALPHA_MAX"):
        loader.validate({"ALG": {"ALPHA_MAX": 0}})
    assert loader.validate({"ALG": {"ALPHA_MAX": None}})["ALG"]["ALPHA_MAX"] is None
    with pytest.raises(UserError, match="alpha_max"):
        SACAgent(OBS3, ACT2, "cpu", alpha_max=-1.0)
