"""SimbaV2-style agent (tmrl/algorithms/simbav2.py): the C51 projection and the target it builds,
the hyperspherical normalisation and the weight projection after a step, the LERP block, the
reward scaler, one real update on the lidar spaces, checkpoints, the non-finite guard and the
compiled update, each against values computed by hand on tiny networks."""

from __future__ import annotations

import io
import math
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces

from tmrl.algorithms.simbav2 import (
    HyperLinear,
    LerpBlock,
    ReturnScaler,
    SimbaV2ActorCritic,
    SimbaV2Agent,
    SimbaV2Critic,
    categorical_projection,
    l2_normalize,
)
from tmrl.batch import Batch
from tmrl.driving.models import LidarActor, LidarSimbaV2ActorCritic
from tmrl.errors import UserError
from tmrl.util import partial

OBS = spaces.Box(-1.0, 1.0, (1,), np.float32)
ACT = spaces.Box(-1.0, 1.0, (1,), np.float32)
ACT3 = spaces.Box(-1.0, 1.0, (3,), np.float32)
LIDAR = spaces.Tuple([spaces.Box(0, 1000, (1,)), spaces.Box(0, 1, (1,)), spaces.Box(0, np.inf, (76,)), ACT3, ACT3])
TINY = {"hidden_sizes": (8, 8), "n_atoms": 5, "v_max": 2.0, "critic_width": 4, "critic_blocks": 1}
SUPPORT = [-2.0, -1.0, 0.0, 1.0, 2.0]


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_agent(seed: int = 0, **kwargs: Any) -> SimbaV2Agent:
    torch.manual_seed(seed)
    model = {k: kwargs.pop(k) for k in list(kwargs) if k in ("hidden_sizes",)} or {"hidden_sizes": (8, 8)}
    args = {k: v for k, v in TINY.items() if k != "hidden_sizes"}
    args.update(kwargs)
    return SimbaV2Agent(OBS, ACT, "cpu", model_cls=partial(SimbaV2ActorCritic, **model), **args)


def lidar_agent(seed: int = 0, **kwargs: Any) -> SimbaV2Agent:
    torch.manual_seed(seed)
    return SimbaV2Agent(LIDAR, ACT3, "cpu", model_cls=partial(LidarSimbaV2ActorCritic, hidden_sizes=(16, 16)),
                        n_atoms=11, v_max=5.0, critic_width=8, critic_blocks=1, **kwargs)


def lidar_obs(b: int, g: torch.Generator) -> tuple[torch.Tensor, ...]:
    return (torch.rand(b, 1, generator=g) * 300, torch.rand(b, 1, generator=g), torch.rand(b, 76, generator=g) * 300,
            torch.rand(b, 3, generator=g) * 2 - 1, torch.rand(b, 3, generator=g) * 2 - 1)


def lidar_batch(b: int = 32, seed: int = 1) -> tuple:
    g = torch.Generator().manual_seed(seed)
    return (lidar_obs(b, g), torch.rand(b, 3, generator=g) * 2 - 1, torch.randn(b, generator=g) * 3,
            lidar_obs(b, g), (torch.rand(b, generator=g) < 0.2).float(), (torch.rand(b, generator=g) < 0.1).float())


def set_distribution(critic: SimbaV2Critic, probs: list[float]) -> None:
    """Make ``critic`` give ``probs`` whatever its input: zero output weights, logits log(p)."""
    with torch.no_grad():
        critic.out.weight.zero_()
        critic.out.bias.copy_(torch.tensor(probs).log())


# --- (1) the C51 projection, and the target it builds -------------------------------------------


def test_the_projection_splits_mass_between_neighbours_and_clips_at_the_ends():
    probs = torch.tensor([[0.1, 0.2, 0.3, 0.2, 0.2]])
    # -3 lies beyond -2: all to the first atom; -0.5 halfway between -1 and 0; 0.25 a quarter of
    # the way from 0 to 1 (3/4 to 0, 1/4 to 1); 2 exactly on the last atom; 5 beyond it
    atoms = torch.tensor([[-3.0, -0.5, 0.25, 2.0, 5.0]])
    got = categorical_projection(probs, atoms, -2.0, 2.0)
    expected = torch.tensor([[0.1, 0.1, 0.1 + 0.3 * 0.75, 0.3 * 0.25, 0.4]])
    torch.testing.assert_close(got, expected)
    # on the atoms exactly: unchanged
    torch.testing.assert_close(categorical_projection(probs, torch.tensor([SUPPORT]), -2.0, 2.0), probs)


