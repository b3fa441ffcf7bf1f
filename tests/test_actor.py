"""tmrl.actor: the worker-facing policy interface, its collation and its weights files."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch
from gymnasium import spaces

from tmrl.actor import ActorModule, TorchActorModule, WeightsError, collate_one
from tmrl.errors import UserError
from tmrl.models import SquashedGaussianMLPActor

OBS_SPACE = spaces.Tuple(
    (
        spaces.Box(-1.0, 1.0, (1,), np.float32),
        spaces.Box(-1.0, 1.0, (1,), np.float32),
        spaces.Box(-0.5, 0.5, (2,), np.float32),
    )
)
ACT_SPACE = spaces.Box(-2.0, 2.0, (2,), np.float32)


def _obs(seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    return tuple(rng.uniform(-0.5, 0.5, s.shape).astype(np.float32) for s in OBS_SPACE)


class _TutorialJSONActor(TorchActorModule):
    """Shaped like the tmrl tutorial's actor: a squashed Gaussian MLP with JSON save/load."""

    def __init__(self, observation_space, action_space, hidden_sizes=(32, 32)):
        super().__init__(observation_space, action_space)
        dim_obs = sum(int(np.prod(s.shape)) for s in observation_space)
        dim_act = action_space.shape[0]
        layers: list[torch.nn.Module] = []
        for a, b in zip([dim_obs, *hidden_sizes[:-1]], hidden_sizes):
            layers += [torch.nn.Linear(a, b), torch.nn.ReLU()]
        self.net = torch.nn.Sequential(*layers)
        self.mu_layer = torch.nn.Linear(hidden_sizes[-1], dim_act)
        self.log_std_layer = torch.nn.Linear(hidden_sizes[-1], dim_act)
        self.act_limit = float(action_space.high[0])

    def save(self, path):
        with open(path, "w") as f:
            json.dump({k: v.cpu().tolist() for k, v in self.state_dict().items()}, f)

    def load(self, path, device):
        self.device = device
        with open(path) as f:
            state = {k: torch.tensor(v) for k, v in json.load(f).items()}
        self.load_state_dict(state)
        self.to_device(device)
        return self

    def forward(self, obs, test=False, with_logprob=True):
        h = self.net(torch.cat(obs, -1))
        mu = self.mu_layer(h)
        std = torch.exp(torch.clamp(self.log_std_layer(h), -20, 2))
        u = mu if test else torch.distributions.Normal(mu, std).rsample()
        return self.act_limit * torch.tanh(u), None

    def act(self, obs, test=False):
        a, _ = self.forward(obs, test, False)
        return a.squeeze().cpu().numpy()


def test_actor_module_is_abstract_and_refuses_to_pickle(tmp_path):
    with pytest.raises(TypeError):
        ActorModule(OBS_SPACE, ACT_SPACE)  # type: ignore[abstract]

    class Constant(ActorModule):
        def act(self, obs, test=False):
            return np.zeros(2, np.float32)

    actor = Constant(OBS_SPACE, ACT_SPACE)
    assert actor.observation_space is OBS_SPACE and actor.action_space is ACT_SPACE
    np.testing.assert_array_equal(actor.act_(_obs()), np.zeros(2))
    assert actor.to_device("cpu") is actor
    with pytest.raises(UserError, match="data-only"):
        actor.save(tmp_path / "w")
    assert not (tmp_path / "w").exists()


def test_collate_one_adds_a_batch_dimension_to_every_leaf():
    obs = (np.zeros((2, 3), np.float32), {"speed": np.float32(1.5), "gear": 3}, [np.ones(4, np.uint8)])
    out = collate_one(obs)
    assert isinstance(out, tuple) and isinstance(out[1], dict) and isinstance(out[2], list)
    assert out[0].shape == (1, 2, 3) and out[0].dtype == torch.float32
    assert out[1]["speed"].shape == (1,) and float(out[1]["speed"][0]) == 1.5
    assert out[1]["gear"].shape == (1,) and int(out[1]["gear"][0]) == 3
    assert out[2][0].shape == (1, 4) and out[2][0].dtype == torch.uint8
    with pytest.raises(UserError, match="obs_preprocessor"):
        collate_one(("text",))


