"""ALG.COMPILE: SAC's update through torch.compile ("compile") or CUDA graphs ("cudagraph").

The compiled update must give the eager update's parameters within float tolerance, its first
update checks this and falls back to eager on a mismatch or a failure (leaving the state as if
eager had run from the start), and agents whose update cannot be compiled warn once and run
eager. The CPU checks run everywhere (one real compilation, about 40 s on a 2-core machine); the
``cuda`` twins carry the ``gpu`` marker (skipped where PyTorch sees no GPU, allowed to skip in CI
by tests/ci_skips.py) and run with ``pytest -m gpu tests/test_compile.py``.
"""

from __future__ import annotations

import copy
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium import spaces

from tmrl.algorithms import CrossQAgent, DroQAgent, REDQSACAgent, SACAgent, TQCAgent
from tmrl.config import loader, schema
from tmrl.errors import UserError
from tmrl.models import MLPActorCritic
from tmrl.util import partial

OBS = spaces.Box(-1.0, 1.0, (3,), np.float32)  # Pendulum-sized
ACT = spaces.Box(-1.0, 1.0, (1,), np.float32)
HIDDEN = (32, 32)
BATCH = 32
UPDATES = 50
RTOL, ATOL = 1e-4, 1e-5
SAC_LOG = "tmrl.algorithms.sac"


@pytest.fixture(autouse=True)
def _exact_float32():
    # full float32 products on a GPU (no TF32), one CPU thread (a shared machine)
    precision, threads = torch.get_float32_matmul_precision(), torch.get_num_threads()
    torch.set_float32_matmul_precision("highest")
    torch.set_num_threads(1)
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
    return [agent.train(b) for b in batches(n, device)]


def state(agent: SACAgent) -> list[torch.Tensor]:
    """Parameters, target parameters and log(alpha), on the CPU."""
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


# --- the key --------------------------------------------------------------------------------------


def test_the_key_defaults_to_off_and_feeds_the_agents():
    cfg = schema.defaults()
    assert cfg["ALG"]["COMPILE"] == "off"
    assert schema.COMPILE_MODES == ("off", "compile", "cudagraph")
    cfg["ALG"]["COMPILE"] = "compile"
    for cls in ("SACAgent", "REDQSACAgent", "DroQAgent", "TQCAgent", "CrossQAgent"):
        assert schema.arguments(cfg, cls)["compile"] == "compile"
    assert "compile" not in schema.arguments(cfg, "DrQAgent")  # DrQ's update cannot be compiled yet


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


# --- agents that cannot compile their update yet ---------------------------------------------------


def _no_compile(*args: Any, **kwargs: Any) -> Any:
    raise AssertionError("torch.compile called for an agent that runs eager")


SUBCLASSES = [
    pytest.param(lambda: REDQSACAgent(OBS, ACT, "cpu", n=3, m=2, compile="compile"), id="REDQSAC"),
    pytest.param(lambda: DroQAgent(OBS, ACT, "cpu", q_updates_per_policy_update=1, compile="compile"), id="DROQ"),
    pytest.param(lambda: TQCAgent(OBS, ACT, "cpu", n=2, n_quantiles=5, compile="compile"), id="TQC"),
    pytest.param(lambda: CrossQAgent(OBS, ACT, "cpu", critic_width=32, compile="compile"), id="CROSSQ"),
    pytest.param(lambda: make_sac("compile", update_order="sequential"), id="SAC-sequential"),
]


@pytest.mark.parametrize("build", SUBCLASSES)
def test_an_update_that_cannot_be_compiled_warns_once_and_runs_eager(build, caplog, monkeypatch):
    monkeypatch.setattr(torch, "compile", _no_compile)
    with caplog.at_level(logging.WARNING):
        agent = build()
        for b in batches(2):
            metrics = agent.train(b)
    lines = warnings_of(caplog)
    assert len(lines) == 1, lines
    assert lines[0].startswith("ALG.COMPILE='compile': ") and "runs eager" in lines[0]
    assert agent._compile_state.mode == "off"
    assert np.isfinite(float(metrics["loss_critic"]))


def test_drq_which_takes_no_compile_argument_warns_once_at_assembly(caplog):
    from tmrl.assembly import assemble

    cfg = schema.defaults()
    cfg["ALG"]["ALGORITHM"], cfg["ENV"]["RTGYM_INTERFACE"], cfg["ALG"]["COMPILE"] = "DRQ", "SIMFULL", "compile"
    with caplog.at_level(logging.WARNING, logger="tmrl.assembly"):
        objects = assemble(cfg)
    lines = warnings_of(caplog)
    assert lines == ["ALG.COMPILE='compile': DrQAgent cannot compile its update yet; the update runs eager"]
    assert "compile" not in objects.TRAINER.keywords["training_agent_cls"].keywords


# --- SAC on the CPU ---------------------------------------------------------------------------------


def test_compile_gives_the_eager_parameters_over_50_updates():
    """One real compilation (the slow test of this file, about 40 s on a 2-core machine)."""
    eager = make_sac("off", fused=False)
    run(eager)
    compiled = make_sac("compile")
    metrics = run(compiled)
    st = compiled._compile_state
    assert st.mode == "compile" and st.checked, "the compiled update fell back to eager"
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
    assert checked._compile_state.checked and checked._compile_state.mode == "compile"
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


def _wrong(fn: Any, **kwargs: Any) -> Any:
    def wrong(b: Any) -> Any:
        alpha, loss_critic, loss_actor, loss_alpha, stats = fn(b)
        return alpha, 2.0 * loss_critic, loss_actor, loss_alpha, stats

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
    assert twin._compile_state.mode == "compile" and twin._compile_state.fn is None
    assert not twin._compile_state.checked
    twin.train(batches(1)[0])
    assert twin._compile_state.fn.__self__ is twin  # type: ignore[union-attr]


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
