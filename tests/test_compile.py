"""ALG.COMPILE: every agent's update through torch.compile ("compile") or CUDA graphs ("cudagraph").

The compiled update must give the eager update's parameters within float tolerance, its first
update of each kind (with and without a policy update) checks this and falls back to eager on a
mismatch or a failure (leaving the state as if eager had run from the start), and an update that
cannot be compiled (SAC's sequential order, a subclass with a ``train`` of its own) warns once
and runs eager.

On the CPU, SAC's check runs one real compilation (inductor, about 40 s on a 2-core machine when
the compiler's cache is cold); the other agents' CPU checks run TorchDynamo and AOTAutograd with
the ``aot_eager`` backend (the graphs, their backward, the buffer updates and the random draws
they capture, without inductor's code generation, which would take 20 to 35 s per agent), and
assert that graphs were captured. The ``cuda`` twins (50 updates, inductor, both modes) carry the
``gpu`` marker (skipped where PyTorch sees no GPU, allowed to skip in CI by tests/ci_skips.py) and
run with ``pytest -m gpu tests/test_compile.py``.
"""

from __future__ import annotations

import copy
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces

from tmrl.algorithms import BROAgent, CrossQAgent, DroQAgent, DrQAgent, REDQSACAgent, SACAgent, TQCAgent
from tmrl.algorithms.bro import BROActorCritic
from tmrl.algorithms.simbav2 import SimbaV2Agent, SimbaV2ActorCritic
from tmrl.algorithms.crossq import CrossQActorCritic
from tmrl.algorithms.droq import DroQMLPActorCritic
from tmrl.algorithms.drq import DrQActorCritic
from tmrl.algorithms.tqc import TQCActorCritic
from tmrl.config import loader, schema
from tmrl.errors import UserError
from tmrl.models import MLPActorCritic, REDQMLPActorCritic
from tmrl.util import partial

OBS = spaces.Box(-1.0, 1.0, (3,), np.float32)  # Pendulum-sized
ACT = spaces.Box(-1.0, 1.0, (1,), np.float32)
HIDDEN = (32, 32)
BATCH = 32
UPDATES = 50
RTOL, ATOL = 1e-4, 1e-5
SAC_LOG = "tmrl.algorithms.sac"
gpu = pytest.mark.gpu


@pytest.fixture(autouse=True)
def _exact_float32():
    # full float32 products on a GPU (no TF32), one CPU thread (a shared machine); a fresh
    # TorchDynamo cache (each test's agents compile their own methods)
    precision, threads = torch.get_float32_matmul_precision(), torch.get_num_threads()
    torch.set_float32_matmul_precision("highest")
    torch.set_num_threads(1)
    torch._dynamo.reset()
    yield
    torch.set_float32_matmul_precision(precision)
    torch.set_num_threads(threads)


def make_sac(compile: str = "off", device: str = "cpu", **kwargs: Any) -> SACAgent:
    torch.manual_seed(0)
    kwargs.setdefault("learn_entropy_coef", True)
    return SACAgent(OBS, ACT, device, model_cls=partial(MLPActorCritic, hidden_sizes=HIDDEN), compile=compile,
                    **kwargs)


def batches(n: int, device: str = "cpu") -> list[tuple[torch.Tensor, ...]]:
    g = torch.Generator().manual_seed(1)
    out = []
    for _ in range(n):
        b = (torch.randn(BATCH, 3, generator=g), torch.rand(BATCH, 1, generator=g) * 2 - 1,
             torch.randn(BATCH, generator=g), torch.randn(BATCH, 3, generator=g),
             (torch.rand(BATCH, generator=g) < 0.1).float(), torch.zeros(BATCH))
        out.append(tuple(t.to(device) for t in b))
    return out


def run(agent: SACAgent, n: int = UPDATES, device: str = "cpu") -> list[dict[str, Any]]:
    torch.manual_seed(5)  # the actions sampled in the updates
    return [agent.train(b) for b in agent_batches(agent, n, device)]


