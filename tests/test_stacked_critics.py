"""Critics kept as separate modules, evaluated as one batched product per layer
(``tmrl.models.StackedCritics``, ``stacked_mlp``): DroQ's dropout critics, TQC's quantile critics,
CrossQ's batch-renormalised critics, their lidar wrappers, DrQ's Q heads, tutorial-style
``MLPQFunction`` pairs.

The stacked evaluation must give the loop's values and gradients (DroQ: the same dropout masks
from the same generator state; CrossQ: the same running statistics), keep the modules' parameter
names (checkpoints), and is what a critic set uses off a CPU (on a CPU the loop, faster there).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gymnasium import spaces

from tmrl.algorithms import CrossQAgent, DroQAgent, TQCAgent
from tmrl.algorithms.critics import CriticSet
from tmrl.algorithms.crossq import CrossQActorCritic, CrossQQFunction
from tmrl.algorithms.droq import DropoutQFunction, DroQMLPActorCritic
from tmrl.algorithms.drq import DrQCritics
from tmrl.algorithms.tqc import QuantileQFunction, TQCActorCritic
from tmrl.driving.models import LidarCrossQActorCritic, LidarDroQActorCritic, LidarTQCActorCritic
from tmrl.models import MLPQFunction, StackedCritics, stacked_mlp
from tmrl.util import partial

OBS = spaces.Tuple((spaces.Box(-1.0, 1.0, (4,), np.float32), spaces.Box(0.0, 1.0, (2,), np.float32)))
ACT = spaces.Box(-1.0, 1.0, (2,), np.float32)
H = (16, 16)
B = 12


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def lidar_space() -> spaces.Tuple:
    # the shape the lidar interfaces have: speed, four lidar scans of 19, progress... (scaled per element)
    return spaces.Tuple((spaces.Box(0.0, 1000.0, (1,), np.float32), spaces.Box(0.0, np.inf, (4, 19), np.float32),
                         spaces.Box(-1.0, 1.0, (3,), np.float32), spaces.Box(-1.0, 1.0, (3,), np.float32)))


CRITICS = {
    "droq": lambda: [DropoutQFunction(OBS, ACT, H, dropout_rate=0.3) for _ in range(3)],
    "tqc": lambda: [QuantileQFunction(OBS, ACT, H, n_quantiles=5) for _ in range(4)],
    "crossq": lambda: [CrossQQFunction(OBS, ACT, H, renorm_warmup_steps=1) for _ in range(2)],
    "crossq-no-input-norm": lambda: [CrossQQFunction(OBS, ACT, H, input_norm=False) for _ in range(2)],
    "mlp-pair": lambda: [MLPQFunction(OBS, ACT, H) for _ in range(2)],
    "lidar-droq": lambda: list(LidarDroQActorCritic(lidar_space(), spaces.Box(-1, 1, (3,), np.float32), H).qs),
    "lidar-tqc": lambda: list(LidarTQCActorCritic(lidar_space(), spaces.Box(-1, 1, (3,), np.float32), H, n=3,
                                                  n_quantiles=4, critic_hidden_sizes=H).qs),
    "lidar-crossq": lambda: list(LidarCrossQActorCritic(lidar_space(), spaces.Box(-1, 1, (3,), np.float32), H,
                                                        critic_hidden_sizes=H).qs),
}


def inputs(name: str, gen: torch.Generator) -> tuple:
    if name.startswith("lidar"):
        obs = (torch.rand(B, 1, generator=gen) * 300, torch.rand(B, 4, 19, generator=gen) * 50,
               torch.rand(B, 3, generator=gen), torch.rand(B, 3, generator=gen))
        return obs, torch.rand(B, 3, generator=gen) * 2 - 1
    obs = (torch.randn(B, 4, generator=gen), torch.rand(B, 2, generator=gen))
    return obs, torch.rand(B, 2, generator=gen) * 2 - 1


def loop(critics: list[torch.nn.Module], obs: tuple, act: torch.Tensor) -> torch.Tensor:
    return torch.stack([q(obs, act) for q in critics])


@pytest.mark.parametrize("name", list(CRITICS))
@pytest.mark.parametrize("training", [True, False], ids=["train", "eval"])
def test_stacked_critics_give_the_loops_values_gradients_and_statistics(name: str, training: bool):
    torch.manual_seed(0)
    critics = CRITICS[name]()
    twins = [__import__("copy").deepcopy(q) for q in critics]
    for q in critics + twins:
        q.train(training)
    stacked = StackedCritics.of(critics)
    assert stacked is not None
    obs, act = inputs(name, torch.Generator().manual_seed(1))
    act.requires_grad_(True)
    act_twin = act.detach().clone().requires_grad_(True)
    for _ in range(2):  # twice: CrossQ's renormalisation starts after one training pass
        torch.manual_seed(7)  # the same dropout masks, drawn in the loop's order
        expected = loop(twins, obs, act_twin)
        torch.manual_seed(7)
        got = stacked(obs, act)
        assert got.shape == expected.shape
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)
    weights = torch.randn(expected.shape, generator=torch.Generator().manual_seed(2))
    (got * weights).sum().backward()
    (expected * weights).sum().backward()
    torch.testing.assert_close(act.grad, act_twin.grad, rtol=1e-5, atol=1e-6)
    for q, twin in zip(critics, twins):
        for (n, p), t in zip(q.named_parameters(), twin.parameters()):
            torch.testing.assert_close(p.grad, t.grad, rtol=1e-4, atol=1e-6, msg=n)
        for (n, buf), t in zip(q.named_buffers(), twin.buffers()):
            torch.testing.assert_close(buf, t, rtol=1e-5, atol=1e-6, msg=n)


def test_detached_stacked_critics_pass_gradients_to_the_input_only():
    torch.manual_seed(0)
    critics = CRITICS["droq"]()
    obs, act = inputs("droq", torch.Generator().manual_seed(1))
    act.requires_grad_(True)
    StackedCritics.of(critics)(obs, act, detach_params=True).sum().backward()  # type: ignore[misc]
    assert act.grad is not None and act.grad.abs().sum() > 0
    assert all(p.grad is None for q in critics for p in q.parameters())


def test_a_subset_of_members_is_those_critics():
    torch.manual_seed(0)
    critics = CRITICS["tqc"]()
    obs, act = inputs("tqc", torch.Generator().manual_seed(1))
    got = StackedCritics.of(critics)(obs, act, members=torch.tensor([3, 1]))  # type: ignore[misc]
    torch.testing.assert_close(got, loop([critics[3], critics[1]], obs, act), rtol=1e-5, atol=1e-6)


def test_critics_of_different_shapes_or_kinds_are_evaluated_one_by_one():
    assert StackedCritics.of([DropoutQFunction(OBS, ACT, H), DropoutQFunction(OBS, ACT, (16, 8))]) is None
    assert StackedCritics.of([DropoutQFunction(OBS, ACT, H), QuantileQFunction(OBS, ACT, H)]) is None
    assert StackedCritics.of([DropoutQFunction(OBS, ACT, H, dropout_rate=0.1),
                              DropoutQFunction(OBS, ACT, H, dropout_rate=0.2)]) is None
    assert StackedCritics.of([CrossQQFunction(OBS, ACT, H, bn_momentum=0.01),
                              CrossQQFunction(OBS, ACT, H, bn_momentum=0.1)]) is None
    with pytest.raises(ValueError, match="cannot be evaluated together"):
        stacked_mlp([torch.nn.Sequential(torch.nn.Linear(3, 2)), torch.nn.Sequential(torch.nn.Linear(3, 4))],
                    torch.zeros(1, 3))


def test_drq_heads_stacked_give_the_loops_values():
    torch.manual_seed(0)
    heads = DrQCritics(10, 2, (16, 16), 3)
    x, others, act = torch.randn(B, 8), torch.randn(B, 2), torch.rand(B, 2)
    assert heads.kinds is not None
    heads.stack = False
    expected = heads.values(x, others, act)
    heads.stack = True
    got = heads.values(x, others, act)
    assert got.shape == (3, B)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)


def test_a_critic_set_stacks_off_a_cpu_and_loops_on_it():
    model = DroQMLPActorCritic(OBS, ACT, H)
    assert CriticSet(model).stacked is None  # on the CPU: one by one (faster there)
    assert CriticSet(model, stack=True).stacked is not None
    assert CriticSet(model.to("meta")).stacked is not None  # any other device: together


SMALL_AGENTS = {
    "droq": lambda: DroQAgent(OBS, ACT, "cpu", model_cls=partial(DroQMLPActorCritic, hidden_sizes=H),
                              dropout_rate=0.2, q_updates_per_policy_update=1),
    "tqc": lambda: TQCAgent(OBS, ACT, "cpu", model_cls=partial(TQCActorCritic, hidden_sizes=H, critic_hidden_sizes=H),
                            n=3, n_quantiles=5),
    "crossq": lambda: CrossQAgent(OBS, ACT, "cpu", model_cls=partial(CrossQActorCritic, hidden_sizes=H),
                                  critic_width=16, policy_delay=1, renorm_warmup_steps=1),
}


@pytest.mark.parametrize("name", list(SMALL_AGENTS))
def test_an_agent_whose_critics_are_stacked_trains_as_with_the_loop(name: str):
    agents = []
    for stack in (False, True):
        torch.manual_seed(0)
        agent = SMALL_AGENTS[name]()
        agent.critics = CriticSet(agent.model, stack=stack)
        if getattr(agent, "critics_target", None) is not None:
            agent.critics_target = CriticSet(agent.model_target, stack=stack)
        assert (agent.critics.stacked is not None) == stack
        gen = torch.Generator().manual_seed(1)
        torch.manual_seed(5)
        for _ in range(3):
            obs = (torch.randn(B, 4, generator=gen), torch.rand(B, 2, generator=gen))
            nxt = (torch.randn(B, 4, generator=gen), torch.rand(B, 2, generator=gen))
            agent.train((obs, torch.rand(B, 2, generator=gen) * 2 - 1, torch.randn(B, generator=gen), nxt,
                         (torch.rand(B, generator=gen) < 0.2).float(), torch.zeros(B)))
        agents.append(agent)
    loop_agent, stacked_agent = agents
    assert list(stacked_agent.model.state_dict()) == list(loop_agent.model.state_dict())  # the same names
    for (n, a), b in zip(stacked_agent.model.state_dict().items(), loop_agent.model.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5, msg=n)