def test_act_returns_numpy_in_bounds_without_building_a_graph():
    actor = SquashedGaussianMLPActor(OBS_SPACE, ACT_SPACE, hidden_sizes=(16, 16))
    seen = {}
    original_act = actor.act

    def spy(obs, test=False):
        seen["grad_enabled"] = torch.is_grad_enabled()
        seen["batch"] = obs[0].shape[0]
        return original_act(obs, test)

    actor.act = spy  # type: ignore[method-assign]
    a = actor.act_(_obs(), test=False)
    assert isinstance(a, np.ndarray) and a.shape == (2,) and a.dtype == np.float32
    assert np.all(np.abs(a) <= 2.0)
    assert seen == {"grad_enabled": False, "batch": 1}
    det1, det2 = actor.act_(_obs(), test=True), actor.act_(_obs(), test=True)
    np.testing.assert_array_equal(det1, det2)


def test_safetensors_round_trip_into_a_fresh_actor(tmp_path):
    torch.manual_seed(1)
    a = SquashedGaussianMLPActor(OBS_SPACE, ACT_SPACE, hidden_sizes=(16, 16))
    torch.manual_seed(2)
    b = SquashedGaussianMLPActor(OBS_SPACE, ACT_SPACE, hidden_sizes=(16, 16))
    assert not np.array_equal(a.act_(_obs(), test=True), b.act_(_obs(), test=True))
    path = tmp_path / "weights" / "actor.tmod"
    a.save(path)
    # Data-only: a safetensors file starts with a little-endian header length then JSON.
    raw = path.read_bytes()
    header_len = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8 : 8 + header_len])
    assert set(header) - {"__metadata__"} == set(a.state_dict())
    assert os.listdir(path.parent) == ["actor.tmod"]  # atomic write leaves no temporary file
    assert b.load(path, "cpu") is b
    assert b.device == torch.device("cpu")
    np.testing.assert_array_equal(a.act_(_obs(), test=True), b.act_(_obs(), test=True))


def test_load_refuses_garbage_and_other_models(tmp_path):
    actor = SquashedGaussianMLPActor(OBS_SPACE, ACT_SPACE, hidden_sizes=(16, 16))
    bad = tmp_path / "bad.tmod"
    bad.write_bytes(b"\x80\x04not safetensors at all")
    with pytest.raises(WeightsError, match="not a tmrl safetensors file") as err:
        actor.load(bad, "cpu")
    assert "\n" not in str(err.value)
    other = SquashedGaussianMLPActor(OBS_SPACE, ACT_SPACE, hidden_sizes=(8, 8))
    other.save(tmp_path / "other.tmod")
    with pytest.raises(WeightsError, match="same model configuration") as err:
        actor.load(tmp_path / "other.tmod", "cpu")
    assert "\n" not in str(err.value)
    assert isinstance(err.value, UserError)


def test_to_tracks_the_device():
    actor = SquashedGaussianMLPActor(OBS_SPACE, ACT_SPACE, hidden_sizes=(8, 8))
    assert actor.to(torch.float32) is actor and actor.device == "cpu"  # dtype only: unchanged
    assert actor.to("cpu").device == torch.device("cpu")
    assert actor.to_device(torch.device("cpu")) is actor


def test_the_device_follows_a_move_of_the_module_that_holds_the_actor():
    """An agent moves its actor-critic, not the actor: torch never calls the actor's ``to`` then.
    The "meta" device stands in for a GPU on a CPU-only machine (any device but the CPU will do)."""
    actor = SquashedGaussianMLPActor(OBS_SPACE, ACT_SPACE, hidden_sizes=(8, 8))
    holder = torch.nn.ModuleDict({"actor": actor})
    holder.to("meta")
    assert next(actor.parameters()).device.type == "meta" and actor.device == torch.device("meta")
    holder.to_empty(device="cpu")
    assert actor.device == torch.device("cpu")
    holder.float()
    assert actor.device == torch.device("cpu")


def test_tutorial_style_json_actor_works_unchanged(tmp_path):
    torch.manual_seed(3)
    trained = _TutorialJSONActor(OBS_SPACE, ACT_SPACE)
    torch.manual_seed(4)
    worker_side = _TutorialJSONActor(OBS_SPACE, ACT_SPACE)
    a = trained.act_(_obs(5), test=True)
    assert a.shape == (2,) and np.all(np.abs(a) <= 2.0)
    # The trainer saves, the bytes travel, the worker writes them and loads.
    trained.save(tmp_path / "t.json")
    data = (tmp_path / "t.json").read_bytes()
    json.loads(data)
    (tmp_path / "w.json").write_bytes(data)
    loaded = worker_side.load(tmp_path / "w.json", "cpu")
    assert loaded is worker_side
    np.testing.assert_allclose(loaded.act_(_obs(5), test=True), a, rtol=1e-6)
