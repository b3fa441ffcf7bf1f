"""DroQ (tmrl/algorithms/droq.py) and TQC (tmrl/algorithms/tqc.py): one update against a step
written here from each paper's equations (plain SGD, tiny networks, target critics moved away
from the online ones), learning on probe problems, checkpoint round trips, determinism, and
their selection through the config (the lidar models: tests/test_driving_models.py)."""

from __future__ import annotations

import copy
import importlib
import json
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from gymnasium import spaces

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
from test_algorithms import _move_targets_away as move_targets_away

from tmrl.algorithms import ALGORITHMS, DroQAgent, TQCAgent, agent_class
from tmrl.algorithms.droq import DroQMLPActorCritic
from tmrl.algorithms.fused_sac import fused_unsupported_reason
from tmrl.algorithms.tqc import TQCActorCritic
from tmrl.config import loader, schema
from tmrl.config.loader import ConfigError
from tmrl.errors import UserError
from tmrl.models import MLPActorCritic
from tmrl.util import partial

SMALL = (16, 16)


def droq(**kwargs) -> DroQAgent:
    hidden = kwargs.pop("hidden", SMALL)
    obs, act = kwargs.pop("spaces", (OBS3, ACT2))
    return DroQAgent(obs, act, "cpu", model_cls=partial(DroQMLPActorCritic, hidden_sizes=hidden), **kwargs)


def tqc(**kwargs) -> TQCAgent:
    hidden = kwargs.pop("hidden", SMALL)
    obs, act = kwargs.pop("spaces", (OBS3, ACT2))
    model = partial(TQCActorCritic, hidden_sizes=hidden, critic_hidden_sizes=hidden)
    return TQCAgent(obs, act, "cpu", model_cls=model, **kwargs)


def sgd(agent, lr: float):
    """Plain SGD everywhere, so that the reference step is a gradient step written out."""
    agent.pi_optimizer = torch.optim.SGD(agent.model.actor.parameters(), lr=lr)
    agent.q_optimizer = torch.optim.SGD(agent.critics.parameters(), lr=lr)
    agent.alpha_optimizer = torch.optim.SGD([agent.log_alpha], lr=lr)
    return agent


def flat(obs: tuple, act: torch.Tensor) -> torch.Tensor:
    return torch.cat([o.reshape(o.shape[0], -1) for o in obs] + [act], dim=1)


def sgd_update(named: dict, params: dict, loss: torch.Tensor, lr: float) -> None:
    """``named[name] = param - lr * d loss / d param`` for each ``(name, param)`` of ``params``."""
    grads = torch.autograd.grad(loss, list(params.values()))
    for (name, p), g in zip(params.items(), grads):
        named[name] = p.detach() - lr * g


def alpha_step(ag, logp_pi: torch.Tensor, lr: float) -> torch.Tensor:
    loss_alpha = -(ag.log_alpha * (logp_pi.detach() + ag.target_entropy)).mean()
    (g,) = torch.autograd.grad(loss_alpha, [ag.log_alpha])
    return ag.log_alpha.detach() - lr * g


def assert_step(agent, before, expected: dict) -> None:
    for name, p in agent.model.named_parameters():
        torch.testing.assert_close(p.detach(), expected[name], rtol=1e-5, atol=1e-6, msg=name)
    torch.testing.assert_close(agent.log_alpha.detach(), expected["log_alpha"])
    # Targets: Polyak-averaged toward the updated online weights, from their own (moved) values.
    for (name, p), pt, p0 in zip(agent.model.named_parameters(), agent.model_target.parameters(),
                                 before.model_target.parameters()):
        torch.testing.assert_close(pt, agent.polyak * p0 + (1 - agent.polyak) * p.detach(), msg=name)


# --- DroQ: the reference step (Hiraoka et al. 2022, Algorithm 2) ---------------------------------


