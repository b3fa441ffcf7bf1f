"""The learning benchmark in environment steps (bench/track_learning.py): the figures it derives
from a run's episodes, and one short real run of its loop on the simulator."""

from __future__ import annotations

import functools
import json
import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench import track_learning as tl

RUN = {
    # (end step, return, lap time or None)
    "episodes": [(1200, 5.0, None), (2600, 80.0, 41.0), (3500, 90.0, 38.5), (5200, 95.0, 33.0)],
    "tests": [(2000, 30.0, None), (3000, 100.0, 36.0), (4000, 60.0, None)],
}


def test_laps_come_from_training_and_test_episodes_in_step_order():
    assert tl.laps(RUN) == [(2600, 41.0), (3000, 36.0), (3500, 38.5), (5200, 33.0)]
    assert tl.first_step(RUN) == 2600
    assert tl.first_step(RUN, within=36.5) == 3000  # the first lap no slower than 36.5 s
    assert tl.first_step(RUN, within=30.0) is None
    assert tl.best_lap(RUN) == 33.0
    assert tl.best_lap({"episodes": [(10, 0.0, None)], "tests": []}) is None


def test_steps_to_a_return_read_the_test_episodes():
    assert tl.steps_to_return(RUN, 50.0) == 3000
    assert tl.steps_to_return(RUN, 200.0) is None


@pytest.mark.parametrize(
    ("values", "median"),
    [
        ([3, 1, 2], 2),
        ([4, 1, 2, 3], 2.5),
        ([None, 1, 2], 2),  # a seed that never got there counts as the slowest
        ([None, None, 1], None),  # most seeds never got there: no median
        ([None, 1, 2, 3], 2.5),
        ([None, 1, 2, None], None),
    ],
)
def test_median_counts_a_run_that_never_got_there_as_the_slowest(values, median):
    assert tl.median_or_none(values) == median


def test_every_variant_has_a_lidar_model_and_an_agent():
    from tmrl.algorithms import agent_class

    assert set(tl.DEFAULT_AGENTS) <= set(tl.VARIANTS)
    for label, (alg, source, utd) in tl.VARIANTS.items():
        assert source in ("tmrl", "demo", "class") and utd >= 1, label
        agent_class(alg)
        assert tl._lidar_model(alg) is not None


def test_a_short_run_drives_the_simulator_and_trains(capsys):
    res = tl.run(env_name="oval", label="SAC", seed=0, steps=300, utd=1, start_steps=100, eval_every=300,
                 batch_size=32, append_every=10)
    assert res["updates"] == 200  # one update per step after the random start
    assert len(res["tests"]) == 1 and res["tests"][0][0] == 300
    assert all(step <= 300 for step, _, _ in res["episodes"])
    assert "[oval SAC seed 0] step    300" in capsys.readouterr().err


def test_the_full_profile_ends_oval_and_technical_after_a_lap_and_runs_classic_to_the_end():
    full, quick = tl.PROFILES["full"], tl.PROFILES["quick"]
    envs = ["oval", "classic", "technical", "pendulum"]
    assert tl.settle_per_env(full, envs, None) == {"oval": 500, "classic": None, "technical": 500, "pendulum": None}
    assert tl.settle_per_env(full, envs, 0) == dict.fromkeys(envs)  # --settle 0: every budget to its end
    assert tl.settle_per_env(quick, ["classic"], 300) == {"classic": 300}
    assert tl.settle_per_env(quick, ["classic"], None) == {"classic": None}


def test_variants_take_their_settings_source_and_learning_rate():
    import gymnasium

    env = gymnasium.make("Pendulum-v1")
    spaces = (env.observation_space, env.action_space)
    tmrl_sac, demo_sac, slow_sac, fixed_sac = (tl._agent(label, spaces, "pendulum", 4)
                                               for label in ("SAC-TMRL", "SAC-UTD4", "SAC-UTD4-LR3", "SAC-UTD4-FA"))
    assert (tmrl_sac.lr_actor, tmrl_sac.lr_critic) == (1e-5, 5e-5)  # tmrl's shipped ALG settings
    assert (demo_sac.lr_actor, demo_sac.lr_critic, demo_sac.lr_entropy) == (1e-3, 1e-3, 1e-3)
    assert (slow_sac.lr_actor, slow_sac.lr_critic, slow_sac.lr_entropy) == (3e-4, 3e-4, 3e-4)
    assert tl.VARIANTS["SAC-UTD2"][2] == 2 and tl.VARIANTS["SAC-UTD4-LR3"][2] == 4
    assert demo_sac.learn_entropy_coef and not fixed_sac.learn_entropy_coef
    assert fixed_sac.lr_actor == 1e-3 and float(fixed_sac.alpha) == 0.01 and float(demo_sac.alpha) == 0.2
    te6 = tl._agent("SAC-UTD4-TE6", spaces, "pendulum", 4)
    assert te6.learn_entropy_coef and te6.target_entropy == -6.0 and demo_sac.target_entropy == -1.0  # -act_dim