def test_the_target_is_the_projected_shifted_distribution_of_the_target_critic_of_smaller_mean():
    agent = tiny_agent(gamma=0.5, alpha=0.0, learn_entropy_coef=False, scale_rewards=False)
    # target critics: means 0.2 and -0.2, the second is taken; the online ones differ from both
    set_distribution(agent.model_target.qs[0], [0.1, 0.2, 0.3, 0.2, 0.2])
    set_distribution(agent.model_target.qs[1], [0.4, 0.1, 0.1, 0.1, 0.3])
    for q in agent.model.qs:
        set_distribution(q, [0.6, 0.1, 0.1, 0.1, 0.1])
    b = Batch(torch.zeros(3, 1), torch.zeros(3, 1), torch.tensor([0.5, 0.5, 3.0]), torch.zeros(3, 1),
              torch.tensor([0.0, 1.0, 0.0]), torch.zeros(3))
    got = agent.target_value(b, agent._entropy_coef())
    expected = torch.tensor([
        # 0.5 + 0.5 z = [-0.5, 0, 0.5, 1, 1.5] carrying [0.4, 0.1, 0.1, 0.1, 0.3]
        [0.0, 0.2, 0.2 + 0.1 + 0.05, 0.05 + 0.1 + 0.15, 0.15],
        # terminated: all the mass at r = 0.5, halfway between 0 and 1
        [0.0, 0.0, 0.5, 0.5, 0.0],
        # 3 + 0.5 z lies beyond the support: all on its last atom
        [0.0, 0.0, 0.0, 0.0, 1.0],
    ])
    torch.testing.assert_close(got, expected)


def test_the_target_divides_the_reward_by_the_scale_and_shifts_the_atoms_by_the_entropy_term():
    agent = tiny_agent(gamma=0.5, alpha=0.1, learn_entropy_coef=False)
    for q in agent.model_target.qs:
        set_distribution(q, [0.0001, 0.0001, 0.9996, 0.0001, 0.0001])
    with torch.no_grad():
        agent.reward_scaler.var.fill_(4.0)  # scale 2
    torch.manual_seed(3)
    obs2 = torch.zeros(1, 1)
    with torch.no_grad():
        _, logp = agent.actor(obs2)
    b = Batch(torch.zeros(1, 1), torch.zeros(1, 1), torch.tensor([2.0]), obs2, torch.zeros(1), torch.zeros(1))
    torch.manual_seed(3)
    got = agent.target_value(b, agent._entropy_coef())
    # the mass at z = 0 moves to 2 / 2 + 0.5 (0 - 0.1 log pi)
    pos = 1.0 - 0.05 * float(logp)
    mass = torch.zeros(5)
    low = math.floor(pos)
    mass[low + 2], mass[low + 3] = 1.0 - (pos - low), pos - low
    torch.testing.assert_close(got[0], mass, atol=1e-3, rtol=0)


# --- (2) hyperspherical normalisation and the weight projection ----------------------------------