def dropout_q(params: dict, prefix: str, x: torch.Tensor, rate: float, layers: int) -> torch.Tensor:
    """A dropout Q-function from its weights: each hidden layer is Linear, dropout (a fresh mask
    from the global generator), layer normalisation, ReLU; then a linear output."""
    h = x
    for i in range(layers):
        h = F.linear(h, params[f"{prefix}.net.{4 * i}.weight"], params[f"{prefix}.net.{4 * i}.bias"])
        h = F.dropout(h, rate, training=True)
        ln_w, ln_b = params[f"{prefix}.net.{4 * i + 2}.weight"], params[f"{prefix}.net.{4 * i + 2}.bias"]
        mean = h.mean(-1, keepdim=True)
        var = (h - mean).square().mean(-1, keepdim=True)
        h = torch.relu((h - mean) / torch.sqrt(var + 1e-5) * ln_w + ln_b)
    return F.linear(h, params[f"{prefix}.net.{4 * layers}.weight"], params[f"{prefix}.net.{4 * layers}.bias"]).squeeze(-1)


def reference_droq_step(ag: DroQAgent, batch: tuple, lr: float) -> dict:
    """Target from the min of the two *target* dropout critics, both critics regress on it, the
    actor maximises the *mean* of the two dropout critics (before their step), SAC v2's alpha.
    Random numbers in the documented order: pi at o, a' at o', target masks, (o, a) masks,
    (o, pi) masks (critic by critic, layer by layer)."""
    o, a, r, o2, d, _ = batch
    rate, layers, n = ag.dropout_rate, len(SMALL), len(ag.model.qs)
    online = dict(ag.model.qs.named_parameters())
    target = dict(ag.model_target.qs.named_parameters())
    alpha = ag.log_alpha.detach().exp()
    pi, logp_pi = ag.model.actor(o)
    with torch.no_grad():
        a2, logp_a2 = ag.model.actor(o2)
        q_targ = torch.stack([dropout_q(target, str(i), flat(o2, a2), rate, layers) for i in range(n)])
        y = r + ag.gamma * (1 - d) * (q_targ.min(0).values - alpha * logp_a2)
    q = [dropout_q(online, str(i), flat(o, a), rate, layers) for i in range(n)]
    loss_q = sum(((qi - y) ** 2).mean() for qi in q) / n
    frozen = {k: v.detach() for k, v in online.items()}
    q_pi = torch.stack([dropout_q(frozen, str(i), flat(o, pi), rate, layers) for i in range(n)]).mean(0)
    loss_pi = (alpha * logp_pi - q_pi).mean()
    out = {name: p.detach().clone() for name, p in ag.model.named_parameters()}
    new_q: dict = {}
    sgd_update(new_q, online, loss_q, lr)
    out.update({f"qs.{k}": v for k, v in new_q.items()})
    new_actor: dict = {}
    sgd_update(new_actor, dict(ag.model.actor.named_parameters()), loss_pi, lr)
    out.update({f"actor.{k}": v for k, v in new_actor.items()})
    out["log_alpha"] = alpha_step(ag, logp_pi, lr)
    return out


def test_droq_one_update_matches_the_paper_step():
    torch.manual_seed(0)
    lr = 0.05
    agent = sgd(droq(dropout_rate=0.2, q_updates_per_policy_update=1, gamma=0.9), lr)
    move_targets_away(agent, seed=3)
    batch = random_batch(torch.Generator().manual_seed(2))
    assert 0 < float(batch[4].sum()) < len(batch[4])  # terminal and bootstrapped transitions
    before = copy.deepcopy(agent)
    torch.manual_seed(5)
    expected = reference_droq_step(before, batch, lr)
    torch.manual_seed(5)
    metrics = agent.train(batch)
    assert_step(agent, before, expected)
    assert {"loss_actor", "loss_critic", "entropy_coef", "loss_entropy_coef", "debug_q", "debug_backup"} <= set(metrics)
    assert agent.fused_update is None and fused_unsupported_reason(agent) is not None


def test_droq_dropout_is_drawn_in_every_critic_pass():
    """Same weights, same inputs, different masks: the critics are stochastic in training."""
    torch.manual_seed(0)
    agent = droq(dropout_rate=0.5)
    o, a, *_ = random_batch(torch.Generator().manual_seed(1))
    assert not torch.equal(agent.critics(o, a), agent.critics(o, a))
    assert not torch.equal(agent.critics_target(o, a), agent.critics_target(o, a))


def test_droq_updates_the_policy_once_per_group_of_critic_updates():
    torch.manual_seed(0)
    agent = droq(q_updates_per_policy_update=3)
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


