"""BRO (tmrl.algorithms.bro): the BroNet block, the pessimistic target and value, the quantile
loss it regresses with, and the whole agent (an update on the lidar spaces, checkpoints, the
config). Expected values are worked out by hand on networks of two or three units."""

from __future__ import annotations

import json
import math
from functools import partial

import gymnasium
import numpy as np
import pytest
import torch

from tmrl.algorithms import BROAgent, agent_class
from tmrl.algorithms.bro import BROActorCritic, BroNet, BroNetBlock, BroNetQuantileCritic
from tmrl.batch import Batch
from tmrl.errors import UserError

OBS = gymnasium.spaces.Box(-1, 1, (3,), np.float32)
ACT = gymnasium.spaces.Box(-1, 1, (2,), np.float32)


def tiny_agent(**kwargs) -> BROAgent:
    torch.manual_seed(0)
    kwargs.setdefault("model_cls", partial(BROActorCritic, hidden_sizes=(4,)))
    return BROAgent(OBS, ACT, "cpu", n=2, n_quantiles=3, critic_width=3, critic_blocks=1, **kwargs)


def constant_critic(critic: BroNetQuantileCritic, quantiles: list[float]) -> None:
    """Make ``critic`` output ``quantiles`` whatever its input: a zero head weight, the values as bias."""
    with torch.no_grad():
        critic.net.head.weight.zero_()
        critic.net.head.bias.copy_(torch.tensor(quantiles))


# --- the network ------------------------------------------------------------------------------------


def _identity_block(width: int) -> BroNetBlock:
    block = BroNetBlock(width)
    with torch.no_grad():
        for fc in (block.fc1, block.fc2):
            fc.weight.copy_(torch.eye(width))
            fc.bias.zero_()
    return block


def test_a_bronet_block_is_its_input_plus_the_normalised_branch():
    """x = (1, 2), identity weights: LN(x) = (-1, 1), ReLU -> (0, 1), LN -> (-1, 1), plus x -> (0, 3)."""
    out = _identity_block(2)(torch.tensor([[1.0, 2.0]]))
    assert out.tolist()[0] == pytest.approx([0.0, 3.0], abs=1e-4)


def test_bronet_is_stem_layernorm_relu_blocks_then_head():
    """Stem identity on (3, 1): LN -> (1, -1), ReLU -> (1, 0); block: LN(1, 0) = (1, -1) -> ReLU (1, 0)
    -> LN (1, -1), plus (1, 0) -> (2, -1); head (1, 1) with bias 0.5 -> 1.5."""
    net = BroNet(2, 2, 1, 1)
    with torch.no_grad():
        net.stem.weight.copy_(torch.eye(2))
        net.stem.bias.zero_()
        net.blocks[0].load_state_dict(_identity_block(2).state_dict())
        net.head.weight.copy_(torch.tensor([[1.0, 1.0]]))
        net.head.bias.fill_(0.5)
    assert net(torch.tensor([[3.0, 1.0]])).item() == pytest.approx(1.5, abs=1e-4)
    assert len(BroNet(2, 4, 0, 1).blocks) == 0 and len(BroNet(2, 4, 3, 1).blocks) == 3


def test_the_critic_reads_observation_then_action_and_outputs_its_quantiles():
    critic = BroNetQuantileCritic(OBS, ACT, width=3, blocks=2, n_quantiles=5)
    assert critic.net.stem.in_features == 5 and critic.net.head.out_features == 5
    out = critic(torch.zeros(7, 3), torch.zeros(7, 2))
    assert out.shape == (7, 5)


# --- the target and the actor's value ---------------------------------------------------------------


def test_the_pessimistic_quantiles_are_mean_minus_beta_standard_deviations():
    """Two critics: quantiles (0, 2, 4) and (2, 2, 8): mean (1, 2, 6), population standard
    deviation (1, 0, 2). beta 1: (0, 2, 4), their minimum; beta 0: the mean; beta 0.5: (0.5, 2, 5)."""
    z = torch.tensor([[[0.0, 2.0, 4.0]], [[2.0, 2.0, 8.0]]])  # (N=2, B=1, M=3)
    assert tiny_agent(pessimism=1.0)._pessimistic(z).tolist() == [[0.0, 2.0, 4.0]]
    assert tiny_agent(pessimism=0.0)._pessimistic(z).tolist() == [[1.0, 2.0, 6.0]]
    assert tiny_agent(pessimism=0.5)._pessimistic(z).tolist() == [[0.5, 2.0, 5.0]]
    # the actor maximises their mean over quantiles: beta 1 -> 2, beta 0 -> 3
    assert tiny_agent(pessimism=1.0).policy_q(z).tolist() == [2.0]
    assert tiny_agent(pessimism=0.0).policy_q(z).tolist() == [3.0]