def state(agent: SACAgent) -> list[torch.Tensor]:
    """Parameters, target parameters, the model's running statistics and log(alpha), on the CPU."""
    return [t.detach().cpu().clone() for t in agent._checked_tensors()]


def assert_close(got: list[torch.Tensor], expected: list[torch.Tensor]) -> None:
    assert len(got) == len(expected)
    for i, (g, e) in enumerate(zip(got, expected)):
        torch.testing.assert_close(g, e, rtol=RTOL, atol=ATOL, msg=lambda m, i=i: f"tensor {i}: {m}")


def assert_equal(got: list[torch.Tensor], expected: list[torch.Tensor]) -> None:
    assert len(got) == len(expected)
    assert all(torch.equal(g, e) for g, e in zip(got, expected))


def warnings_of(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


# --- the other agents, small ----------------------------------------------------------------------

DRQ_SIZES = {"channels": (4, 4), "kernels": (3, 3), "strides": (2, 1), "feature_dim": 8, "hidden_sizes": (16,)}
DRQ_ACT = spaces.Box(-1.0, 1.0, (3,), np.float32)
DRQ_OBS = spaces.Tuple([spaces.Box(0, 1, (1,))] * 3 + [spaces.Box(0, 255, (2, 16, 16), np.uint8), DRQ_ACT, DRQ_ACT])


def with_sgd(agent: SACAgent, lr: float = 0.01) -> SACAgent:
    """Plain SGD everywhere (CrossQ: see :func:`make_agent`)."""
    agent.pi_optimizer = torch.optim.SGD(agent.actor.parameters(), lr=lr)
    agent.q_optimizer = torch.optim.SGD(agent.critics.parameters(), lr=lr)
    if agent.log_alpha is not None:
        agent.alpha_optimizer = torch.optim.SGD([agent.log_alpha], lr=lr)
    return agent


AGENTS: dict[str, Callable[..., SACAgent]] = {
    # the policy every second update, so that both kinds of update are compiled and checked
    "REDQSAC": lambda compile, device: REDQSACAgent(
        OBS, ACT, device, model_cls=partial(REDQMLPActorCritic, hidden_sizes=HIDDEN), n=3, m=2,
        q_updates_per_policy_update=2, compile=compile),
    "DROQ": lambda compile, device: DroQAgent(
        OBS, ACT, device, model_cls=partial(DroQMLPActorCritic, hidden_sizes=HIDDEN), dropout_rate=0.1,
        q_updates_per_policy_update=2, compile=compile),
    "TQC": lambda compile, device: TQCAgent(
        OBS, ACT, device, model_cls=partial(TQCActorCritic, hidden_sizes=HIDDEN, critic_hidden_sizes=HIDDEN), n=3,
        n_quantiles=5, drop_per_critic=1, compile=compile),
    "BRO": lambda compile, device: BROAgent(
        OBS, ACT, device, model_cls=partial(BROActorCritic, hidden_sizes=HIDDEN), n=2, n_quantiles=5,
        critic_width=HIDDEN[0], critic_blocks=1, compile=compile),
    "SIMBAV2": lambda compile, device: SimbaV2Agent(
        OBS, ACT, device, model_cls=partial(SimbaV2ActorCritic, hidden_sizes=HIDDEN), n=2, n_atoms=11,
        critic_width=HIDDEN[0], critic_blocks=1, compile=compile),
    # SGD: the biases under CrossQ's batch normalisation have gradients that are zero up to
    # rounding, which Adam turns into steps of +-lr whose sign is the rounding's (a compiled
    # update rounds differently); SGD keeps such a difference as small as the rounding
    "CROSSQ": lambda compile, device: with_sgd(CrossQAgent(
        OBS, ACT, device, model_cls=partial(CrossQActorCritic, hidden_sizes=HIDDEN), critic_width=32, policy_delay=2,
        renorm_warmup_steps=3, compile=compile)),
    "DRQ": lambda compile, device: DrQAgent(
        DRQ_OBS, DRQ_ACT, device, model_cls=partial(DrQActorCritic, **DRQ_SIZES), image_pad=2, compile=compile),
}


def make_agent(name: str, compile: str = "off", device: str = "cpu") -> SACAgent:
    torch.manual_seed(0)
    return AGENTS[name](compile, device)


def drq_batches(n: int, device: str = "cpu") -> list[tuple]:
    g = torch.Generator().manual_seed(1)

    def obs() -> tuple:
        scalars = tuple(torch.rand(BATCH, 1, generator=g) for _ in range(3))
        frames = torch.randint(0, 256, (BATCH, 2, 16, 16), generator=g, dtype=torch.uint8)
        return (*scalars, frames, torch.rand(BATCH, 3, generator=g) * 2 - 1, torch.rand(BATCH, 3, generator=g) * 2 - 1)

    out = []
    for _ in range(n):
        b = (obs(), torch.rand(BATCH, 3, generator=g) * 2 - 1, torch.randn(BATCH, generator=g), obs(),
             (torch.rand(BATCH, generator=g) < 0.1).float(), torch.zeros(BATCH))
        out.append(tuple(tuple(t.to(device) for t in x) if isinstance(x, tuple) else x.to(device) for x in b))
    return out


def agent_batches(agent: SACAgent, n: int, device: str = "cpu") -> list[tuple]:
    return drq_batches(n, device) if isinstance(agent, DrQAgent) else batches(n, device)


class AotEager:
    """``torch.compile`` with the ``aot_eager`` backend (TorchDynamo and AOTAutograd, no code
    generation); counts the compiled functions and the graphs captured."""

    def __init__(self) -> None:
        self.real = torch.compile
        self.functions = 0
        self.graphs = 0

    def backend(self, gm: Any, example_inputs: Any) -> Any:
        self.graphs += 1
        return torch._dynamo.lookup_backend("aot_eager")(gm, example_inputs)

    def __call__(self, fn: Any, **kwargs: Any) -> Any:
        self.functions += 1
        return self.real(fn, backend=self.backend)


@pytest.fixture
def aot_eager(monkeypatch: pytest.MonkeyPatch) -> AotEager:
    compiler = AotEager()
    monkeypatch.setattr(torch, "compile", compiler)
    return compiler


# --- the key --------------------------------------------------------------------------------------


def test_the_key_defaults_to_off_and_feeds_the_agents():
    cfg = schema.defaults()
    assert cfg["ALG"]["COMPILE"] == "off"
    assert schema.COMPILE_MODES == ("off", "compile", "cudagraph")
    cfg["ALG"]["COMPILE"] = "compile"
    for cls in ("SACAgent", "REDQSACAgent", "DroQAgent", "TQCAgent", "CrossQAgent", "DrQAgent", "BROAgent",
                "SimbaV2Agent"):
        assert schema.arguments(cfg, cls)["compile"] == "compile"


@pytest.mark.parametrize("mode", ["off", "compile", "cudagraph"])
def test_each_value_loads(tmp_path: Path, mode: str):
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"ALG": {"COMPILE": mode}}), encoding="utf-8")
    assert loader.load_config(path)["ALG"]["COMPILE"] == mode