def test_the_entropy_target_screens_change_the_critics_target_only():
    """``-NB``: no entropy term in the target; ``-SH``: the term measured from the target entropy;
    ``-CL``: the term where it is a bonus only. Each against the formula, with SAC-UTD4's weights."""
    import gymnasium
    import torch

    from tmrl.batch import Batch

    env = gymnasium.make("Pendulum-v1")
    spaces = (env.observation_space, env.action_space)
    sac = tl._agent("SAC-UTD4", spaces, "pendulum", 4)
    g = torch.Generator().manual_seed(3)
    rows = 64
    batch = Batch(torch.randn(rows, 3, generator=g), torch.rand(rows, 1, generator=g) * 2 - 1,
                  torch.randn(rows, generator=g), torch.randn(rows, 3, generator=g),
                  (torch.rand(rows, generator=g) < 0.3).float(), torch.zeros(rows))
    alpha = torch.tensor(0.2)
    with torch.no_grad():  # a narrower policy: log-densities of both signs
        sac.model.actor.log_std_layer.bias.fill_(-1.5)
    torch.manual_seed(0)
    a2, logp = sac.actor(batch.next_obs)
    q2, r, live = sac.target_q(batch.next_obs, a2).detach(), batch.rew, sac.gamma * (1.0 - batch.terminated)
    logp = logp.detach()
    assert (logp > 0).any() and (logp < 0).any()  # both signs, so that the bonus-only clip shows
    expected = {"SAC-UTD4-NB-R250": r + live * q2,
                "SAC-UTD4-SH-R250": r + live * (q2 - alpha * (logp + sac.target_entropy)),
                "SAC-UTD4-CL-R250": r + live * (q2 - alpha * logp.clamp(max=0.0))}
    for label, want in expected.items():
        agent = tl._agent(label, spaces, "pendulum", 4)
        agent.model.load_state_dict(sac.model.state_dict())
        agent.model_target.load_state_dict(sac.model_target.state_dict())
        torch.manual_seed(0)
        got = agent.target_value(batch, alpha)
        assert torch.allclose(got, want, atol=1e-5), label
        assert agent.fused_update is None and tl.start_steps_of(label) == 250
    torch.manual_seed(0)
    assert not torch.allclose(sac.target_value(batch, alpha), expected["SAC-UTD4-NB-R250"], atol=1e-3)


def test_the_layer_norm_screens_train_sac_with_layer_normalised_critics():
    """``-LN``: SAC's update and lidar actor, critics ``Linear -> LayerNorm -> ReLU`` with no
    dropout; SAC-UTD4's critics have no normalisation."""
    from torch import nn

    built = {}
    for label in ("SAC-UTD4", "SAC-UTD4-LN-R250", "SAC-UTD8-LN-R250"):
        res = tl.run("classic", label, 0, 260, tl.VARIANTS[label][2], 250, 10**9, 32, 10,
                     on_agent=lambda agent, label=label: built.__setitem__(label, agent))
        assert res["updates"] > 0, label
    sac = built["SAC-UTD4"]
    assert not any(isinstance(m, nn.LayerNorm) for m in sac.model.modules())
    for label in ("SAC-UTD4-LN-R250", "SAC-UTD8-LN-R250"):
        agent = built[label]
        assert type(agent) is type(sac) and type(agent.model.actor) is type(sac.model.actor), label
        assert agent.learn_entropy_coef and tl.start_steps_of(label) == 250
        kinds = [type(m) for m in agent.model.modules()]
        assert kinds.count(nn.LayerNorm) == 4, label  # two hidden layers in each of two critics
        assert all(m.p == 0.0 for m in agent.model.modules() if isinstance(m, nn.Dropout)), label
        assert not any(isinstance(m, nn.LayerNorm) for m in agent.model.actor.modules())


def test_the_redq_screen_updates_its_policy_with_every_critic_update():
    """``REDQSAC-UTD4-R250``: REDQ-SAC (ten critics, a random pair in the target) at the demo's
    settings, the policy updated with each of the 4 critic updates per step; ``REDQSAC`` updates
    it once per step, as in the paper."""
    import gymnasium

    env = gymnasium.make("Pendulum-v1")
    spaces = (env.observation_space, env.action_space)
    screen, paper = tl._agent("REDQSAC-UTD4-R250", spaces, "pendulum", 4), tl._agent("REDQSAC", spaces, "pendulum", 4)
    assert type(screen) is type(paper) and len(screen.critics) == 10 and screen.m == 2
    assert screen.q_updates_per_policy_update == 1 and paper.q_updates_per_policy_update == 4
    assert (screen.lr_actor, screen.gamma, screen.learn_entropy_coef) == (1e-3, 0.99, True)
    assert tl.start_steps_of("REDQSAC-UTD4-R250") == 250 and tl.VARIANTS["REDQSAC-UTD4-R250"][2] == 4


def test_the_five_critic_redq_screen_differs_from_the_ten_critic_one_only_in_its_critics():
    """``REDQSAC-N5-UTD4-R250``: ``REDQSAC-UTD4-R250`` with five critics (still a random pair in
    each target), the rest of its settings equal."""
    import gymnasium

    env = gymnasium.make("Pendulum-v1")
    spaces = (env.observation_space, env.action_space)
    five, ten = tl._agent("REDQSAC-N5-UTD4-R250", spaces, "pendulum", 4), tl._agent("REDQSAC-UTD4-R250", spaces, "pendulum", 4)
    assert (len(five.critics), len(five.critics_target), five.n, five.m) == (5, 5, 5, 2)
    assert len(ten.critics) == 10
    same = ("q_updates_per_policy_update", "lr_actor", "lr_critic", "gamma", "polyak", "learn_entropy_coef")
    assert [getattr(five, k) for k in same] == [getattr(ten, k) for k in same]
    assert tl.start_steps_of("REDQSAC-N5-UTD4-R250") == 250 and tl.VARIANTS["REDQSAC-N5-UTD4-R250"][2] == 4


def test_the_eight_update_redq_screen_differs_from_the_four_update_one_only_in_its_ratio():
    """``REDQSAC-UTD8-CAP-R250``: ``REDQSAC-UTD4-CAP-R250`` at 8 critic updates per environment
    step, each with its policy update, the rest of its settings equal."""
    import gymnasium

    env = gymnasium.make("Pendulum-v1")
    spaces = (env.observation_space, env.action_space)
    eight = tl._agent("REDQSAC-UTD8-CAP-R250", spaces, "pendulum", tl.VARIANTS["REDQSAC-UTD8-CAP-R250"][2])
    four = tl._agent("REDQSAC-UTD4-CAP-R250", spaces, "pendulum", tl.VARIANTS["REDQSAC-UTD4-CAP-R250"][2])
    assert (tl.VARIANTS["REDQSAC-UTD8-CAP-R250"][2], tl.VARIANTS["REDQSAC-UTD4-CAP-R250"][2]) == (8, 4)
    same = ("n", "m", "q_updates_per_policy_update", "lr_actor", "lr_critic", "gamma", "polyak", "learn_entropy_coef")
    assert [getattr(eight, k) for k in same] == [getattr(four, k) for k in same]
    assert eight.q_updates_per_policy_update == 1
    assert tl.start_steps_of("REDQSAC-UTD8-CAP-R250") == tl.start_steps_of("REDQSAC-UTD4-CAP-R250") == 250
    assert tl.DEMO_OVERRIDES["REDQSAC-UTD8-CAP-R250"] == tl.DEMO_OVERRIDES["REDQSAC-UTD4-CAP-R250"]