def test_droq_refuses_critics_without_dropout_or_layer_norm_and_bad_settings():
    with pytest.raises(UserError, match="dropout and layer normalisation"):
        DroQAgent(OBS3, ACT2, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=SMALL))
    with pytest.raises(UserError, match="ALG.DROQ_DROPOUT_RATE"):
        droq(dropout_rate=1.0)
    with pytest.raises(UserError, match="ALG.DROQ_Q_UPDATES_PER_POLICY_UPDATE"):
        droq(q_updates_per_policy_update=0)
    assert droq(dropout_rate=0.3).model.qs[1].net[1].p == 0.3  # the rate reaches the model


# --- TQC: the reference step (Kuznetsov et al. 2020, section 4) -----------------------------------


def quantile_mlp(params: dict, prefix: str, x: torch.Tensor, layers: int) -> torch.Tensor:
    h = x
    for i in range(layers):
        h = torch.relu(F.linear(h, params[f"{prefix}.net.{2 * i}.weight"], params[f"{prefix}.net.{2 * i}.bias"]))
    return F.linear(h, params[f"{prefix}.net.{2 * layers}.weight"], params[f"{prefix}.net.{2 * layers}.bias"])


def textbook_quantile_huber(theta: list[torch.Tensor], y: torch.Tensor) -> torch.Tensor:
    """``1/(N M K) sum_n sum_m sum_i rho_{tau_m}(y_i - theta_n^m)`` (batch mean), kappa = 1, with
    ``tau_m = (2m - 1) / (2M)`` for ``m = 1..M``, written as loops over critics and quantiles."""
    total = 0.0
    big_m = theta[0].shape[1]
    for theta_n in theta:
        for m in range(1, big_m + 1):
            tau = (2 * m - 1) / (2 * big_m)
            u = y - theta_n[:, m - 1 : m]  # (B, K)
            huber = torch.where(u.abs() <= 1, 0.5 * u**2, u.abs() - 0.5)
            indicator = (u < 0).float()
            total = total + ((tau - indicator).abs() * huber).mean()
    return total / (len(theta) * big_m)


def reference_tqc_step(ag: TQCAgent, batch: tuple, lr: float) -> dict:
    """Pool the N*M target quantiles at (o', a'), sort, keep the N*(M - d) smallest, subtract
    alpha log pi; quantile Huber regression of every critic's quantiles; the actor maximises the
    mean of all quantiles of all critics (before their step); SAC v2's alpha."""
    o, a, r, o2, d, _ = batch
    n, m, drop, layers = ag.n, ag.n_quantiles, ag.drop_per_critic, len(SMALL)
    online = dict(ag.model.qs.named_parameters())
    target = dict(ag.model_target.qs.named_parameters())
    alpha = ag.log_alpha.detach().exp()
    pi, logp_pi = ag.model.actor(o)
    with torch.no_grad():
        a2, logp_a2 = ag.model.actor(o2)
        pooled = torch.cat([quantile_mlp(target, str(i), flat(o2, a2), layers) for i in range(n)], dim=1)
        kept = torch.sort(pooled, dim=1).values[:, : n * (m - drop)]
        y = r[:, None] + ag.gamma * (1 - d[:, None]) * (kept - alpha * logp_a2[:, None])
    theta = [quantile_mlp(online, str(i), flat(o, a), layers) for i in range(n)]
    loss_q = textbook_quantile_huber(theta, y)
    frozen = {k: v.detach() for k, v in online.items()}
    z_pi = torch.stack([quantile_mlp(frozen, str(i), flat(o, pi), layers) for i in range(n)])
    loss_pi = (alpha * logp_pi - z_pi.mean(dim=(0, 2))).mean()
    out = {name: p.detach().clone() for name, p in ag.model.named_parameters()}
    new_q: dict = {}
    sgd_update(new_q, online, loss_q, lr)
    out.update({f"qs.{k}": v for k, v in new_q.items()})
    new_actor: dict = {}
    sgd_update(new_actor, dict(ag.model.actor.named_parameters()), loss_pi, lr)
    out.update({f"actor.{k}": v for k, v in new_actor.items()})
    out["log_alpha"] = alpha_step(ag, logp_pi, lr)
    out["loss_critic"] = loss_q.detach()
    out["y"] = y
    return out