def test_a_wrong_value_is_one_line(tmp_path: Path):
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"ALG": {"COMPILE": "fast"}}), encoding="utf-8")
    with pytest.raises(loader.ConfigError) as info:
        loader.load_config(path)
    message = str(info.value)
    assert "\n" not in message
    assert 'ALG.COMPILE must be one of "off", "compile", "cudagraph", got "fast"' in message


def test_a_wrong_value_given_to_the_agent_is_one_user_error_line():
    with pytest.raises(UserError) as info:
        make_sac("fast")
    assert "\n" not in str(info.value) and "ALG.COMPILE='fast'" in str(info.value)


def test_cudagraph_on_the_cpu_is_one_user_error_line():
    with pytest.raises(UserError) as info:
        make_sac("cudagraph", device="cpu")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("ALG.COMPILE='cudagraph': cudagraph needs a CUDA device")
    assert "the training device is cpu" in message


def test_drq_takes_the_key_at_assembly(caplog):
    from tmrl.assembly import assemble

    cfg = schema.defaults()
    cfg["ALG"]["ALGORITHM"], cfg["ENV"]["RTGYM_INTERFACE"], cfg["ALG"]["COMPILE"] = "DRQ", "SIMFULL", "compile"
    with caplog.at_level(logging.WARNING):
        objects = assemble(cfg)
    assert not [line for line in warnings_of(caplog) if "COMPILE" in line]
    assert objects.TRAINER.keywords["training_agent_cls"].keywords["compile"] == "compile"