def test_features_are_shifted_and_normalised_onto_the_sphere():
    torch.testing.assert_close(l2_normalize(torch.tensor([[3.0, 4.0]])), torch.tensor([[0.6, 0.8]]))
    critic = SimbaV2Critic(OBS, ACT, width=2, blocks=0, n_atoms=5, shift=4.0)
    with torch.no_grad():
        critic.embed.weight.copy_(torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
        critic.embed_scaler.param.copy_(torch.tensor([2.0, 1.0]) / critic.embed_scaler.factor)
    # [3, 0] and the shift 4: [3, 0, 4] / 5; the rows pick 0.6 and 0.8; scaled 1.2, 0.8; normalised
    h = critic.embedding(torch.tensor([[3.0, 0.0]]))
    torch.testing.assert_close(h, torch.tensor([[1.2, 0.8]]) / math.sqrt(1.2**2 + 0.8**2))


def test_project_puts_every_weight_row_back_to_norm_one():
    layer = HyperLinear(2, 2)
    with torch.no_grad():
        layer.weight.copy_(torch.tensor([[3.0, 4.0], [0.0, 2.0]]))
    layer.project_()
    torch.testing.assert_close(layer.weight, torch.tensor([[0.6, 0.8], [0.0, 1.0]]))


def test_the_critic_rows_are_back_on_the_sphere_after_each_step():
    agent = tiny_agent()
    g = torch.Generator().manual_seed(2)
    for _ in range(3):
        b = (torch.randn(16, 1, generator=g), torch.rand(16, 1, generator=g) * 2 - 1, torch.randn(16, generator=g),
             torch.randn(16, 1, generator=g), torch.zeros(16), torch.zeros(16))
        before = [m.weight.detach().clone() for m in agent._hyper]
        agent.train(b)
        for m, w in zip(agent._hyper, before):
            assert not torch.equal(m.weight, w)  # the step moved it
            torch.testing.assert_close(m.weight.norm(dim=1), torch.ones(m.weight.shape[0]))
    assert len(agent._hyper) == 2 * 5  # embedding, the block's two, head and output of each critic


# --- (3) the LERP block --------------------------------------------------------------------------


def test_the_lerp_block_interpolates_toward_the_normalised_mlp_output_and_renormalises():
    block = LerpBlock(2, expansion=1)
    with torch.no_grad():
        block.w1.weight.copy_(torch.eye(2))
        block.s1.param.copy_(torch.ones(2) / block.s1.factor)
        block.w2.weight.copy_(torch.tensor([[0.0, 1.0], [1.0, 0.0]]))  # swaps the units
        block.alpha.param.copy_(torch.tensor([0.5, 0.25]) / block.alpha.factor)
    h = torch.tensor([[0.6, 0.8], [0.6, -0.8]])
    # row 1: m = [0.8, 0.6]; h + alpha (m - h) = [0.7, 0.75]; row 2: relu cuts -0.8, m = [0, 1];
    # h + alpha (m - h) = [0.3, -0.35]
    expected = torch.tensor([[0.7, 0.75], [0.3, -0.35]])
    expected = expected / expected.norm(dim=1, keepdim=True)
    torch.testing.assert_close(block(h), expected)


# --- (4) the reward scaler ---------------------------------------------------------------------


def test_the_reward_scaler_follows_the_running_discounted_return():
    s = ReturnScaler(gamma=0.5, g_max=5.0)
    assert float(s.scale()) == pytest.approx(1.0)  # before any return
    # G = 1, then 2 + 0.5 * 1 = 2.5 (the episode ends), then 4
    s.update(torch.tensor([1.0, 2.0, 4.0]), torch.tensor([0.0, 1.0, 0.0]), torch.zeros(3))
    assert float(s.mean) == pytest.approx(2.5) and float(s.var) == pytest.approx(1.5)
    assert float(s.abs_max) == 4.0 and float(s.carry) == pytest.approx(2.0) and float(s.count) == 3
    assert float(s.scale()) == pytest.approx(math.sqrt(1.5))
    # G = 1 + 0.5 * 4 = 3 (truncated: the episode ends too), then 1
    s.update(torch.tensor([1.0, 1.0]), torch.zeros(2), torch.tensor([1.0, 0.0]))
    values = np.array([1.0, 2.5, 4.0, 3.0, 1.0])
    assert float(s.mean) == pytest.approx(values.mean()) and float(s.var) == pytest.approx(values.var())
    assert float(s.carry) == pytest.approx(0.5) and float(s.count) == 5
    assert float(s.scale()) == pytest.approx(math.sqrt(values.var()))
    s.g_max = 1.0  # now max |G| / g_max = 4 is the larger
    assert float(s.scale()) == pytest.approx(4.0)
    torch.testing.assert_close(s(torch.tensor([2.0])), torch.tensor([0.5]))


def test_the_agent_feeds_the_scaler_the_batches_it_trained_on():
    agent = tiny_agent(gamma=0.5)
    b = (torch.zeros(3, 1), torch.zeros(3, 1), torch.tensor([1.0, 2.0, 4.0]), torch.zeros(3, 1),
         torch.tensor([0.0, 1.0, 0.0]), torch.zeros(3))
    agent.train(b)
    assert float(agent.reward_scaler.mean) == pytest.approx(2.5) and float(agent.reward_scaler.count) == 3


# --- (5) one real update on the lidar spaces ------------------------------------------------------


def test_one_update_on_lidar_batches_moves_the_critics_and_keeps_their_rows_on_the_sphere():
    agent = lidar_agent()
    assert type(agent.model.actor) is LidarActor
    before = {k: v.clone() for k, v in agent.model.state_dict().items()}
    target_before = {k: v.clone() for k, v in agent.model_target.state_dict().items()}
    metrics = agent.train(lidar_batch())
    assert all(np.isfinite(float(v)) for v in metrics.values()) and agent.skipped_updates == 0
    after = agent.model.state_dict()
    for k in before:
        if k.startswith("qs.") and not k.endswith(".factor"):
            assert not torch.equal(before[k], after[k]), k
    assert any(not torch.equal(target_before[k], v) for k, v in agent.model_target.state_dict().items())
    for m in agent._hyper:
        torch.testing.assert_close(m.weight.norm(dim=1), torch.ones(m.weight.shape[0]))
    assert float(agent.reward_scaler.count) == 32
    # the workers' policy: a LidarActor of the same sizes loads the trained actor's weights by name
    policy = LidarActor(LIDAR, ACT3, (16, 16))
    policy.load_state_dict(agent.get_actor().state_dict())


# --- (6) checkpoints ----------------------------------------------------------------------------


def _outputs(agent: SimbaV2Agent, b: tuple) -> list[torch.Tensor]:
    with torch.no_grad():
        obs, act = b[0], b[1]
        return [agent.critics(obs, act), agent.critics_target(obs, act), agent.actor(obs, test=True)[0],
                agent.reward_scaler.scale()]


def test_a_checkpoint_round_trip_gives_the_same_outputs_scaler_and_next_update():
    agent = lidar_agent(seed=0)
    for i in range(3):
        agent.train(lidar_batch(seed=i))
    buf = io.BytesIO()
    torch.save(agent.state_dict(), buf)
    buf.seek(0)
    fresh = lidar_agent(seed=7)
    fresh.load_state_dict(torch.load(buf, weights_only=False))
    b = lidar_batch(seed=9)
    for x, y in zip(_outputs(agent, b), _outputs(fresh, b)):
        assert torch.equal(x, y)
    for k, v in agent.reward_scaler.state_dict().items():
        assert torch.equal(v, fresh.reward_scaler.state_dict()[k]), k
    torch.manual_seed(4)
    agent.train(b)
    torch.manual_seed(4)
    fresh.train(b)
    for x, y in zip(agent._checked_tensors(), fresh._checked_tensors()):
        assert torch.equal(x, y)


def test_a_checkpoint_without_the_scaler_is_refused_in_one_line():
    agent = lidar_agent()
    state = agent.state_dict()
    del state["reward_scaler"]
    with pytest.raises(UserError) as info:
        lidar_agent().load_state_dict(state)
    assert "\n" not in str(info.value)


# --- the non-finite guard and the compiled update ------------------------------------------------


@pytest.mark.parametrize("device_side", [False, True], ids=["host", "device-side"])
def test_a_non_finite_update_changes_nothing_not_even_the_scaler(device_side: bool):
    agent = lidar_agent()
    agent.train(lidar_batch(seed=0))  # Adam's state exists from here: the device side can decide
    agent.guard.device_side = device_side
    before = [t.detach().clone() for t in agent._checked_tensors()]
    bad = list(lidar_batch(seed=1))
    bad[2] = bad[2].clone()
    bad[2][0] = float("nan")
    agent.train(tuple(bad))
    assert agent.skipped_updates == 1
    for x, y in zip(before, agent._checked_tensors()):
        assert torch.equal(x, y)


class AotEager:
    """``torch.compile`` with the ``aot_eager`` backend (as tests/test_compile.py: the graphs and
    their backward without code generation), counting the graphs captured."""

    def __init__(self) -> None:
        self.real = torch.compile
        self.graphs = 0

    def backend(self, gm: Any, example_inputs: Any) -> Any:
        self.graphs += 1
        return torch._dynamo.lookup_backend("aot_eager")(gm, example_inputs)

    def __call__(self, fn: Any, **kwargs: Any) -> Any:
        return self.real(fn, backend=self.backend)


def test_compiled_gives_the_eager_state_over_10_updates(monkeypatch):
    torch._dynamo.reset()
    batches = [lidar_batch(seed=i) for i in range(10)]
    eager = lidar_agent()
    torch.manual_seed(5)
    for b in batches:
        eager.train(b)
    compiler = AotEager()
    monkeypatch.setattr(torch, "compile", compiler)
    compiled = lidar_agent(compile="compile")
    torch.manual_seed(5)
    for b in batches:
        compiled.train(b)
    assert compiled._compile_state.mode == "compile" and compiled._compile_state.checked == {True}
    assert compiler.graphs >= 1
    for i, (x, y) in enumerate(zip(compiled._checked_tensors(), eager._checked_tensors())):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5, msg=lambda m, i=i: f"tensor {i}: {m}")
    torch._dynamo.reset()


# --- arguments ------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [{"n": 0}, {"n_atoms": 1}, {"v_max": 0.0}, {"critic_width": 0},
                                 {"critic_blocks": -1}, {"reward_g_max": 0.0}])
def test_bad_arguments_are_one_user_error_line(bad: dict):
    with pytest.raises(UserError) as info:
        tiny_agent(**bad)
    assert "\n" not in str(info.value)


def test_a_model_that_ignores_the_arguments_is_refused():
    with pytest.raises(UserError, match="built 2 of 101"):
        SimbaV2Agent(OBS, ACT, "cpu", model_cls=lambda o, a: SimbaV2ActorCritic(o, a, (8, 8)), n_atoms=5)