def test_tqc_one_update_matches_the_paper_step():
    torch.manual_seed(0)
    lr = 0.05
    agent = sgd(tqc(n=3, n_quantiles=5, drop_per_critic=2, gamma=0.9), lr)
    move_targets_away(agent, seed=4)
    batch = random_batch(torch.Generator().manual_seed(2))
    before = copy.deepcopy(agent)
    torch.manual_seed(6)
    expected = reference_tqc_step(before, batch, lr)
    torch.manual_seed(6)
    metrics = agent.train(batch)
    assert_step(agent, before, expected)
    torch.testing.assert_close(metrics["loss_critic"], expected["loss_critic"])
    torch.testing.assert_close(metrics["debug_backup"], expected["y"].mean())
    assert agent.fused_update is None and fused_unsupported_reason(agent) is not None


def test_tqc_truncation_pools_the_critics_before_dropping_the_largest_atoms():
    """Critic 0 predicts far larger values than critic 1: pooled truncation drops only critic 0's
    top atoms (dropping per critic would also drop critic 1's largest)."""
    torch.manual_seed(0)
    agent = tqc(n=2, n_quantiles=4, drop_per_critic=1)
    z = torch.tensor([[[10.0, 11.0, 12.0, 13.0]], [[0.0, 1.0, 2.0, 3.0]]])  # (N=2, B=1, M=4)
    agent.critics_target = lambda obs, act: z
    atoms = agent.target_q(None, torch.zeros(1, 2))
    assert atoms.tolist() == [[0.0, 1.0, 2.0, 3.0, 10.0, 11.0]]


def test_tqc_refuses_settings_that_leave_no_atom_or_do_not_fit_the_model():
    with pytest.raises(UserError, match="ALG.TQC_DROP_PER_CRITIC"):
        tqc(n=2, n_quantiles=3, drop_per_critic=3)
    with pytest.raises(UserError, match="ALG.TQC_N"):
        tqc(n=0)
    with pytest.raises(UserError, match="ALG.TQC_N and ALG.TQC_QUANTILES"):
        TQCAgent(OBS3, ACT2, "cpu", model_cls=lambda o, a: TQCActorCritic(o, a, (8,), n=2, critic_hidden_sizes=(8,)),
                 n=3)


# --- both: learning, bootstrapping, checkpoints, determinism -------------------------------------

LEARN = {"lr_actor": 3e-3, "lr_critic": 3e-3, "lr_entropy": 3e-3, "alpha": 0.05}


def make(algo: str, obs=OBS, **kwargs):
    if algo == "droq":
        return droq(spaces=(obs, ACT), hidden=(64, 64), q_updates_per_policy_update=2, **LEARN, **kwargs)
    return tqc(spaces=(obs, ACT), hidden=(64, 64), n=3, n_quantiles=10, drop_per_critic=1, **LEARN, **kwargs)


@pytest.mark.parametrize("algo", ["droq", "tqc"])
def test_learns_the_probe_problem(algo):
    torch.manual_seed(0)
    agent = make(algo)
    gen = torch.Generator().manual_seed(1)
    assert policy_error(agent) > 0.2
    for _ in range(400):
        metrics = agent.train(probe_batch(gen))
    assert policy_error(agent) < 0.1
    assert float(metrics["entropy_coef"]) < 0.05  # learned down toward the target entropy


@pytest.mark.parametrize("algo", ["droq", "tqc"])
def test_learns_a_probe_that_needs_bootstrapping(algo):
    torch.manual_seed(0)
    agent = make(algo, obs=OBS2, gamma=0.9)
    gen = torch.Generator().manual_seed(1)
    assert first_step_error(agent) > 0.2
    for _ in range(500):
        agent.train(two_step_batch(gen))
    assert first_step_error(agent) < 0.1


def small(algo: str):
    return droq(q_updates_per_policy_update=2) if algo == "droq" else tqc(n=3, n_quantiles=5)