# --- updates that cannot be compiled ----------------------------------------------------------------


def _no_compile(*args: Any, **kwargs: Any) -> Any:
    raise AssertionError("torch.compile called for an agent that runs eager")


class OwnTrain(SACAgent):
    """A user's agent with its own ``train`` (which ALG.COMPILE cannot know)."""

    def train(self, batch: tuple) -> dict[str, Any]:
        return super().train(batch) if self._compile_state.mode != "off" else self._update_off(batch, True)


UNCOMPILABLE = [
    pytest.param(lambda: make_sac("compile", update_order="sequential"), "update_order='sequential'",
                 id="SAC-sequential"),
    pytest.param(lambda: OwnTrain(OBS, ACT, "cpu", model_cls=partial(MLPActorCritic, hidden_sizes=HIDDEN),
                                  compile="compile"), "OwnTrain overrides train", id="own-train"),
]


@pytest.mark.parametrize(("build", "why"), UNCOMPILABLE)
def test_an_update_that_cannot_be_compiled_warns_once_and_runs_eager(build, why, caplog, monkeypatch):
    monkeypatch.setattr(torch, "compile", _no_compile)
    with caplog.at_level(logging.WARNING):
        agent = build()
        for b in batches(2):
            metrics = agent.train(b)
    lines = warnings_of(caplog)
    assert len(lines) == 1, lines
    assert lines[0].startswith("ALG.COMPILE='compile': ") and why in lines[0] and "runs eager" in lines[0]
    assert agent._compile_state.mode == "off"
    assert np.isfinite(float(metrics["loss_critic"]))


# --- SAC on the CPU ---------------------------------------------------------------------------------


def test_compile_gives_the_eager_parameters_over_50_updates():
    """One real compilation (the slow test of this file, about 40 s on a 2-core machine)."""
    eager = make_sac("off", fused=False)
    run(eager)
    compiled = make_sac("compile")
    metrics = run(compiled)
    st = compiled._compile_state
    assert st.mode == "compile" and st.checked == {True}, "the compiled update fell back to eager"
    assert_close(state(compiled), state(eager))
    # metrics stay tensors (read once per round by the trainer), one per update
    assert all(isinstance(v, torch.Tensor) for v in metrics[-1].values())
    assert set(metrics[-1]) == set(run(make_sac("off", fused=False), n=1)[0])


@pytest.mark.parametrize("learn_entropy_coef", [True, False], ids=["learned-alpha", "fixed-alpha"])
def test_the_first_update_check_leaves_the_state_of_the_chosen_mode(monkeypatch, learn_entropy_coef: bool):
    """With a "compiled" function that is the eager one, the check passes and the run is the
    eager autograd update's exactly: the check's extra eager update leaves no trace (parameters,
    optimizer moments, random generator, guard count)."""
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)
    eager = make_sac("off", fused=False, learn_entropy_coef=learn_entropy_coef)
    run(eager, n=5)
    eager_rng = torch.get_rng_state()
    checked = make_sac("compile", learn_entropy_coef=learn_entropy_coef)
    run(checked, n=5)
    assert checked._compile_state.checked == {True} and checked._compile_state.mode == "compile"
    assert torch.equal(torch.get_rng_state(), eager_rng)
    assert checked.guard.skipped == eager.guard.skipped == 0
    assert_equal(state(checked), state(eager))
    for opt, ref in ((checked.q_optimizer, eager.q_optimizer), (checked.pi_optimizer, eager.pi_optimizer)):
        for a, b in zip(opt.state.values(), ref.state.values()):
            assert torch.equal(a["exp_avg"], b["exp_avg"]) and torch.equal(a["exp_avg_sq"], b["exp_avg_sq"])


