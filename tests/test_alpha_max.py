"""ALG.ALPHA_MAX: a learned entropy coefficient that has fallen to its ceiling never rises above it
again, on every agent and on both of SAC's update paths (fused and autograd); it may start above
it; the rule survives a checkpoint; a ceiling of 0 is refused."""

from __future__ import annotations

import math

import pytest
import torch
from test_agents_crossq import crossq
from test_agents_droq_tqc import droq, tqc
from test_algorithms import (  # noqa: F401 (_one_thread: the autouse fixture, one torch thread)
    ACT2,
    OBS3,
    SMALL,
    _one_thread,
    random_batch,
)

from tmrl.algorithms import REDQSACAgent, SACAgent
from tmrl.config import loader
from tmrl.config.loader import ConfigError
from tmrl.errors import UserError
from tmrl.models import MLPActorCritic, REDQMLPActorCritic
from tmrl.util import partial

CAP = 0.05
# big Adam steps on log(alpha) (about 0.2 each), one policy update per critic update
LEARN = {"alpha": 0.2, "lr_entropy": 0.2, "learn_entropy_coef": True}


def _sac(fused: bool, **kw):
    return SACAgent(OBS3, ACT2, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=SMALL), fused=fused, **kw)


MAKERS = {
    "sac-fused": lambda **kw: _sac(True, **kw),
    "sac-autograd": lambda **kw: _sac(False, **kw),
    "redq": lambda **kw: REDQSACAgent(OBS3, ACT2, "cpu", model_cls=partial(REDQMLPActorCritic, hidden_sizes=SMALL),
                                      n=2, **kw),
    "droq": lambda **kw: droq(q_updates_per_policy_update=1, **kw),
    "tqc": lambda **kw: tqc(**kw),
    "crossq": lambda **kw: crossq(policy_delay=1, **kw),
}


def _alpha(agent) -> float:
    return math.exp(float(agent.log_alpha.detach()))


def _drive(agent, target_entropy: float, updates: int, gen: torch.Generator) -> list[float]:
    """``updates`` updates with the entropy target moved far off (alpha falls for a very low target,
    rises for a very high one); the coefficient after each."""
    agent.target_entropy = target_entropy
    out = []
    for _ in range(updates):
        agent.train(random_batch(gen))
        out.append(_alpha(agent))
    return out


@pytest.mark.parametrize("name", list(MAKERS))
def test_a_learned_coefficient_that_fell_to_the_ceiling_never_rises_above_it(name):
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(1)
    agent = MAKERS[name](alpha_max=CAP, **LEARN)
    if name == "sac-fused":
        assert agent.fused_update is not None
    if name == "sac-autograd":
        assert agent.fused_update is None
    falling = _drive(agent, -100.0, 10, gen)
    assert CAP < falling[0] < 0.2  # above the ceiling at first: it only binds once reached
    assert falling[-1] < CAP
    rising = _drive(agent, 100.0, 40, gen)
    assert max(rising) <= CAP * (1 + 1e-5) and rising[-1] == pytest.approx(CAP, rel=1e-5)

    # without the ceiling the same updates lift it well above (the test can fail)
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(1)
    free = MAKERS[name](**LEARN)
    _drive(free, -100.0, 10, gen)
    assert max(_drive(free, 100.0, 40, gen)) > 2 * CAP


def test_the_ceiling_holds_after_a_checkpoint_round_trip():
    gen = torch.Generator().manual_seed(2)
    agent = _sac(True, alpha_max=CAP, **LEARN)
    _drive(agent, -100.0, 10, gen)
    resumed = _sac(True, alpha_max=CAP, **LEARN)
    resumed.load_state_dict(agent.state_dict())
    assert _alpha(resumed) < CAP
    assert max(_drive(resumed, 100.0, 30, gen)) <= CAP * (1 + 1e-5)


def test_a_fixed_coefficient_ignores_the_ceiling_and_a_ceiling_of_zero_is_refused(tmp_path):
    fixed = _sac(True, alpha=0.3, learn_entropy_coef=False, alpha_max=CAP)
    metrics = fixed.train(random_batch(torch.Generator().manual_seed(3)))
    assert float(metrics["entropy_coef"]) == pytest.approx(0.3)
    with pytest.raises(UserError, match=r"alpha_max=0\.0 must be > 0.*ALG\.ALPHA_MAX"):
        _sac(True, alpha_max=0.0)
    cfg = loader.validate({"ALG": {"ALPHA_MAX": 0.01}})
    assert cfg["ALG"]["ALPHA_MAX"] == 0.01
    assert loader.validate({})["ALG"]["ALPHA_MAX"] is None  # a config without the key: no ceiling
    with pytest.raises(ConfigError, match="ALPHA_MAX"):
        loader.validate({"ALG": {"ALPHA_MAX": 0}})