def test_the_n_step_screen_regresses_on_n_step_returns_cut_at_episode_ends():
    """``-NS3``: batches carry ``r_t + g r_{t+1} + g^2 r_{t+2}`` and ``o_{t+3}``, fewer terms where
    the episode ends (terminated: no bootstrap; truncated: bootstrap from its last observation) or
    the memory's newest sample comes first; the target bootstraps with ``g^K`` of each transition."""
    import gymnasium
    import numpy as np
    import torch

    from tmrl.memory import GenericTorchMemory

    class Buf:
        def __init__(self, samples):
            self.memory, self.sources = samples, None
            self.stat_train_return = self.stat_test_return = 0.0
            self.stat_train_steps = self.stat_test_steps = 0

        def __len__(self):
            return len(self.memory)

    def episode(ep, n, rewards, end):  # a reset sample, then n - 1 steps; obs = (ep, t, 0)
        return [(None if t == 0 else np.array([0.1 * t], dtype=np.float32), np.array([ep, t, 0.0], dtype=np.float32),
                 0.0 if t == 0 else rewards[t - 1], t == n - 1 and end == "terminated",
                 t == n - 1 and end == "truncated", {}) for t in range(n)]

    env = gymnasium.make("Pendulum-v1")
    agent = tl._agent("REDQSAC-UTD4-CAP-NS3-R250", (env.observation_space, env.action_space), "pendulum", 4)
    g = agent.gamma
    memory = GenericTorchMemory(device="cpu", nb_steps=1, memory_size=100, batch_size=4)
    memory.append(Buf(episode(0, 6, [1.0, 2.0, 3.0, 4.0, 5.0], "terminated") + episode(1, 4, [10.0, 20.0, 30.0], "truncated")
                      + episode(2, 4, [7.0, 8.0, 9.0], None)))  # the third episode goes on (newest sample: its t=3)
    one_step = memory.sample
    assert tl.DEMO_OVERRIDES["REDQSAC-UTD4-CAP-NS3-R250"]["n_step"] == 3
    tl._n_step_targets(agent, memory, 3)
    slots = {(int(o[0]), int(o[1])): j for j, o in zip(memory.valid_slots(), one_step(memory.valid_slots()).next_obs)}
    cases = {  # (episode, t of o_{t+1}) -> (return, t of the bootstrap observation, terminated, K)
        (0, 1): (1 + 2 * g + 3 * g**2, 3, 0.0, 3),
        (0, 3): (3 + 4 * g + 5 * g**2, 5, 1.0, 3),
        (0, 4): (4 + 5 * g, 5, 1.0, 2),  # terminated after two steps
        (0, 5): (5.0, 5, 1.0, 1),
        (1, 2): (20 + 30 * g, 3, 0.0, 2),  # truncated: bootstrap from its last observation
        (1, 3): (30.0, 3, 0.0, 1),
        (2, 2): (8 + 9 * g, 3, 0.0, 2),  # the newest sample comes first
    }
    batch = memory.sample(np.array([slots[k] for k in cases]))
    for i, (k, (ret, t_end, term, K)) in enumerate(cases.items()):
        assert batch.rew[i].item() == pytest.approx(ret, rel=1e-6), k
        assert batch.obs[i].tolist() == [k[0], k[1] - 1, 0.0] and batch.next_obs[i].tolist() == [k[0], t_end, 0.0], k
        assert batch.terminated[i].item() == term, k
    alpha = torch.tensor(0.3)
    torch.manual_seed(0)
    got = agent.target_value(batch, alpha)
    torch.manual_seed(0)
    a2, logp = agent.actor(batch.next_obs)
    q2 = agent.target_q(batch.next_obs, a2)
    discount = torch.tensor([g ** K for *_, K in cases.values()], dtype=torch.float32)
    want = batch.rew + discount * (1 - batch.terminated) * (q2 - alpha * logp)
    assert torch.allclose(got, want, atol=1e-5)
    assert agent.fused_update is None
    # a distributional critic's target atoms (B, M) take each transition's return and discount too
    bro = tl._agent("BRO-W128-UTD8-CAP-NS3-R250", (env.observation_space, env.action_space), "pendulum", 8)
    tl._n_step_targets(bro, memory, 3)
    batch = memory.sample(np.array([slots[k] for k in cases]))
    torch.manual_seed(0)
    got = bro.target_value(batch, alpha)
    torch.manual_seed(0)
    a2, logp = bro.actor(batch.next_obs)
    z = bro.target_q(batch.next_obs, a2)
    want = batch.rew[:, None] + (discount * (1 - batch.terminated))[:, None] * (z - alpha * logp[:, None])
    assert got.shape == z.shape == (len(cases), bro.n_quantiles) and torch.allclose(got, want, atol=1e-5)