def _raising(fn: Any, **kwargs: Any) -> Any:
    def broken(*args: Any, **kw: Any) -> Any:
        raise RuntimeError("planted compile failure")

    return broken


def _scaled_loss(out: tuple, factor: float, value_too: bool = True) -> tuple:
    """``out`` with its first tensor that carries a gradient (the first loss) scaled: its value
    and gradient, or (``value_too`` false) its gradient only."""
    out = list(out)
    i = next(i for i, v in enumerate(out) if isinstance(v, torch.Tensor) and v.requires_grad)
    loss = out[i]
    out[i] = factor * loss if value_too else loss.detach() + factor * (loss - loss.detach())
    return tuple(out)


def _wrong(fn: Any, **kwargs: Any) -> Any:
    def wrong(*args: Any) -> Any:
        return _scaled_loss(fn(*args), 2.0)

    return wrong


def _wrong_gradient(fn: Any, **kwargs: Any) -> Any:
    """The right losses, with a wrong gradient: only the gradients can tell."""
    def wrong(*args: Any) -> Any:
        return _scaled_loss(fn(*args), 2.0, value_too=False)

    return wrong


@pytest.mark.parametrize(("planted", "why"), [(_raising, "failed (RuntimeError: planted compile failure)"),
                                              (_wrong, "differs from the eager update")])
def test_a_failing_or_wrong_compiled_update_warns_once_and_trains_eagerly(planted, why, caplog, monkeypatch):
    monkeypatch.setattr(torch, "compile", planted)
    with caplog.at_level(logging.WARNING, logger=SAC_LOG):
        agent = make_sac("compile")
        run(agent, n=10)
    lines = warnings_of(caplog)
    assert len(lines) == 1, lines
    assert lines[0].startswith("ALG.COMPILE='compile': the compiled update ") and why in lines[0]
    assert lines[0].endswith("falls back to eager")
    assert agent._compile_state.mode == "off"
    eager = make_sac("off")  # the fallback is "off" exactly, the fused update included
    run(eager, n=10)
    assert_equal(state(agent), state(eager))


def test_a_copy_compiles_and_checks_its_own_update(monkeypatch):
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)
    agent = make_sac("compile")
    run(agent, n=1)
    twin = copy.deepcopy(agent)
    assert twin._compile_state.mode == "compile" and twin._compile_state.fns is None
    assert not twin._compile_state.checked
    twin.train(batches(1)[0])
    assert twin._compile_state.fns["_update_losses"].__self__ is twin  # type: ignore[index]


# --- every other agent on the CPU -------------------------------------------------------------------

OTHERS = list(AGENTS)


@pytest.mark.parametrize("name", OTHERS)
def test_each_agent_compiled_gives_the_eager_parameters_over_10_updates(name: str, aot_eager: AotEager):
    eager = make_agent(name, "off")
    eager_metrics = run(eager, n=10)
    compiled = make_agent(name, "compile")
    metrics = run(compiled, n=10)
    st = compiled._compile_state
    assert st.mode == "compile", "the compiled update fell back to eager"
    # both kinds of update compiled and checked where an agent has both (DrQ and TQC update their
    # policy at every update, and BRO and SimbaV2 as TQC)
    assert st.checked == ({True} if name in ("DRQ", "TQC", "BRO", "SIMBAV2") else {False, True})
    assert aot_eager.functions == len(compiled.COMPILED) and aot_eager.graphs >= len(compiled.COMPILED)
    assert_close(state(compiled), state(eager))
    assert compiled.guard.skipped == eager.guard.skipped == 0
    assert list(metrics[-1]) == list(eager_metrics[-1])  # the same metrics, in the same order
    for key, value in metrics[-1].items():
        torch.testing.assert_close(value, eager_metrics[-1][key], rtol=RTOL, atol=ATOL, msg=key)


@pytest.mark.parametrize("name", OTHERS)
@pytest.mark.parametrize(("planted", "why"), [(_raising, "failed (RuntimeError: planted compile failure)"),
                                              (_wrong, "differs from the eager update"),
                                              (_wrong_gradient, "differs from the eager update (gradient of ")],
                         ids=["raises", "wrong", "wrong-gradient"])