def test_three_critics_take_the_population_standard_deviation_and_two_the_same_in_closed_form():
    """Three critics: quantiles 0, 3 and 6 have mean 3 and population deviation sqrt(6); beta 1
    gives 3 - sqrt(6). Two critics (computed as ``mean - beta |a - b| / 2``) agree with
    ``mean - beta std`` on random values."""
    three = BROAgent(OBS, ACT, "cpu", n=3, n_quantiles=1, critic_width=3, critic_blocks=1, pessimism=1.0)
    z3 = torch.tensor([[[0.0]], [[3.0]], [[6.0]]])
    assert three._pessimistic(z3).item() == pytest.approx(3.0 - 6.0 ** 0.5)
    z2 = torch.randn(2, 5, 3, generator=torch.Generator().manual_seed(0))
    for beta in (0.3, 1.0, 2.0):
        expected = z2.mean(0) - beta * z2.std(0, unbiased=False)
        torch.testing.assert_close(tiny_agent(pessimism=beta)._pessimistic(z2), expected)


def _batch(rew: float, terminated: float) -> Batch:
    obs = torch.tensor([[0.1, -0.2, 0.3]])
    return Batch(obs, torch.tensor([[0.5, -0.5]]), torch.tensor([rew]), obs * 2, torch.tensor([terminated]),
                 torch.tensor([0.0]))


def test_the_target_reads_the_target_critics_per_quantile_and_stops_at_termination():
    """Target critics output (0, 2, 4) and (2, 2, 8) (beta 1: (0, 2, 4)); online critics something
    else. y = r + gamma (1 - terminated) (z - alpha log pi(a'|o')), per quantile."""
    agent = tiny_agent(gamma=0.9)
    for critic, values in zip(agent.critics_target.modules, ([0.0, 2.0, 4.0], [2.0, 2.0, 8.0])):
        constant_critic(critic, values)
    for critic in agent.critics.modules:  # the online critics must not be read
        constant_critic(critic, [100.0, 100.0, 100.0])
    alpha = torch.tensor(0.5)
    b = _batch(rew=1.0, terminated=0.0)
    torch.manual_seed(3)
    _, logp = agent.actor(b.next_obs)
    torch.manual_seed(3)
    y = agent.target_value(b, alpha)
    lp = float(logp.detach())
    expected = [1.0 + 0.9 * (z - 0.5 * lp) for z in (0.0, 2.0, 4.0)]
    assert y.shape == (1, 3) and y[0].tolist() == pytest.approx(expected, rel=1e-5)
    assert agent.target_value(_batch(rew=1.0, terminated=1.0), alpha)[0].tolist() == [1.0, 1.0, 1.0]


def test_the_critics_regress_every_quantile_on_every_target_atom():
    """One critic, quantiles (0, 1) at fractions (1/4, 3/4), target atoms (0.5, 0.5): each pair has
    |u| = 0.5, Huber 0.125; theta 0 lies below the atoms (weight 1/4), theta 1 above (weight
    1 - 3/4): every term 0.03125, and so the mean."""
    agent = tiny_agent()
    loss = agent.critic_loss(torch.tensor([[[0.0, 1.0]]]), torch.tensor([[0.5, 0.5]]))
    assert loss.item() == pytest.approx(0.03125)


# --- the agent --------------------------------------------------------------------------------------