def test_variants_take_tmrls_random_start_unless_they_name_their_own(tmp_path, monkeypatch):
    assert tl.START_STEPS == 1000  # tmrl's ENVIRONMENT_STEPS_BEFORE_TRAINING
    assert tl.start_steps_of("SAC-TMRL") == 1000 and tl.start_steps_of("DROQ") == 1000
    assert tl.start_steps_of("SAC-UTD8-R250") == 250
    seen = []

    class Done:
        returncode = 0
        stdout = json.dumps({"episodes": [], "tests": [], "wall_s": 1.0, "updates": 0, "steps": 4, "updates_per_s": 0.0})

    real_run = tl.subprocess.run

    def fake_run(cmd, **kwargs):  # the child runs only; anything else (git, for the record) really runs
        if "--run" not in cmd:
            return real_run(cmd, **kwargs)
        seen.append(json.loads(cmd[cmd.index("--run") + 1]))
        return Done()

    monkeypatch.setattr(tl.harness, "Recorder", functools.partial(tl.harness.Recorder, out_dir=tmp_path))
    monkeypatch.setattr(tl.subprocess, "run", fake_run)
    tl.main(["--agents", "SAC-TMRL,SAC-UTD8-R250", "--tracks", "classic", "--seeds", "1", "--steps", "4000",
             "--jobs", "1"])
    assert sorted((k["label"], k["start_steps"]) for k in seen) == [("SAC-TMRL", 1000), ("SAC-UTD8-R250", 250)]
    seen.clear()
    tl.main(["--agents", "SAC-TMRL,SAC-UTD8-R250", "--tracks", "classic", "--seeds", "1", "--steps", "4000",
             "--jobs", "1", "--start-steps", "100"])  # one value for every agent
    assert sorted((k["label"], k["start_steps"]) for k in seen) == [("SAC-TMRL", 100), ("SAC-UTD8-R250", 100)]


def test_the_demos_real_time_setting_is_a_default_agent_of_the_benchmark():
    """What ``--demo --realtime --algorithm SAC`` trains (the CPU's real-time default until
    2026-12-02) is what a plain benchmark run measures as ``SAC-UTD4-FA``; the CPU's real-time
    default since, ``SAC-W128-UTD8-CAP-R250``, is a default agent too (tests/test_sim.py compares
    its settings)."""
    import gymnasium

    from tmrl.sim.demo import DEMO_SETTINGS as S

    env = gymnasium.make("Pendulum-v1")
    agent = tl._agent("SAC-UTD4-FA", (env.observation_space, env.action_space), "pendulum", 4)
    assert "SAC-UTD4-FA" in tl.DEFAULT_AGENTS and "SAC-W128-UTD8-CAP-R250" in tl.DEFAULT_AGENTS
    assert (S["algorithm"], S["realtime_max_training_steps_per_env_step"]) == (tl.VARIANTS["SAC-UTD4-FA"][0],
                                                                               tl.VARIANTS["SAC-UTD4-FA"][2])
    assert (agent.lr_actor, agent.lr_critic, agent.gamma, float(agent.alpha), agent.learn_entropy_coef) == \
        (S["lr"], S["lr"], S["gamma"], S["realtime_alpha"], S["realtime_learn_entropy_coef"])


def _record(path, budgets, runs):
    """A track_learning JSONL file as the Recorder writes it: a run line, then per run its measures."""
    import json

    lines = [{"kind": "run", "bench": "track_learning", "settings": {"budgets": budgets}}]
    for (case, side, seed), res in runs.items():
        lines += [
            {"kind": "measure", "case": case, "metric": "wall_s", "side": side, "value": res["wall_s"], "round": seed},
            {"kind": "measure", "case": case, "metric": "updates_per_s_in_train", "side": side, "value": 50.0,
             "round": seed},
            {"kind": "measure", "case": case, "metric": "steps_to_first_lap", "side": side,
             "value": tl.first_step(res), "round": seed, "episodes": res["episodes"], "tests": res["tests"]},
        ]
    path.write_text("\n".join(json.dumps(line) for line in lines) + "\n")


