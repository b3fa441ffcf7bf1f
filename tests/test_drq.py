"""Tests of tmrl.algorithms.drq: the random shift, the encoder trained by the critic alone, the
actor the workers run (its own encoder weights, no augmentation), one update against a step
written here from the equations, the checkpoint round trip, the selection through the config, and
simulator samples reaching the agent with uint8 frames.
Tiny frames (2 of 16x16) and tiny networks: every test runs in well under a second on a CPU."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from gymnasium import spaces
from test_config_objects import SMALL as SIM_SMALL
from test_config_objects import FakeInterface, fresh_objects  # noqa: F401 (fresh_objects: a fixture)

from tmrl.algorithms import drq
from tmrl.algorithms.drq import DrQActor, DrQActorCritic, DrQAgent, random_shift
from tmrl.errors import UserError
from tmrl.util import partial

ACT = spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)
HIST, SIDE, PAD = 2, 16, 4
SIZES = {"channels": (4, 4), "kernels": (3, 3), "strides": (2, 1), "feature_dim": 8, "hidden_sizes": (16,)}
TINY = partial(DrQActorCritic, **SIZES)


def obs_space() -> spaces.Tuple:
    return spaces.Tuple([spaces.Box(0, 1, (1,))] * 3 + [spaces.Box(0, 255, (HIST, SIDE, SIDE), np.uint8), ACT, ACT])


def random_obs(b: int, gen: torch.Generator) -> tuple:
    scalars = tuple(torch.rand(b, 1, generator=gen) for _ in range(3))
    frames = torch.randint(0, 256, (b, HIST, SIDE, SIDE), generator=gen, dtype=torch.uint8)
    return (*scalars, frames, torch.rand(b, 3, generator=gen) * 2 - 1, torch.rand(b, 3, generator=gen) * 2 - 1)


def random_batch(gen: torch.Generator, b: int = 6) -> tuple:
    done = (torch.rand(b, generator=gen) < 0.3).float()
    return (random_obs(b, gen), torch.rand(b, 3, generator=gen) * 2 - 1, torch.randn(b, generator=gen),
            random_obs(b, gen), done, torch.zeros(b))


def agent(**kwargs) -> DrQAgent:
    return DrQAgent(obs_space(), ACT, "cpu", model_cls=TINY, **kwargs)


# --- the random shift ----------------------------------------------------------------------------


def coded_frames(b: int) -> torch.Tensor:
    """Every pixel holds its own address: sample * 10^6 + frame * 10^4 + row * 100 + column."""
    s, c, i, j = torch.meshgrid(torch.arange(b), torch.arange(HIST), torch.arange(SIDE), torch.arange(SIDE),
                                indexing="ij")
    return s * 1_000_000 + c * 10_000 + i * 100 + j


def test_random_shift_moves_each_history_as_one_within_the_padding():
    b = 16
    imgs = coded_frames(b)
    out = random_shift(imgs, PAD, generator=torch.Generator().manual_seed(0))
    assert out.shape == imgs.shape and out.dtype == imgs.dtype
    src_s, src_c = out // 1_000_000, out // 10_000 % 100
    src_i, src_j = out // 100 % 100, out % 100
    _, c, i, j = torch.meshgrid(torch.arange(b), torch.arange(HIST), torch.arange(SIDE), torch.arange(SIDE),
                                indexing="ij")
    # Every output pixel is a pixel of the same sample and frame, at most PAD pixels away.
    assert torch.equal(src_s, torch.arange(b)[:, None, None, None].expand_as(out)) and torch.equal(src_c, c)
    assert (src_i - i).abs().max() <= PAD and (src_j - j).abs().max() <= PAD
    shifts = []
    for k in range(b):
        # Away from the edges (where the padding repeats the border) one displacement holds for
        # every pixel of every frame of the sample.
        inner = (slice(None), slice(PAD, SIDE - PAD), slice(PAD, SIDE - PAD))
        di, dj = (src_i[k] - i[k])[inner], (src_j[k] - j[k])[inner]
        assert di.unique().numel() == 1 and dj.unique().numel() == 1
        dy, dx = int(di.flatten()[0]), int(dj.flatten()[0])
        # The border: what a replicate padding gives, the nearest edge pixel.
        rows = (torch.arange(SIDE) + dy).clamp(0, SIDE - 1)
        cols = (torch.arange(SIDE) + dx).clamp(0, SIDE - 1)
        assert torch.equal(out[k], imgs[k][:, rows][:, :, cols])
        shifts.append((dy, dx))
    assert len(set(shifts)) >= b // 2  # independent shifts across samples
    assert any(s != (0, 0) for s in shifts)


def test_random_shift_keeps_uint8_frames_and_pad_zero_is_the_identity():
    frames = random_obs(4, torch.Generator().manual_seed(1))[3]
    shifted = random_shift(frames, PAD, generator=torch.Generator().manual_seed(2))
    assert shifted.dtype == torch.uint8 and not torch.equal(shifted, frames)
    assert torch.equal(random_shift(frames, 0), frames)


def test_the_trainer_shifts_obs_and_next_obs_independently_and_the_actor_never(monkeypatch):
    calls = []

    def recording(imgs, pad, generator=None):
        out = random_shift(imgs, pad, generator)
        calls.append((imgs, out))
        return out

    monkeypatch.setattr(drq, "random_shift", recording)
    torch.manual_seed(0)
    a = agent()
    batch = list(random_batch(torch.Generator().manual_seed(3)))
    batch[3] = batch[0]  # the same frames as obs and next_obs
    a.train(tuple(batch))
    assert len(calls) == 2 and calls[0][0] is batch[0][3] and calls[1][0] is batch[3][3]
    assert not torch.equal(calls[0][1], calls[1][1])  # two draws, not one shift reused
    # Acting (worker and test episodes) reads the frames as they are.
    calls.clear()
    actor = a.get_actor()
    one = tuple(x[0] for x in batch[0])
    first = actor.act_(one, test=True)
    assert np.array_equal(first, actor.act_(one, test=True)) and calls == []
    with torch.no_grad():
        feats = a.model.encoder(batch[0][3][:1])
        others = torch.cat([x[:1].reshape(1, -1) for k, x in enumerate(batch[0]) if k != 3], dim=-1)
        expected = a.model.actor.head(feats, others, test=True, with_logprob=False)[0][0].numpy()
    assert np.allclose(first, expected, atol=1e-6)


# --- the encoder learns from the critic only -----------------------------------------------------


def test_the_encoder_gets_gradients_from_the_critic_loss_only():
    torch.manual_seed(0)
    a = agent()
    encoder = list(a.model.encoder.parameters())
    out = a.losses(random_batch(torch.Generator().manual_seed(4)))
    out["loss_actor"].backward(retain_graph=True)
    assert all(p.grad is None or not p.grad.any() for p in encoder)
    assert all(p.grad is not None and p.grad.any() for p in a.model.actor.mu_layer.parameters())
    assert all(p.grad is None for p in a.model.qs.parameters())  # the critics' weights held constant
    out["loss_critic"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in encoder)
    # The encoder is the critics' optimizer's to step, never the actor's.
    in_pi = {id(p) for g in a.pi_optimizer.param_groups for p in g["params"]}
    in_q = {id(p) for g in a.q_optimizer.param_groups for p in g["params"]}
    assert all(id(p) in in_q and id(p) not in in_pi for p in encoder)
    assert a.model.actor.encoder is a.model.encoder


# --- one update against a step written from the equations ----------------------------------------


def _encode(p: dict, imgs: torch.Tensor) -> torch.Tensor:
    x = F.relu(F.conv2d(imgs, p["encoder.convs.0.weight"], p["encoder.convs.0.bias"], stride=2))
    x = F.relu(F.conv2d(x, p["encoder.convs.2.weight"], p["encoder.convs.2.bias"], stride=1))
    x = F.linear(x.flatten(1), p["encoder.projection.weight"], p["encoder.projection.bias"])
    return torch.tanh(F.layer_norm(x, (x.shape[-1],), p["encoder.norm.weight"], p["encoder.norm.bias"]))


def _mlp(p: dict, prefix: str, x: torch.Tensor, layers: int) -> torch.Tensor:
    for k in range(layers):
        x = F.linear(x, p[f"{prefix}.{2 * k}.weight"], p[f"{prefix}.{2 * k}.bias"])
        if k < layers - 1:
            x = F.relu(x)
    return x


def _policy(p: dict, feats: torch.Tensor, others: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    h = F.relu(_mlp(p, "actor.net", torch.cat((feats, others), -1), 1))
    mu = F.linear(h, p["actor.mu_layer.weight"], p["actor.mu_layer.bias"])
    std = F.linear(h, p["actor.log_std_layer.weight"], p["actor.log_std_layer.bias"]).clamp(-20, 2).exp()
    u = mu + std * torch.randn(mu.shape)
    logp = torch.distributions.Normal(mu, std).log_prob(u).sum(-1) - torch.log(1 - torch.tanh(u) ** 2).sum(-1)
    return torch.tanh(u), logp


def _q(p: dict, prefix: str, feats: torch.Tensor, others: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
    x = torch.cat((feats, others, act), -1)
    return torch.stack([_mlp(p, f"{prefix}.{i}", x, 2).squeeze(-1) for i in range(2)])


def _shifted(frames: torch.Tensor) -> torch.Tensor:
    """The random shift as the papers describe it: replicate padding, then a crop per sample."""
    offsets = torch.randint(0, 2 * PAD + 1, (frames.shape[0], 2))
    padded = F.pad(frames.float() / 255.0, (PAD, PAD, PAD, PAD), mode="replicate")
    return torch.stack([padded[k, :, dy:dy + SIDE, dx:dx + SIDE] for k, (dy, dx) in enumerate(offsets.tolist())])


def _others(obs: tuple) -> torch.Tensor:
    return torch.cat([x.reshape(x.shape[0], -1) for k, x in enumerate(obs) if k != 3], -1)


def test_one_update_matches_a_step_written_from_the_equations():
    lr_a, lr_c, lr_e, gamma, polyak, alpha0 = 0.01, 0.02, 0.05, 0.9, 0.8, 0.3
    torch.manual_seed(0)
    a = agent(optimizer_actor="sgd", optimizer_critic="sgd", lr_actor=lr_a, lr_critic=lr_c, lr_entropy=lr_e,
              gamma=gamma, polyak=polyak, alpha=alpha0, target_entropy=-2.0)
    # Make the targets differ from the online networks, so that using one for the other shows.
    with torch.no_grad():
        for t in a.model_target.parameters():
            t.add_(0.05 * torch.randn_like(t))
    online = {k: v.detach().clone() for k, v in a.model.named_parameters()}
    target = {k: v.detach().clone() for k, v in a.model_target.named_parameters()}
    batch = random_batch(torch.Generator().manual_seed(5))
    o, act, r, o2, d, _ = batch
    torch.manual_seed(11)
    a.train(batch)

    torch.manual_seed(11)
    p = {k: v.clone().requires_grad_() for k, v in online.items()}
    x, x2 = _shifted(o[3]), _shifted(o2[3])  # obs first, then next_obs: two independent draws
    s, s2 = _others(o), _others(o2)
    feats = _encode(p, x)
    pi, logp = _policy(p, feats.detach(), s)  # the actor reads sg(f(aug(o)))
    with torch.no_grad():
        a2, logp2 = _policy(p, _encode(p, x2), s2)  # a' from the online encoder and actor
        q_targ = _q(target, "qs", _encode(target, x2), s2, a2).min(0).values
        y = r + gamma * (1 - d) * (q_targ - alpha0 * logp2)
    loss_q = (_q(p, "qs", feats, s, act) - y).square().mean()
    const = {k: v.detach() for k, v in p.items()}  # the critics' weights as constants in the actor's loss
    loss_pi = (alpha0 * logp - _q(const, "qs", feats.detach(), s, pi).min(0).values).mean()
    log_alpha = torch.tensor(float(np.log(alpha0)), dtype=torch.float32, requires_grad=True)
    loss_alpha = -(log_alpha * (logp.detach() - 2.0)).mean()
    names = list(p)
    grads = torch.autograd.grad(loss_q + loss_pi, [p[k] for k in names], allow_unused=True)
    (g_alpha,) = torch.autograd.grad(loss_alpha, [log_alpha])
    new = {}
    for k, g in zip(names, grads):
        lr = lr_a if k.startswith("actor.") and not k.startswith("actor.encoder.") else lr_c
        new[k] = online[k] - lr * (torch.zeros_like(online[k]) if g is None else g)
    # Adam's first step: m / (sqrt(v) + eps) with bias correction is g / (|g| + eps).
    alpha_new = log_alpha.detach() - lr_e * g_alpha / (g_alpha.abs() + 1e-8)

    got = dict(a.model.named_parameters())
    for k in names:
        torch.testing.assert_close(got[k].detach(), new[k], rtol=1e-4, atol=1e-6, msg=k)
    got_t = dict(a.model_target.named_parameters())
    for k in names:
        if k.startswith(("encoder.", "qs.")):  # the target encoder and critics, by the same factor
            torch.testing.assert_close(got_t[k], polyak * target[k] + (1 - polyak) * new[k], rtol=1e-4, atol=1e-6,
                                       msg=k)
    torch.testing.assert_close(a.log_alpha.detach(), alpha_new, rtol=1e-5, atol=1e-7)
    # The step moved the encoder (the critic's loss) and the actor's head.
    assert not torch.equal(got["encoder.projection.weight"].detach(), online["encoder.projection.weight"])
    assert not torch.equal(got["actor.mu_layer.weight"].detach(), online["actor.mu_layer.weight"])


# --- the workers' actor, checkpoints ------------------------------------------------------------


def test_a_worker_acts_from_the_broadcast_weights_alone(tmp_path):
    torch.manual_seed(0)
    a = agent()
    a.train(random_batch(torch.Generator().manual_seed(6)))
    path = tmp_path / "weights.tmod"
    a.get_actor().save(path)
    worker = DrQActor(obs_space(), ACT, **SIZES).load(path, "cpu")
    one = tuple(x[0] for x in random_obs(1, torch.Generator().manual_seed(7)))
    assert np.array_equal(worker.act_(one, test=True), a.get_actor().act_(one, test=True))
    trained = a.model.encoder.projection.weight
    assert torch.equal(worker.encoder.projection.weight, trained)


def test_checkpoint_round_trip_gives_the_same_parameters_and_next_update(tmp_path):
    from tmrl.checkpoint import load_checkpoint, save_checkpoint

    gen = torch.Generator().manual_seed(8)
    batches = [random_batch(gen) for _ in range(4)]
    torch.manual_seed(0)
    a = agent()
    for b in batches[:2]:
        a.train(b)

    class NoMemory(SimpleNamespace):  # a user memory holding nothing: only the agent matters here
        def __len__(self) -> int:
            return 0

    def training(ag: DrQAgent) -> SimpleNamespace:
        memory = NoMemory(data=[], stat_train_return=0.0, stat_test_return=0.0, stat_train_steps=0, stat_test_steps=0)
        return SimpleNamespace(agent=ag, memory=memory, epoch=1, total_updates=2, total_samples=0, run_epoch=None)

    save_checkpoint(training(a), tmp_path / "ckpt")
    torch.manual_seed(1)
    b = agent()
    actor_b = b.get_actor()
    load_checkpoint(tmp_path / "ckpt", training(b))
    for (name, x), y in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.equal(x, y), name
    for x, y in zip(a.model_target.state_dict().values(), b.model_target.state_dict().values()):
        assert torch.equal(x, y)
    assert b.model.actor.encoder is b.model.encoder  # still one encoder after loading
    assert torch.equal(actor_b.encoder.projection.weight, a.model.encoder.projection.weight)
    for batch in batches[2:]:
        torch.manual_seed(42)
        ma = a.train(batch)
        torch.manual_seed(42)
        mb = b.train(batch)
        assert {k: float(v) for k, v in ma.items()} == {k: float(v) for k, v in mb.items()}
    for x, y in zip(a.model.state_dict().values(), b.model.state_dict().values()):
        assert torch.equal(x, y)
    assert torch.equal(a.log_alpha, b.log_alpha)


def test_a_model_without_a_shared_encoder_or_frames_is_refused_in_one_line():
    from tmrl.driving.models import CNNActorCritic

    with pytest.raises(UserError, match="shared by the actor and the critics") as err:
        DrQAgent(obs_space(), ACT, "cpu", model_cls=partial(CNNActorCritic, channels=(4,), kernels=(3,),
                                                            strides=(2,), hidden_sizes=(8,)))
    assert "\n" not in str(err.value)
    flat = spaces.Box(-1.0, 1.0, (19,), np.float32)
    with pytest.raises(UserError, match='ALG.ALGORITHM "DRQ"') as err:
        DrQAgent(flat, ACT, "cpu")
    assert "\n" not in str(err.value)
    with pytest.raises(UserError, match="ALG.DRQ_IMAGE_PAD"):
        agent(image_pad=-1)


# --- the config ----------------------------------------------------------------------------------


@pytest.mark.parametrize("iface", ["SIMFULL", "TM20FULL"])
def test_alg_drq_on_an_image_interface_builds_the_drq_agent_and_its_pipeline(
    iface, fresh_objects,  # noqa: F811 (the imported fixture)
):
    from tmrl.driving.memories import RawImageMemory
    from tmrl.driving.preprocessors import preprocess_full_obs_uint8

    o = fresh_objects({"ENV": {"RTGYM_INTERFACE": iface}, "ALG": {"ALGORITHM": "DRQ", "DRQ_IMAGE_PAD": 3}})
    assert o.AGENT.func is DrQAgent and o.AGENT.keywords["model_cls"] is DrQActorCritic
    assert o.AGENT.keywords["image_pad"] == 3 and o.POLICY is DrQActor and o.TRAIN_MODEL is DrQActorCritic
    assert o.MEMORY.func is RawImageMemory and o.OBS_PREPROCESSOR is preprocess_full_obs_uint8
    built = o.AGENT(observation_space=spaces.Tuple(
        [spaces.Box(0, 1, (1,))] * 3 + [spaces.Box(0, 255, (4, 64, 64), np.uint8), ACT, ACT]), action_space=ACT,
        device="cpu")
    assert type(built) is DrQAgent and built.image_pad == 3
    # The frames reach the worker's actor and the memory's batches as uint8.
    raw = (np.float32(120.0), np.float32(3.0), np.float32(5000.0), np.full((4, 64, 64), 200, np.uint8),
           np.zeros(3, np.float32), np.zeros(3, np.float32))
    pre = o.OBS_PREPROCESSOR(raw)
    assert pre[3].dtype == np.uint8 and pre[3][0, 0, 0] == 200 and np.isclose(pre[0], 0.12)
    assert RawImageMemory.scale is None


@pytest.mark.parametrize("iface", ["SIMLIDAR", "TM20LIDARPROGRESS", "GYM"])
def test_alg_drq_without_images_is_refused_in_one_line_naming_the_key(
    iface, fresh_objects,  # noqa: F811 (the imported fixture)
):
    from tmrl.config.loader import ConfigError

    with pytest.raises(ConfigError, match='ALG.ALGORITHM "DRQ"') as err:
        fresh_objects({"ENV": {"RTGYM_INTERFACE": iface}, "ALG": {"ALGORITHM": "DRQ"}})
    assert "\n" not in str(err.value) and "SIMFULL" in str(err.value)


def test_simfull_samples_reach_the_agent_as_uint8_and_the_worker_loads_its_actor(
    fresh_objects, tmp_path, monkeypatch,  # noqa: F811 (the imported fixture)
):
    from tmrl.networking import RolloutWorker, pack_buffer, unpack_buffer

    torch.manual_seed(0)
    o = fresh_objects({**SIM_SMALL, "ENV": {"RTGYM_INTERFACE": "SIMFULL", "IMG_HIST_LEN": 2, "IMG_WIDTH": 32,
                                            "IMG_HEIGHT": 32, "RTGYM_CONFIG": {"ep_max_length": 30}},
                       "ALG": {"ALGORITHM": "DRQ"}})
    env = o.ENV_CLS()
    obs, _ = env.reset()
    worker = RolloutWorker(env_cls=o.ENV_CLS, actor_module_cls=o.POLICY, sample_compressor=o.SAMPLE_COMPRESSOR,
                           obs_preprocessor=o.OBS_PREPROCESSOR, standalone=True, model_path=str(tmp_path / "w.tmod"),
                           model_history=0)
    try:
        worker.collect_train_episode()
        worker.collect_train_episode()
        buffer = unpack_buffer(pack_buffer(worker.buffer, worker.source_id, 0))  # the network's format
        training = o.TRAINER(sleep_between_buffer_retrieval_attempts=0.0)
        training.max_wait_s = 60.0
        agent = training.agent
        assert type(agent) is DrQAgent
        seen = []
        train = agent.train
        monkeypatch.setattr(agent, "train", lambda batch: seen.append(batch[0][3].dtype) or train(batch))
        interface = FakeInterface(buffer)
        stats = training.run_epoch(interface)
        assert training.total_updates == 5 and np.isfinite(stats[-1]["loss_critic"]) and agent.skipped_updates == 0
        assert seen and set(seen) == {torch.uint8}  # the memory's batches keep the frames as bytes
        worker.actor.load_state_dict(interface.broadcasts[-1])  # encoder included
        assert torch.equal(worker.actor.encoder.projection.weight, agent.model.encoder.projection.weight)
        assert worker.env.action_space.contains(np.asarray(worker.act(o.OBS_PREPROCESSOR(obs)), np.float32))
    finally:
        worker.close()
        env.close()