def test_one_update_on_the_lidar_spaces_moves_critics_actor_and_targets_by_polyak():
    from tmrl.driving.models import LidarBROActorCritic
    from tmrl.sim.demo import _demo_config
    from tmrl.sim.interfaces import fast_env

    env = fast_env(_demo_config("SIMLIDAR", "classic"))
    try:
        obs_space, act_space = env.observation_space, env.action_space
    finally:
        env.close()
    torch.manual_seed(0)
    agent = BROAgent(obs_space, act_space, "cpu", model_cls=LidarBROActorCritic, critic_width=16, polyak=0.9)
    rng = np.random.default_rng(0)

    def sample(n: int) -> tuple:
        return tuple(torch.as_tensor(np.stack([s.sample() for _ in range(n)])) for s in obs_space.spaces)

    obs, nxt = sample(8), sample(8)
    act = torch.as_tensor(rng.uniform(-1, 1, (8, 3)), dtype=torch.float32)
    batch = (obs, act, torch.ones(8), nxt, torch.zeros(8), torch.zeros(8))
    before = {k: v.clone() for k, v in agent.model.state_dict().items()}
    target_before = {k: v.clone() for k, v in agent.model_target.state_dict().items()}
    metrics = agent.train(batch)
    after = agent.model.state_dict()
    assert all(math.isfinite(float(v)) for v in metrics.values())
    assert not torch.equal(before["qs.0.critic.net.stem.weight"], after["qs.0.critic.net.stem.weight"])
    assert not torch.equal(before["actor.net.0.weight"], after["actor.net.0.weight"])
    key = "qs.1.critic.net.head.weight"
    expected = 0.9 * target_before[key] + 0.1 * after[key]
    assert torch.allclose(agent.model_target.state_dict()[key], expected, atol=1e-6)


def test_a_checkpoint_gives_back_the_same_agent():
    agent = tiny_agent()
    batch = (torch.rand(16, 3), torch.rand(16, 2) * 2 - 1, torch.rand(16), torch.rand(16, 3), torch.zeros(16),
             torch.zeros(16))
    for _ in range(3):
        agent.train(batch)
    state = agent.state_dict()
    fresh = tiny_agent()
    fresh.load_state_dict(state)
    o, a = torch.rand(5, 3), torch.rand(5, 2)
    assert torch.equal(agent.critics(o, a), fresh.critics(o, a))
    assert torch.equal(agent.critics_target(o, a), fresh.critics_target(o, a))
    torch.manual_seed(1)
    m1 = agent.train(batch)
    torch.manual_seed(1)
    m2 = fresh.train(batch)
    assert float(m1["loss_critic"]) == float(m2["loss_critic"])


@pytest.mark.parametrize("kwargs, key", [
    ({"pessimism": -0.1}, "ALG.BRO_PESSIMISM"),
    ({"critic_width": 0}, "ALG.BRO_CRITIC_WIDTH"),
    ({"critic_blocks": -1}, "ALG.BRO_CRITIC_BLOCKS"),
    ({"n": 0}, "ALG.BRO_N"),
    ({"n_quantiles": 0}, "ALG.BRO_QUANTILES"),
])
def test_bad_arguments_name_their_setting(kwargs, key):
    with pytest.raises(UserError, match=key):
        BROAgent(OBS, ACT, "cpu", **kwargs)


def test_the_config_selects_bro_and_its_settings_reach_the_agent(tmp_path):
    from tmrl.assembly import assemble
    from tmrl.config import loader
    from tmrl.driving.models import LidarBROActorCritic

    assert agent_class("bro") is BROAgent
    path = tmp_path / "config.json"
    raw = loader.shipped_config("SIMLIDAR")
    raw["ALG"].update({"ALGORITHM": "BRO", "BRO_CRITIC_WIDTH": 24, "BRO_CRITIC_BLOCKS": 2, "BRO_PESSIMISM": 0.5,
                       "BRO_QUANTILES": 7, "BRO_N": 3})
    path.write_text(json.dumps(raw), encoding="utf-8")
    built = assemble(loader.load_config(path))
    assert built.TRAIN_MODEL is LidarBROActorCritic
    env = built.ENV_CLS()
    try:
        agent = built.AGENT(env.observation_space, env.action_space, "cpu")
    finally:
        env.close()
    assert isinstance(agent, BROAgent) and agent.pessimism == 0.5 and len(agent.critics) == 3
    critic = agent.model.qs[0].critic
    assert critic.net.head.out_features == 7 and len(critic.net.blocks) == 2 and critic.net.stem.out_features == 24