@pytest.mark.parametrize("algo", ["droq", "tqc"])
def test_state_dict_round_trip_resumes_identically(algo):
    gen = torch.Generator().manual_seed(5)
    batches = [random_batch(gen) for _ in range(7)]
    torch.manual_seed(0)
    a = small(algo)
    for b in batches[:3]:
        a.train(b)
    state = copy.deepcopy(a.state_dict())
    torch.manual_seed(1)
    b = small(algo)
    actor_b = b.get_actor()
    b.load_state_dict(state)
    if algo == "droq":
        assert b.i_update == 3 and torch.equal(b.loss_pi, a.loss_pi)
    for batch in batches[3:]:
        torch.manual_seed(42)
        ma = a.train(batch)
        torch.manual_seed(42)
        mb = b.train(batch)
        assert {k: float(v) for k, v in ma.items()} == {k: float(v) for k, v in mb.items()}
    for x, y in zip(a.model.parameters(), b.model.parameters()):
        assert torch.equal(x, y)
    for x, y in zip(a.model_target.parameters(), b.model_target.parameters()):
        assert torch.equal(x, y)
    assert torch.equal(a.log_alpha, b.log_alpha)
    # Adam's moments came along: the next step is the same too (checked above), and the state is.
    assert a.q_optimizer.state_dict()["state"][0]["step"] == b.q_optimizer.state_dict()["state"][0]["step"]
    assert all(torch.equal(x, y) for x, y in zip(actor_b.parameters(), b.model.actor.parameters()))


@pytest.mark.parametrize("algo", ["droq", "tqc"])
def test_state_dict_from_another_configuration_is_refused(algo):
    a = small(algo)
    other = droq(hidden=(8, 8)) if algo == "droq" else tqc(n=2, n_quantiles=5)
    with pytest.raises(UserError, match="same algorithm and model settings"):
        other.load_state_dict(a.state_dict())


@pytest.mark.parametrize("algo", ["droq", "tqc"])
def test_same_seed_same_parameters(algo):
    def run():
        torch.manual_seed(123)
        agent = small(algo)
        gen = torch.Generator().manual_seed(4)
        for _ in range(8):
            agent.train(random_batch(gen))
        return [p.detach().clone() for p in agent.model.parameters()] + [agent.log_alpha.detach().clone()]

    assert all(torch.equal(x, y) for x, y in zip(run(), run()))


@pytest.mark.parametrize("algo", ["droq", "tqc"])
def test_default_models_are_the_papers(algo):
    obs, act = spaces.Box(-1.0, 1.0, (3,), np.float32), spaces.Box(-1.0, 1.0, (2,), np.float32)
    if algo == "droq":
        agent = DroQAgent(obs, act, "cpu")
        assert len(agent.critics) == 2 and agent.q_updates_per_policy_update == 20
        q = agent.model.qs[0].net
        kinds = [type(m) for m in q]
        assert kinds == [torch.nn.Linear, torch.nn.Dropout, torch.nn.LayerNorm, torch.nn.ReLU] * 2 + [torch.nn.Linear]
        assert q[1].p == 0.01 and q[0].out_features == 256
    else:
        agent = TQCAgent(obs, act, "cpu")
        assert (agent.n, agent.n_quantiles, agent.drop_per_critic, agent.kept_atoms) == (5, 25, 2, 115)
        widths = [m.out_features for m in agent.model.qs[0].net if isinstance(m, torch.nn.Linear)]
        assert widths == [512, 512, 512, 25]
    widths = [m.out_features for m in agent.model.actor.net if isinstance(m, torch.nn.Linear)]
    assert widths == [256, 256]


# --- selection through the config -----------------------------------------------------------------

_FRESH = ("tmrl.config.config_objects", "tmrl.config.config_constants")


@pytest.fixture
def config_objects(monkeypatch):
    """``load(override)``: a freshly imported tmrl.config.config_objects (the previous modules are
    put back afterwards)."""
    import tmrl.config as package

    saved = {name: sys.modules.get(name) for name in _FRESH}
    attrs = {name: vars(package).get(name.rsplit(".", 1)[1]) for name in _FRESH}

    def forget() -> None:
        for name in _FRESH:
            sys.modules.pop(name, None)
            if hasattr(package, name.rsplit(".", 1)[1]):
                delattr(package, name.rsplit(".", 1)[1])

    def load(override: dict):
        monkeypatch.setenv(loader.OVERRIDE_ENV, json.dumps(override))
        forget()
        return importlib.import_module("tmrl.config.config_objects")

    yield load
    forget()
    for name, module in saved.items():
        if module is not None:
            sys.modules[name] = module
            setattr(package, name.rsplit(".", 1)[1], attrs[name])