def test_each_agent_falls_back_to_eager_with_one_warning_and_the_state_of_eager(name, planted, why, caplog,
                                                                                monkeypatch):
    monkeypatch.setattr(torch, "compile", planted)
    with caplog.at_level(logging.WARNING, logger=SAC_LOG):
        agent = make_agent(name, "compile")
        run(agent, n=6)
    lines = warnings_of(caplog)
    assert len(lines) == 1, lines
    assert lines[0].startswith("ALG.COMPILE='compile': the compiled update ") and why in lines[0]
    assert agent._compile_state.mode == "off" and agent._compile_state.fns is None
    eager = make_agent(name, "off")
    run(eager, n=6)
    assert_equal(state(agent), state(eager))
    assert agent.state_dict().get("i_update") == eager.state_dict().get("i_update")


def test_the_first_policy_update_is_checked_too(caplog, monkeypatch):
    """REDQ updates its policy every second update: the function is wrong only when it updates the
    policy, which the first update (no policy update) cannot see; the second update's check does."""
    def wrong_with_the_policy(fn: Any, **kwargs: Any) -> Any:
        def wrong(b: Any, update_policy: bool) -> Any:
            out = fn(b, update_policy)
            return _scaled_loss(out, 2.0) if update_policy else out

        return wrong

    monkeypatch.setattr(torch, "compile", wrong_with_the_policy)
    with caplog.at_level(logging.WARNING, logger=SAC_LOG):
        agent = make_agent("REDQSAC", "compile")
        b = batches(4)
        torch.manual_seed(5)
        agent.train(b[0])
        assert agent._compile_state.checked == {False} and agent._compile_state.mode == "compile"
        assert not warnings_of(caplog)
        for x in b[1:]:
            agent.train(x)
    assert len(warnings_of(caplog)) == 1 and agent._compile_state.mode == "off"
    eager = make_agent("REDQSAC", "off")
    torch.manual_seed(5)
    for x in batches(4):
        eager.train(x)
    assert_equal(state(agent), state(eager))


# --- the GPU twins ----------------------------------------------------------------------------------


@pytest.mark.gpu
@pytest.mark.parametrize("mode", ["compile", "cudagraph"])
def test_cuda_compiled_update_gives_the_eager_parameters_over_50_updates(mode: str):
    eager = make_sac("off", device="cuda", fused=False)
    eager_metrics = run(eager, device="cuda")
    compiled = make_sac(mode, device="cuda")
    metrics = run(compiled, device="cuda")
    st = compiled._compile_state
    assert st.mode == mode and st.checked, "the compiled update fell back to eager"
    assert_close(state(compiled), state(eager))
    # the metrics of the first update survive the later replays (cloned out of the graph's memory)
    for key in ("loss_critic", "loss_actor", "entropy_coef"):
        torch.testing.assert_close(metrics[0][key], eager_metrics[0][key], rtol=RTOL, atol=ATOL)
    assert all(v.device.type == "cuda" for v in metrics[-1].values())


@pytest.mark.gpu
@pytest.mark.parametrize("mode", ["compile", "cudagraph"])
@pytest.mark.parametrize("name", OTHERS)
def test_cuda_each_agent_compiled_gives_the_eager_parameters_over_50_updates(name: str, mode: str):
    eager = make_agent(name, "off", device="cuda")
    eager_metrics = run(eager, device="cuda")
    compiled = make_agent(name, mode, device="cuda")
    metrics = run(compiled, device="cuda")
    st = compiled._compile_state
    assert st.mode == mode, "the compiled update fell back to eager"
    assert st.checked == ({True} if name in ("DRQ", "TQC", "BRO", "SIMBAV2") else {False, True})
    assert_close(state(compiled), state(eager))
    assert compiled.guard.skipped == eager.guard.skipped == 0
    for key in ("loss_critic", "entropy_coef", "debug_q"):
        torch.testing.assert_close(metrics[0][key], eager_metrics[0][key], rtol=RTOL, atol=ATOL, msg=key)
