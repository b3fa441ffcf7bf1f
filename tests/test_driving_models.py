"""Tests of tmrl.driving.models: the CNN actor-critic on full-observation batches (shapes from
the space, sizes from arguments, a SAC update, weights round trip), the lidar MLP wiring, and the
lidar models of DroQ, TQC and CrossQ (scaling, selection through the config, training on simulator
samples, the workers loading their actor)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from gymnasium import spaces
from test_config_objects import SMALL as SIM_SMALL
from test_config_objects import FakeInterface, fresh_objects  # noqa: F401 (fresh_objects: a fixture)

from tmrl.driving.models import CNNActorCritic, ImageEncoder, REDQCNNActorCritic, lidar_actor_critic
from tmrl.errors import UserError

ACT = spaces.Box(-1.0, 1.0, (3,), dtype=np.float32)


def full_space(hist: int = 4, h: int = 64, w: int = 64, act_buf_len: int = 2) -> spaces.Tuple:
    return spaces.Tuple([
        spaces.Box(0, 1, (1,)), spaces.Box(0, 1, (1,)), spaces.Box(0, 1, (1,)),
        spaces.Box(0, 1, (hist, h, w)),
        *[ACT] * act_buf_len,
    ])


def batch_obs(b: int, hist: int = 4, h: int = 64, w: int = 64) -> tuple:
    g = torch.Generator().manual_seed(0)
    return (torch.rand(b, 1, generator=g), torch.rand(b, 1, generator=g), torch.rand(b, 1, generator=g),
            torch.rand(b, hist, h, w, generator=g), torch.rand(b, 3, generator=g), torch.rand(b, 3, generator=g))


def test_shapes_and_bounds():
    model = CNNActorCritic(full_space(), ACT)
    obs = batch_obs(5)
    a, logp = model.actor(obs)
    assert a.shape == (5, 3) and logp.shape == (5,)
    assert torch.all(a.abs() <= 1.0)
    assert model.q1(obs, a).shape == (5,) and len(model.qs) == 2
    assert model.actor.encoder.out_dim == 128  # 64 -> 29 -> 13 -> 5 -> 1 pixels, as the original
    one = tuple(o[:1] for o in obs)
    assert model.act(one, test=True).shape == (3,)
    assert len(REDQCNNActorCritic(full_space(), ACT).qs) == 10


def test_sizes_come_from_the_space_and_arguments():
    model = CNNActorCritic(full_space(hist=2, h=32, w=48, act_buf_len=1), ACT,
                           channels=(8, 16), kernels=(4, 3), strides=(2, 2), hidden_sizes=(32,))
    assert model.actor.encoder.convs[0].in_channels == 2
    assert model.actor.encoder.out_dim == 16 * 7 * 11
    g = torch.Generator().manual_seed(1)
    obs = (torch.rand(3, 1), torch.rand(3, 1), torch.rand(3, 1), torch.rand(3, 2, 32, 48, generator=g), torch.rand(3, 3))
    assert model.actor(obs)[0].shape == (3, 3)
    # uint8 frames are scaled like the preprocessor does
    raw = obs[:3] + ((obs[3] * 256).to(torch.uint8),) + obs[4:]
    scaled = obs[:3] + ((obs[3] * 256).to(torch.uint8).float() / 256,) + obs[4:]
    assert torch.allclose(model.actor(raw, test=True)[0], model.actor(scaled, test=True)[0])
    with pytest.raises(UserError, match="too small"):
        ImageEncoder((4, 16, 16))
    with pytest.raises(UserError, match="IMG_GRAYSCALE"):
        CNNActorCritic(spaces.Tuple([spaces.Box(0, 1, (1,))] * 3 + [spaces.Box(0, 1, (4, 64, 64, 3))]), ACT)


@pytest.mark.parametrize("n", [3, ImageEncoder.CHANNELS_LAST_FROM])
def test_encoder_features_and_gradients_match_a_plain_nchw_convolution_stack(n):
    # Large batches run channels-last, all with in-place ReLUs; the features must still come out
    # in the NCHW order of the original (weights trained before stay valid), gradients the same.
    enc = ImageEncoder((2, 32, 48), channels=(8, 16), kernels=(4, 3), strides=(2, 2))
    seen = []
    enc.convs[0].register_forward_pre_hook(
        lambda _, args: seen.append(args[0].is_contiguous(memory_format=torch.channels_last)))
    imgs = torch.rand(n, 2, 32, 48, generator=torch.Generator().manual_seed(2))
    convs = [m for m in enc.convs if isinstance(m, torch.nn.Conv2d)]
    weights = [(c.weight.detach().contiguous().requires_grad_(), c.bias.detach().clone().requires_grad_()) for c in convs]
    x = imgs
    for (w, b), conv in zip(weights, convs):
        x = torch.nn.functional.conv2d(x, w, b, stride=conv.stride).relu()
    reference = x.reshape(n, -1)
    features = enc(imgs)
    assert seen == [n >= ImageEncoder.CHANNELS_LAST_FROM]
    assert features.shape == (n, 16 * 7 * 11) and features.is_contiguous()
    assert torch.allclose(features, reference, atol=1e-5)
    probe = torch.rand(features.shape, generator=torch.Generator().manual_seed(3))
    (features * probe).sum().backward()
    (reference * probe).sum().backward()
    for (w, b), conv in zip(weights, convs):
        assert torch.allclose(conv.weight.grad, w.grad, atol=1e-4)
        assert torch.allclose(conv.bias.grad, b.grad, atol=1e-4)


def test_one_sac_update_on_memory_batches_and_weights_round_trip(tmp_path):
    from tmrl.algorithms.sac import SACAgent
    from tmrl.driving.memories import ImageMemory

    mem = ImageMemory(hist_len=2, act_buf_len=1, memory_size=64, batch_size=8)
    samples = []
    for step in range(20):
        img = np.full((32, 32), step * 5, dtype=np.uint8)
        act = np.zeros(3, np.float32) if step == 0 else np.full(3, 0.1, np.float32)
        samples.append((act, (np.float32([0.1]), np.float32([0.2]), np.float32([0.3]), img), 1.0, False, step == 19, {}))
    mem.append_buffer(SimpleNamespace(memory=samples, sources=None))
    space = full_space(hist=2, h=32, w=32, act_buf_len=1)
    small = {"channels": (8, 8), "kernels": (4, 4), "strides": (2, 2), "hidden_sizes": (32,)}
    agent = SACAgent(space, ACT, device="cpu",
                     model_cls=lambda o, a, n=2: CNNActorCritic(o, a, n=n, **small))
    before = [p.detach().clone() for p in agent.model.parameters()]
    stats = agent.train(mem.sample())
    assert np.isfinite(float(stats["loss_critic"])) and np.isfinite(float(stats["loss_actor"]))
    assert any(not torch.equal(p0, p1) for p0, p1 in zip(before, agent.model.parameters()))
    actor = agent.get_actor()
    path = tmp_path / "w.safetensors"
    actor.save(path)
    other = CNNActorCritic(space, ACT, **small).actor
    other.load(path, "cpu")
    obs = tuple(torch.as_tensor(x) for x in mem.sample()[0])
    assert torch.allclose(other(obs, test=True)[0], actor(obs, test=True)[0])


def test_lidar_wiring_scales_speed_and_lidar_only():
    from tmrl.driving.models import lidar_obs_scales
    from tmrl.models import MLPActorCritic

    space = spaces.Tuple([spaces.Box(0, 1000, (1,)), spaces.Box(0, 1, (1,)), spaces.Box(0, np.inf, (76,)), ACT, ACT])
    assert lidar_obs_scales(space) == (0.01, 1.0, 0.01, 1.0, 1.0)
    model = lidar_actor_critic(space, ACT, hidden_sizes=(64, 64))
    obs = (torch.rand(4, 1) * 300, torch.rand(4, 1), torch.rand(4, 76) * 400, torch.rand(4, 3), torch.rand(4, 3))
    a, _ = model.actor(obs, test=True)
    assert a.shape == (4, 3)
    # same weights without the scaling, fed pre-scaled inputs: same actions and Q values
    plain = MLPActorCritic(space, ACT, hidden_sizes=(64, 64))
    plain.load_state_dict(model.state_dict())
    pre = (obs[0] * 0.01, obs[1], obs[2] * 0.01, obs[3], obs[4])
    assert torch.allclose(plain.actor(pre, test=True)[0], a, atol=1e-6)
    assert torch.allclose(plain.qs(pre, a), model.qs(obs, a), atol=1e-5)
    assert lidar_actor_critic(space, ACT, n=10).n == 10


@pytest.mark.parametrize("algo", ["sac", "redq"])
def test_critics_read_the_images_once_for_both_losses_with_the_same_result(algo):
    # Q(o, a) and Q(o, pi) share the critics' convolution pass over o; the update must be the
    # one computed with two passes (the generic path), and the encoders run fewer times.
    from tmrl.algorithms.redq import REDQSACAgent
    from tmrl.algorithms.sac import SACAgent

    space = full_space(hist=2, h=32, w=32, act_buf_len=1)
    small = {"channels": (8, 8), "kernels": (4, 4), "strides": (2, 2), "hidden_sizes": (32,)}
    g = torch.Generator().manual_seed(4)
    b = 16
    obs = (torch.rand(b, 1, generator=g), torch.rand(b, 1, generator=g), torch.rand(b, 1, generator=g),
           torch.rand(b, 2, 32, 32, generator=g), torch.rand(b, 3, generator=g) * 2 - 1)
    obs2 = tuple(o.roll(1, 0) for o in obs)
    batch = (obs, torch.rand(b, 3, generator=g) * 2 - 1, torch.rand(b, generator=g), obs2,
             (torch.rand(b, generator=g) < 0.2).float(), torch.zeros(b))

    def run(shared: bool):
        torch.manual_seed(0)
        if algo == "sac":
            agent = SACAgent(space, ACT, device="cpu", model_cls=lambda o, a, n=2: CNNActorCritic(o, a, n=n, **small))
        else:
            agent = REDQSACAgent(space, ACT, device="cpu", n=4, m=2, q_updates_per_policy_update=2,
                                 model_cls=lambda o, a, n=4: CNNActorCritic(o, a, n=n, **small))
        assert agent.critics._split
        agent.critics._split = shared
        calls = []
        for module in agent.model.modules():
            if isinstance(module, ImageEncoder):
                module.register_forward_hook(lambda *_: calls.append(1))
        stats = [agent.train(batch) for _ in range(3)]
        return [p.detach().clone() for p in agent.model.parameters()], stats, len(calls)

    params_shared, stats_shared, calls_shared = run(True)
    params_generic, stats_generic, calls_generic = run(False)
    n = 2 if algo == "sac" else 4
    policy_updates = 3 if algo == "sac" else 1  # REDQ: a policy update every 2nd critic update
    assert calls_generic - calls_shared == n * policy_updates
    for p1, p2 in zip(params_shared, params_generic):
        assert torch.allclose(p1, p2, atol=1e-6)
    for s1, s2 in zip(stats_shared, stats_generic):
        assert torch.allclose(s1["loss_actor"], s2["loss_actor"]) and torch.allclose(s1["loss_critic"], s2["loss_critic"])


# --- the lidar models of DroQ, TQC and CrossQ ---------------------------------------------------

LIDAR_ALGOS = ["DROQ", "TQC", "CROSSQ"]
SMALL_MODELS = {"DROQ": {}, "TQC": {"n": 2, "n_quantiles": 5, "critic_hidden_sizes": (32, 32)},
                "CROSSQ": {"critic_hidden_sizes": (32, 32)}}


def lidar_space() -> spaces.Tuple:
    return spaces.Tuple([spaces.Box(0, 1000, (1,)), spaces.Box(0, 1, (1,)), spaces.Box(0, np.inf, (76,)), ACT, ACT])


@pytest.mark.parametrize("algo", LIDAR_ALGOS)
def test_lidar_models_scale_like_the_lidar_actor_critic_and_share_the_workers_actor(algo):
    from tmrl.algorithms.crossq import CrossQActorCritic
    from tmrl.algorithms.droq import DroQMLPActorCritic
    from tmrl.algorithms.tqc import TQCActorCritic
    from tmrl.config import schema
    from tmrl.driving.models import LIDAR_MODELS, LidarActor, LidarActorCritic, lidar_model_cls

    # Every algorithm has a lidar model but DrQ, which learns from images only.
    assert set(LIDAR_MODELS) == set(schema.ALGORITHMS) - {"DRQ"} and LIDAR_MODELS["REDQSAC"] is LidarActorCritic
    assert lidar_model_cls(algo.lower()) is LIDAR_MODELS[algo]
    torch.manual_seed(0)
    space = lidar_space()
    model = lidar_model_cls(algo)(space, ACT, hidden_sizes=(32, 32), **SMALL_MODELS[algo])
    assert type(model.actor) is LidarActor
    plain_extra = {"critic_input_norm": False} if algo == "CROSSQ" else {}  # the lidar model's (below)
    plain = {"DROQ": DroQMLPActorCritic, "TQC": TQCActorCritic, "CROSSQ": CrossQActorCritic}[algo](
        space, ACT, hidden_sizes=(32, 32), **SMALL_MODELS[algo], **plain_extra)
    # the same weights without the scaling, fed pre-scaled inputs: same actions and Q values
    plain.load_state_dict({k.replace(".critic.", "."): v for k, v in model.state_dict().items()})
    model.eval()  # no dropout, running statistics: deterministic critics
    plain.eval()
    obs = (torch.rand(4, 1) * 300, torch.rand(4, 1), torch.rand(4, 76) * 400, torch.rand(4, 3), torch.rand(4, 3))
    pre = (obs[0] * 0.01, obs[1], obs[2] * 0.01, obs[3], obs[4])
    a, _ = model.actor(obs, test=True)
    assert torch.allclose(plain.actor(pre, test=True)[0], a, atol=1e-6)
    for q, q_plain in zip(model.qs, plain.qs):
        assert torch.allclose(q(obs, a), q_plain(pre, a), atol=1e-5)
    # The workers' policy class loads the trained actor's weights.
    worker_actor = LidarActor(space, ACT, hidden_sizes=(32, 32))
    worker_actor.load_state_dict(model.actor.state_dict())
    assert torch.allclose(worker_actor(obs, test=True)[0], a)
    with pytest.raises(UserError, match="no lidar model"):
        lidar_model_cls("PPO")


def test_the_lidar_crossq_critics_have_no_input_normalisation_layer():
    """The lidar scaling already puts CrossQ's critic inputs on a common scale; a normalisation
    layer there would standardise each of the 76 lidar features and leave the action 3 of 83
    inputs of equal weight. The generic critic keeps the paper's input layer. (The layer's effect
    on learning is measured in docs/benchmarks.md, not here.)"""
    from tmrl.algorithms.crossq import BatchRenorm1d, CrossQActorCritic
    from tmrl.driving.models import LidarCrossQActorCritic

    space = lidar_space()
    lidar = LidarCrossQActorCritic(space, ACT, hidden_sizes=(32, 32), critic_hidden_sizes=(32, 32))
    generic = CrossQActorCritic(space, ACT, hidden_sizes=(32, 32), critic_hidden_sizes=(32, 32))
    for q in lidar.qs:
        assert isinstance(q.critic.net[0], torch.nn.Identity)
        assert sum(isinstance(m, BatchRenorm1d) for m in q.modules()) == 2  # after each hidden layer
    for q in generic.qs:
        assert isinstance(q.net[0], BatchRenorm1d) and sum(isinstance(m, BatchRenorm1d) for m in q.modules()) == 3


def _lidar_alg_settings(algo: str) -> dict:
    return {"DROQ": {"DROQ_Q_UPDATES_PER_POLICY_UPDATE": 2},
            "TQC": {"TQC_N": 2, "TQC_QUANTILES": 5, "TQC_DROP_PER_CRITIC": 1},
            "CROSSQ": {"CROSSQ_POLICY_DELAY": 2, "CROSSQ_CRITIC_WIDTH": 64, "CROSSQ_RENORM_WARMUP_STEPS": 2}}[algo]


@pytest.mark.parametrize("algo, iface", [("DROQ", "SIMLIDAR"), ("TQC", "SIMLIDAR"), ("CROSSQ", "SIMLIDAR"),
                                         ("CROSSQ", "SIMLIDARPROGRESS")])
def test_agents_train_on_simulator_lidar_samples_and_workers_load_their_actor(
    algo, iface, fresh_objects, tmp_path,  # noqa: F811 (the imported fixture)
):
    from tmrl.algorithms import agent_class
    from tmrl.driving.models import LIDAR_MODELS, LidarActor
    from tmrl.networking import RolloutWorker, pack_buffer, unpack_buffer

    torch.manual_seed(0)
    o = fresh_objects({**SIM_SMALL, "ENV": {"RTGYM_INTERFACE": iface, "RTGYM_CONFIG": {"ep_max_length": 30}},
                       "ALG": {"ALGORITHM": algo, **_lidar_alg_settings(algo)}})
    assert o.TRAIN_MODEL is LIDAR_MODELS[algo] and o.POLICY is LidarActor
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
        assert type(agent) is agent_class(algo) and type(agent.model) is LIDAR_MODELS[algo]
        interface = FakeInterface(buffer)
        before = {k: v.clone() for k, v in agent.get_actor().state_dict().items()}
        stats = training.run_epoch(interface)
        assert training.total_updates == 5 and np.isfinite(stats[-1]["loss_critic"])
        assert agent.skipped_updates == 0
        # The memory's batches are what the agent trained on: the actor moved, the worker loads it.
        assert any(not torch.equal(before[k], v) for k, v in interface.broadcasts[-1].items())
        worker.actor.load_state_dict(interface.broadcasts[-1])
        assert worker.env.action_space.contains(np.asarray(worker.act(o.OBS_PREPROCESSOR(obs)), np.float32))
    finally:
        worker.close()
        env.close()


@pytest.mark.parametrize("algo", LIDAR_ALGOS)
@pytest.mark.parametrize("iface", ["TM20LIDAR", "TM20LIDARPROGRESS"])
def test_trackmania_lidar_interfaces_pick_the_algorithms_lidar_model(
    algo, iface, fresh_objects,  # noqa: F811 (the imported fixture)
):
    from tmrl.driving.models import LIDAR_MODELS, LidarActor

    o = fresh_objects({"ENV": {"RTGYM_INTERFACE": iface}, "ALG": {"ALGORITHM": algo}})
    assert o.TRAIN_MODEL is LIDAR_MODELS[algo] and o.POLICY is LidarActor and o.AGENT.keywords["model_cls"] is \
        LIDAR_MODELS[algo]


@pytest.mark.parametrize("algo", LIDAR_ALGOS)
@pytest.mark.parametrize("iface", ["SIMFULL", "TM20FULL"])
def test_image_interfaces_refuse_the_mlp_only_algorithms_in_one_line(
    algo, iface, fresh_objects,  # noqa: F811 (the imported fixture)
):
    from tmrl.config.loader import ConfigError

    with pytest.raises(ConfigError, match=f"ALG.ALGORITHM {algo} has no image model") as err:
        fresh_objects({"ENV": {"RTGYM_INTERFACE": iface}, "ALG": {"ALGORITHM": algo}})
    assert "\n" not in str(err.value) and "SIMLIDAR" in str(err.value)