def test_merge_joins_the_runs_of_several_records_into_one_table(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(tl.harness, "OUT", tmp_path / "out")
    fast = {"episodes": [(2000, 161.7, 27.0)], "tests": [], "wall_s": 10.0}
    slow = {"episodes": [(6000, 161.7, 26.0)], "tests": [(5000, 1.0, None)], "wall_s": 30.0}
    _record(tmp_path / "a.jsonl", {"classic": 10000}, {("classic", "SAC-TMRL", 0): slow, ("classic", "SAC-UTD4", 0): fast})
    _record(tmp_path / "b.jsonl", {"classic": 8000}, {("classic", "SAC-UTD4", 1): {**fast, "episodes": [(3000, 161.7, 28.0)]},
                                                       ("classic", "SAC-TMRL", 0): {**slow, "wall_s": 99.0}})
    results, budgets, seeds = tl.load_results([tmp_path / "a.jsonl", tmp_path / "b.jsonl"])
    assert budgets == {"classic": 10000} and seeds == 2
    assert sorted(tl.first_step(r) for r in results[("classic", "SAC-UTD4")]) == [2000, 3000]
    assert [r["wall_s"] for r in results[("classic", "SAC-TMRL")]] == [99.0]  # the same seed twice: the later record
    assert results[("classic", "SAC-TMRL")][0]["tests"] == [(5000, 1.0, None)]
    tl.main(["--merge", str(tmp_path / "a.jsonl"), str(tmp_path / "b.jsonl")])
    out = capsys.readouterr().out
    assert "SAC-UTD4" in out and "2500 [2000..3000] 2/2" in out and "6000 [6000..6000] 1/1" in out
    assert len(list((tmp_path / "out").glob("track_learning-merged-*.png"))) == 1


def test_merge_names_a_missing_record_in_one_line(tmp_path):
    with pytest.raises(SystemExit, match="no-such.jsonl: no such record"):
        tl.main(["--merge", str(tmp_path / "no-such.jsonl")])


def test_merge_refuses_another_benchmark_s_record(tmp_path):
    (tmp_path / "x.jsonl").write_text('{"kind": "run", "bench": "trainer_speed", "settings": {}}\n')
    with pytest.raises(SystemExit, match="not a track_learning record"):
        tl.load_results([tmp_path / "x.jsonl"])


def test_the_cap_screens_hold_a_fallen_entropy_coefficient_under_their_ceiling():
    """``SAC-UTD*-CAP`` (and REDQ-SAC's ``-CAP-R250``): once the learned coefficient has fallen to 0.01 it stays at or under it;
    above it (its start, 0.2) it moves freely; the uncapped variant's rises above it."""
    import math

    import gymnasium
    import torch
    from test_algorithms import random_batch

    env = gymnasium.make("Pendulum-v1")
    spaces = (env.observation_space, env.action_space)
    gen = torch.Generator().manual_seed(0)

    def drive(agent, target, n):
        agent.target_entropy = target  # far below the policy's entropy: alpha falls; far above: it rises
        alphas = []
        for _ in range(n):
            agent.train(random_batch(gen, 32, obs_space=(env.observation_space,), act_dim=1))
            alphas.append(math.exp(float(agent.log_alpha.detach())))
        return alphas

    for label, capped in (("SAC-UTD4-CAP", True), ("SAC-UTD4", False), ("REDQSAC-UTD4-CAP-R250", True),
                          ("REDQSAC-UTD8-CAP-R250", True), ("REDQSAC-UTD4-R250", False)):
        agent = tl._agent(label, spaces, "pendulum", 4)
        agent.alpha_optimizer.param_groups[0]["lr"] = 0.3  # big steps on log(alpha)
        falling = drive(agent, -100.0, 12)
        assert 0.01 < falling[0] < 0.2 and falling[-1] < 0.01
        rising = max(drive(agent, 100.0, 40))
        assert (rising <= 0.01 * (1 + 1e-5)) if capped else rising > 0.02, label


def test_the_floor_counts_an_update_as_its_matrix_products_forward_and_backward():
    """The FLOP count of a real SAC run's updates matches the matrix products of SAC's update
    written out by hand (bench/trainer_speed.py's floor), four updates per step."""
    from bench.trainer_speed import update_products

    counted = tl.update_gflop_per_step("SAC-TMRL", batch_size=32, count_steps=3)
    by_hand = sum(2 * c * m * k * n for c, m, k, n in update_products(obs_dim=83, act_dim=3, hidden=256, batch=32,
                                                                      n_critics=2, n_targets=2)) / 1e9
    assert counted == pytest.approx(4 * by_hand, rel=0.01)
    # CrossQ: one update per step, but critics 1024 wide on twice the batch
    assert tl.update_gflop_per_step("CROSSQ", batch_size=32, count_steps=3) > 2 * counted


def test_the_floor_of_a_run_is_its_training_steps_at_the_cores_rate():
    assert tl.floor_seconds(2.0, 10_000, 1_000, 100.0) == 180.0  # 9,000 steps x 2 GFLOP at 100 GFLOP/s
    assert tl.floor_seconds(2.0, 500, 1_000, 100.0) == 0.0  # no training step in the budget


def test_floor_prints_the_least_time_of_the_runs_a_command_would_start(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(tl.harness, "Recorder", functools.partial(tl.harness.Recorder, out_dir=tmp_path))
    monkeypatch.setattr(tl, "matmul_gflops", lambda: 50.0)  # the rate is the machine's; the sums are the test's
    monkeypatch.setattr(tl, "update_gflop_per_step", lambda label, batch_size: {"SAC": 1.0, "DROQ": 2.0}[label])
    tl.main(["--floor", "--agents", "SAC,DROQ", "--tracks", "oval,classic", "--seeds", "3", "--steps", "6000",
             "--jobs", "2"])
    out = capsys.readouterr().out
    # per run (5,000 training steps): SAC 100 s, DroQ 200 s; 3 seeds, 2 at once: classic alone
    # (3 x 300 / 2 = 450 s = 7.5 min, printed 8) and every run to its budget (15 min)
    assert "SAC" in out and "DROQ" in out and "between 8 min (the classic runs alone" in out
    assert "and 15 min (every run to its budget; oval runs end after their first lap)" in out
    records = [json.loads(line) for line in next(tmp_path.glob("track_learning-*.jsonl")).read_text().splitlines()]
    floors = {r["metric"]: r["value"] for r in records if r.get("case") == "floor" and r.get("side") == "ours"}
    assert floors["floor_min_all_budgets"] == 15.0 and floors["floor_min_whole_budget_tracks"] == 7.5
    assert not any(r.get("metric") == "steps_to_first_lap" for r in records)  # nothing was run


def test_the_settings_docs_trackmania_gives_are_the_ones_the_benchmark_measured():
    """Each ``config.json`` fragment of docs/trackmania.md, laid over the shipped TM20LIDAR file,
    builds the agent of the benchmark variant it stands for: same ratio, random steps and every
    hyperparameter (the TrackMania file's own betas and target entropy are tmrl's, not the
    benchmark's, so a fragment that leaves them out is not what was measured)."""
    import re

    import gymnasium

    from tmrl.algorithms import agent_class
    from tmrl.config import loader
    from tmrl.config.schema import AGENT_CLASSES, arguments

    measured = {"SAC": "SAC-UTD4-FA", "REDQSAC": "REDQSAC-UTD8-CAP-R250", "BRO": "BRO-W128-UTD8-CAP-R250"}
    doc = (REPO / "docs" / "trackmania.md").read_text(encoding="utf-8")
    fragments = [json.loads("{" + b + "}") for b in re.findall(r"```json\n(.*?)```", doc, re.DOTALL)
                 if '"ALGORITHM"' in b and '"DRQ"' not in b]  # DrQ: the pixel test below
    assert sorted(f["ALG"]["ALGORITHM"] for f in fragments) == sorted(measured)
    shipped = json.loads((REPO / "config" / "config_tm20lidar.json").read_text(encoding="utf-8"))
    env = gymnasium.make("Pendulum-v1")
    spaces = (env.observation_space, env.action_space)

    for fragment in fragments:
        alg = fragment["ALG"]["ALGORITHM"]
        label = measured[alg]
        cfg = loader.validate({**shipped, **{k: v for k, v in fragment.items() if k != "ALG"},
                               "ALG": {**shipped["ALG"], **fragment["ALG"]}})
        assert cfg["MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP"] == tl.VARIANTS[label][2], label
        assert cfg["ENVIRONMENT_STEPS_BEFORE_TRAINING"] == tl.start_steps_of(label), label
        built = agent_class(alg)(*spaces, "cpu", **arguments(cfg, AGENT_CLASSES[alg]))
        measured_agent = tl._agent(label, spaces, "pendulum", tl.VARIANTS[label][2])
        assert _measured_settings(built) == _measured_settings(measured_agent), label


# --- from pixels (--interface SIMFULL) ---------------------------------------------------------------


def _agent_settings(agent):
    """What makes two agents the same setting: their hyperparameters, optimizers' betas and classes."""
    keys = ("lr_actor", "lr_critic", "lr_entropy", "gamma", "polyak", "alpha", "learn_entropy_coef",
            "target_entropy", "alpha_max", "image_pad", "update_order")
    betas = [g["betas"] for opt in (agent.pi_optimizer, agent.q_optimizer) for g in opt.param_groups]
    return {k: getattr(agent, k, None) for k in keys} | {"betas": betas, "type": type(agent).__name__,
                                                        "model": type(agent.model).__name__}


def _pixel_agent(label):
    """The agent, memory and worker parts a run of image variant ``label`` builds (on classic)."""
    from tmrl.sim.interfaces import fast_env

    parts = tl._pixel_parts(label, "classic", 8, 1000, "cpu")
    env = fast_env(tl.pixel_config(label, "classic", 8))
    return parts, parts["agent"]((env.observation_space, env.action_space), "cpu")


def test_the_image_variants_are_what_a_simfull_config_builds():
    """``DRQ``: DrQ's settings, uint8 frames (preprocessor and RawImageMemory), 8 updates per step
    after 1,000 random steps. ``SAC-TMRL-CNN``: tmrl 0.7.1's TM20FULL file's ALG values (the anchor
    file) on SAC with the CNN actor-critic and the float ImageMemory, 4 updates per step."""
    from tmrl.algorithms.drq import DrQActor
    from tmrl.driving import preprocessors
    from tmrl.driving.memories import ImageMemory, RawImageMemory
    from tmrl.driving.models import DEFAULT_CNN, SquashedGaussianCNNActor

    cfg = tl.pixel_config("DRQ", "oval", 256)
    env = cfg["ENV"]
    assert (env["RTGYM_INTERFACE"], env["SIM_FAST_MODE"], env["IMG_HIST_LEN"], env["IMG_WIDTH"], env["IMG_HEIGHT"]) == \
        ("SIMFULL", True, 4, 64, 64)
    assert env["RTGYM_CONFIG"]["interface_kwargs"] == {"track": "oval"} and cfg["BATCH_SIZE"] == 256
    parts, drq = _pixel_agent("DRQ")
    assert type(parts["memory"]) is RawImageMemory and parts["actor_cls"] is DrQActor
    assert parts["worker"]["obs_preprocessor"] is preprocessors.preprocess_full_obs_uint8
    assert _agent_settings(drq) == {
        "lr_actor": 1e-3, "lr_critic": 1e-3, "lr_entropy": 1e-3, "gamma": 0.99, "polyak": 0.99, "alpha": drq.alpha,
        "learn_entropy_coef": True, "target_entropy": -3.0, "alpha_max": None, "image_pad": 4,
        "update_order": "simultaneous", "betas": [(0.9, 0.999)] * 2, "type": "DrQAgent", "model": "DrQActorCritic"}
    assert abs(float(drq.alpha) - 0.1) < 1e-6
    assert (tl.utd_of("DRQ"), tl.start_steps_of("DRQ")) == (8, 1000)
    assert (tl.utd_of("DRQ-UTD4"), tl.utd_of("DRQ-UTD1")) == (4, 1)

    parts, cnn = _pixel_agent("SAC-TMRL-CNN")
    assert type(parts["memory"]) is ImageMemory and parts["actor_cls"] is SquashedGaussianCNNActor
    assert parts["worker"]["obs_preprocessor"] is preprocessors.preprocess_full_obs
    assert type(cnn.model).__name__ == "CNNActorCritic" and len(cnn.model.qs) == 2
    assert [m.out_channels for m in cnn.model.actor.modules() if type(m).__name__ == "Conv2d"] == \
        list(DEFAULT_CNN["channels"])  # tmrl's VanillaCNN sizes
    anchor = json.loads((REPO / "bench" / "anchors" / "tmrl-0.7.1-config.json").read_text(encoding="utf-8"))
    alg = anchor["ALG"]
    assert anchor["ENV"]["RTGYM_INTERFACE"] == "TM20FULL" and alg["ALGORITHM"] == "SAC"
    got = _agent_settings(cnn)
    assert (got["lr_actor"], got["lr_critic"], got["lr_entropy"], got["gamma"], got["polyak"]) == \
        (alg["LR_ACTOR"], alg["LR_CRITIC"], alg["LR_ENTROPY"], alg["GAMMA"], alg["POLYAK"])
    assert got["learn_entropy_coef"] is alg["LEARN_ENTROPY_COEF"] is False and float(cnn.alpha) == alg["ALPHA"]
    assert got["target_entropy"] == alg["TARGET_ENTROPY"] and got["betas"] == [tuple(alg["BETAS_ACTOR"])] * 2
    assert (tl.utd_of("SAC-TMRL-CNN"), tl.start_steps_of("SAC-TMRL-CNN")) == \
        (anchor["MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP"], anchor["ENVIRONMENT_STEPS_BEFORE_TRAINING"])
    # the lidar reference is docs/trackmania.md's recommendation for a GPU, and it stays on the lidar
    assert tl.LIDAR_REFERENCE in tl.VARIANTS and tl.LIDAR_REFERENCE in tl.DEFAULT_PIXEL_AGENTS
    assert tl.interface_of(tl.LIDAR_REFERENCE) == "SIMLIDAR" and tl.interface_of("DRQ") == "SIMFULL"
    assert not set(tl.PIXEL_VARIANTS) & set(tl.VARIANTS)


def test_the_pixel_quick_check_records_image_rows_beside_the_lidar_reference(tmp_path, monkeypatch, capsys):
    """``--interface SIMFULL --quick``, run for real (one child process per row): the record says
    the interface of the command and of every row, and the observation each row's environment
    gave (frames for the image rows, lidar for the reference); every row trained, and has a curve."""
    monkeypatch.setattr(tl.harness, "Recorder", functools.partial(tl.harness.Recorder, out_dir=tmp_path))
    tl.main(["--interface", "SIMFULL", "--quick", "--device", "cpu"])
    path = next(tmp_path.glob("track_learning-*.jsonl"))
    records = [json.loads(line) for line in path.read_text().splitlines()]
    settings = records[0]["settings"]
    assert (settings["interface"], settings["device"], settings["profile"], settings["budgets"]) == \
        ("SIMFULL", "cpu", "pixels-quick", {"classic": 200})
    want = {"DRQ": "SIMFULL", "SAC-TMRL-CNN": "SIMFULL", tl.LIDAR_REFERENCE: "SIMLIDAR"}
    assert settings["interfaces"] == want and set(settings["pixel_variants"]) == {"DRQ", "SAC-TMRL-CNN"}
    measures = [r for r in records if r["kind"] == "measure"]
    assert {r["side"] for r in measures} == set(want)
    assert all(r["interface"] == want[r["side"]] for r in measures)
    laps = {r["side"]: r for r in measures if r["metric"] == "steps_to_first_lap"}
    for label, row in laps.items():
        frames = [s for s in row["observation"] if len(s) == 3]
        assert frames == ([[4, 64, 64]] if want[label] == "SIMFULL" else []), label
        assert [4, 19] in row["observation"] or want[label] == "SIMFULL", label
        assert [t[0] for t in row["tests"]] == [200] and row["episodes"], label  # a curve to draw
    speeds = {r["side"]: r["value"] for r in measures if r["metric"] == "updates_per_s_in_train"}
    assert all(v > 0 for v in speeds.values()), speeds  # the last 10 steps trained
    assert path.with_suffix(".png").is_file()
    out = capsys.readouterr().out  # the table: one row per variant, its interface beside it
    assert re.search(r"agent +interface +steps to first lap", out)
    for label, interface in want.items():
        assert re.search(rf"^  {label} +{interface} +not reached", out, re.MULTILINE), label


def _fake_children(monkeypatch, tmp_path, report=None):
    """Each child run's keyword arguments; a child reports ``report(kwargs)`` as its interface."""
    seen = []
    real_run = tl.subprocess.run

    class Done:
        returncode = 0

    def fake_run(cmd, **kwargs):
        if "--run" not in cmd:
            return real_run(cmd, **kwargs)
        job = json.loads(cmd[cmd.index("--run") + 1])
        seen.append(job)
        done = Done()
        res = {"episodes": [], "tests": [], "wall_s": 1.0, "updates": 0, "steps": 4, "updates_per_s": 0.0}
        if report is not None:
            res["interface"] = report(job)
        done.stdout = json.dumps(res)
        return done

    monkeypatch.setattr(tl.harness, "Recorder", functools.partial(tl.harness.Recorder, out_dir=tmp_path))
    monkeypatch.setattr(tl.subprocess, "run", fake_run)
    return seen


def test_a_simfull_run_drives_each_row_on_its_own_interface(tmp_path, monkeypatch):
    seen = _fake_children(monkeypatch, tmp_path, report=lambda job: job.get("interface", "SIMLIDAR"))
    tl.main(["--interface", "simfull", "--tracks", "classic", "--seeds", "2", "--steps", "3000", "--jobs", "1",
             "--device", "cpu"])
    got = {(k["label"], k["interface"]) for k in seen}
    assert got == {("DRQ", "SIMFULL"), ("SAC-TMRL-CNN", "SIMFULL"), (tl.LIDAR_REFERENCE, "SIMLIDAR")}
    assert len(seen) == 6 and {k["seed"] for k in seen} == {0, 1}
    # every row on the same track, budget and batch; each variant's own ratio and random start
    assert {(k["env_name"], k["steps"], k["batch_size"]) for k in seen} == {("classic", 3000, 256)}
    assert {(k["label"], k["utd"], k["start_steps"]) for k in seen} == {
        ("DRQ", 8, 1000), ("SAC-TMRL-CNN", 4, 1000), (tl.LIDAR_REFERENCE, 8, 250)}
    seen.clear()
    tl.main(["--tracks", "classic", "--seeds", "1", "--steps", "400", "--jobs", "1", "--agents", "SAC"])
    assert ["interface" in k for k in seen] == [False]  # SIMLIDAR, the default: the child's arguments as before
    with pytest.raises(SystemExit) as stop:  # an image variant needs --interface SIMFULL
        tl.main(["--agents", "DRQ", "--tracks", "classic", "--seeds", "1"])
    assert stop.value.code == 2


def test_a_row_that_drove_another_interface_than_asked_stops_the_run(tmp_path, monkeypatch):
    _fake_children(monkeypatch, tmp_path, report=lambda job: "SIMLIDAR")  # the images silently not used
    with pytest.raises(SystemExit, match="the DRQ run on classic, seed 0, drove SIMLIDAR, not SIMFULL"):
        tl.main(["--interface", "SIMFULL", "--agents", "DRQ", "--tracks", "classic", "--seeds", "1", "--steps", "300",
                 "--jobs", "1", "--device", "cpu"])
    with pytest.raises(SystemExit, match=f"{tl.LIDAR_REFERENCE} runs on SIMLIDAR, not SIMFULL"):
        tl.run("classic", tl.LIDAR_REFERENCE, 0, 10, 8, 5, 10, 8, 5, interface="SIMFULL")
    with pytest.raises(SystemExit, match="DRQ runs on SIMFULL, not SIMLIDAR"):
        tl.run("classic", "DRQ", 0, 10, 8, 5, 10, 8, 5)


def test_merge_refuses_records_of_two_interfaces(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(tl.harness, "OUT", tmp_path / "out")
    run = {"episodes": [(3000, 150.0, 30.0)], "tests": [], "wall_s": 10.0}
    _record(tmp_path / "lidar.jsonl", {"classic": 10000}, {("classic", "SAC-TMRL", 0): run})  # before --interface
    _record(tmp_path / "pixels.jsonl", {"classic": 20000}, {("classic", "DRQ", 0): run})
    lines = (tmp_path / "pixels.jsonl").read_text().splitlines()
    head = json.loads(lines[0])
    head["settings"]["interface"] = "SIMFULL"
    (tmp_path / "pixels.jsonl").write_text("\n".join([json.dumps(head), *lines[1:]]) + "\n")
    with pytest.raises(SystemExit, match=r"pixels.jsonl was recorded with --interface SIMFULL and .*lidar.jsonl with "
                                         "--interface SIMLIDAR: merge the records of one interface at a time"):
        tl.load_results([tmp_path / "lidar.jsonl", tmp_path / "pixels.jsonl"])
    results, _, _ = tl.load_results([tmp_path / "pixels.jsonl", tmp_path / "pixels.jsonl"])  # one interface: fine
    assert list(results) == [("classic", "DRQ")]
    tl.main(["--merge", str(tmp_path / "pixels.jsonl")])
    assert "DRQ" in capsys.readouterr().out


def test_the_drq_settings_the_docs_give_are_the_ones_the_benchmark_runs():
    """Each DrQ ``config.json`` block of docs/simulator.md (laid over the shipped SIMFULL file) and
    docs/trackmania.md (over the shipped defaults, tmrl's TM20FULL file) builds the ``DRQ`` row's
    agent, ratio, random start and batch size."""
    from tmrl.assembly import assemble
    from tmrl.config import loader
    from tmrl.sim.interfaces import fast_env

    _, measured = _pixel_agent("DRQ")
    env = fast_env(tl.pixel_config("DRQ", "classic", 256))  # TM20FULL's observations are the same
    found = 0
    for page, file, interface in (("simulator.md", "config_simfull.json", "SIMFULL"),
                                  ("trackmania.md", "config.json", "TM20FULL")):
        shipped = json.loads((REPO / "config" / file).read_text(encoding="utf-8"))
        assert shipped["ENV"]["RTGYM_INTERFACE"] == interface
        doc = (REPO / "docs" / page).read_text(encoding="utf-8")
        for block in re.findall(r"```json\n(.*?)```", doc, re.DOTALL):
            if '"DRQ"' not in block:
                continue
            fragment = json.loads("{" + block + "}")
            cfg = loader.validate(loader.deep_merge(shipped, fragment))
            assert cfg["MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP"] == tl.utd_of("DRQ"), page
            assert cfg["ENVIRONMENT_STEPS_BEFORE_TRAINING"] == tl.start_steps_of("DRQ"), page
            assert cfg["BATCH_SIZE"] == 256, page  # the benchmark's batch
            built = assemble(cfg).AGENT(env.observation_space, env.action_space, "cpu")  # assembling reaches no game
            assert _agent_settings(built) == _agent_settings(measured), page
            assert abs(float(built.alpha) - float(measured.alpha)) < 1e-7, page
            found += 1
    assert found == 2


@pytest.mark.parametrize("label", ["DRQ", "SAC-TMRL-CNN"])
def test_an_image_row_builds_its_memory_agent_and_actor_on_its_device(label):
    from tmrl.sim.interfaces import fast_env

    parts = tl._pixel_parts(label, "classic", 8, 1000, "meta")  # meta stands in for a GPU
    env = fast_env(tl.pixel_config(label, "classic", 8))
    agent = parts["agent"]((env.observation_space, env.action_space), "meta")
    assert parts["memory"].device == "meta"
    assert {p.device.type for p in agent.model.parameters()} == {"meta"}
    assert torch_device(agent.get_actor().device) == "meta"  # the loop acts with it: observations collate there


def torch_device(device):
    import torch

    return torch.device(device).type


def test_the_recommended_trackmania_templates_build_the_agents_the_benchmark_measured():
    """config_tm20lidar_cpu.json and _gpu.json, as shipped, build the agent of the benchmark variant
    each names (tmrl.config.generate.TM_CPU_SETTING, TM_GPU_SETTING): same class, ratio, random
    steps, hyperparameters and critic sizes."""
    import gymnasium

    from tmrl.algorithms import agent_class
    from tmrl.config import loader
    from tmrl.config.generate import TM_CPU_SETTING, TM_GPU_SETTING
    from tmrl.config.schema import AGENT_CLASSES, arguments

    env = gymnasium.make("Pendulum-v1")
    spaces = (env.observation_space, env.action_space)

    for name, label in (("config_tm20lidar_cpu.json", TM_CPU_SETTING), ("config_tm20lidar_gpu.json", TM_GPU_SETTING)):
        cfg = loader.load_config(REPO / "config" / name)
        assert cfg["ENV"]["RTGYM_INTERFACE"] == "TM20LIDAR", name
        assert cfg["MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP"] == tl.VARIANTS[label][2], name
        assert cfg["ENVIRONMENT_STEPS_BEFORE_TRAINING"] == tl.start_steps_of(label), name
        alg = cfg["ALG"]["ALGORITHM"]
        assert alg == tl.VARIANTS[label][0], name
        built = agent_class(alg)(*spaces, "cpu", **arguments(cfg, AGENT_CLASSES[alg]))
        measured_agent = tl._agent(label, spaces, "pendulum", tl.VARIANTS[label][2])
        assert _measured_settings(built) == _measured_settings(measured_agent), name


def _measured_settings(agent):
    """What makes two agents the same measured setting: hyperparameters, critic sizes, betas, class."""
    keys = ("lr_actor", "lr_critic", "lr_entropy", "gamma", "polyak", "alpha", "learn_entropy_coef",
            "target_entropy", "alpha_max", "n", "m", "q_updates_per_policy_update", "n_quantiles", "pessimism",
            "critic_width", "critic_blocks")
    betas = [g["betas"] for opt in (agent.pi_optimizer, agent.q_optimizer) for g in opt.param_groups]
    return {k: getattr(agent, k, None) for k in keys} | {"betas": betas, "type": type(agent).__name__}