GYM = {"RTGYM_INTERFACE": "GYM", "GYM_ID": "Pendulum-v1"}


def test_droq_is_selected_through_the_config(config_objects):
    o = config_objects({"ENV": GYM, "ALG": {"ALGORITHM": "droq", "DROQ_DROPOUT_RATE": 0.05,
                                            "DROQ_Q_UPDATES_PER_POLICY_UPDATE": 4, "LR_ACTOR": 0.002}})
    assert o.AGENT.func is DroQAgent and o.TRAIN_MODEL is DroQMLPActorCritic
    kw = o.AGENT.keywords
    assert (kw["dropout_rate"], kw["q_updates_per_policy_update"], kw["lr_actor"]) == (0.05, 4, 0.002)
    assert "n_quantiles" not in kw and "update_order" not in kw
    env = o.ENV_CLS()
    try:
        agent = o.AGENT(env.observation_space, env.action_space, "cpu")
    finally:
        env.close()
    assert agent.model.qs[0].net[1].p == 0.05 and agent.q_updates_per_policy_update == 4
    # The worker's policy class loads the trained actor's weights.
    policy = o.POLICY(env.observation_space, env.action_space)
    policy.load_state_dict(agent.get_actor().state_dict())


def test_tqc_is_selected_through_the_config(config_objects):
    o = config_objects({"ENV": GYM, "ALG": {"ALGORITHM": "TQC", "TQC_N": 3, "TQC_QUANTILES": 7,
                                            "TQC_DROP_PER_CRITIC": 1}})
    assert o.AGENT.func is TQCAgent and o.TRAIN_MODEL is TQCActorCritic
    kw = o.AGENT.keywords
    assert (kw["n"], kw["n_quantiles"], kw["drop_per_critic"]) == (3, 7, 1)
    env = o.ENV_CLS()
    try:
        agent = o.AGENT(env.observation_space, env.action_space, "cpu")
    finally:
        env.close()
    assert len(agent.critics) == 3 and agent.kept_atoms == 18
    policy = o.POLICY(env.observation_space, env.action_space)
    policy.load_state_dict(agent.get_actor().state_dict())


@pytest.mark.parametrize("algo", ["DROQ", "TQC"])
def test_image_interfaces_refuse_droq_and_tqc_in_one_line_lidar_ones_take_them(config_objects, algo):
    from tmrl.driving.models import LIDAR_MODELS

    with pytest.raises(ConfigError, match="has no image model") as err:
        config_objects({"ENV": {"RTGYM_INTERFACE": "SIMFULL"}, "ALG": {"ALGORITHM": algo}})
    assert "\n" not in str(err.value)
    # tests/test_driving_models.py trains them on the lidar interfaces
    assert config_objects({"ENV": {"RTGYM_INTERFACE": "SIMLIDAR"}, "ALG": {"ALGORITHM": algo}}).TRAIN_MODEL is \
        LIDAR_MODELS[algo]


def test_the_table_registry_and_signatures_agree_for_droq_and_tqc():
    assert agent_class("DroQ") is DroQAgent and agent_class("t-q-c") is TQCAgent
    assert {"DROQ", "TQC"} <= set(ALGORITHMS) and tuple(ALGORITHMS) == schema.ALGORITHMS
    fed = schema.fed_arguments()
    not_settings = {"self", "observation_space", "action_space", "device", "model_cls"}
    import inspect

    for cls in (DroQAgent, TQCAgent):
        params = dict(inspect.signature(cls.__init__).parameters)
        assert set(params) - not_settings == set(fed[cls.__name__])
        for arg, (key, class_default) in fed[cls.__name__].items():
            if class_default is not schema.NO_CLASS_DEFAULT:
                assert params[arg].default == class_default, key
    cfg = schema.defaults()["ALG"]
    assert (cfg["DROQ_DROPOUT_RATE"], cfg["DROQ_Q_UPDATES_PER_POLICY_UPDATE"]) == (0.01, 20)
    assert (cfg["TQC_N"], cfg["TQC_QUANTILES"], cfg["TQC_DROP_PER_CRITIC"]) == (5, 25, 2)
