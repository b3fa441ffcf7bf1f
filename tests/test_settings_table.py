"""The settings table (tmrl/config/schema.py): every key that sets a constructor argument says
which, and the classes, the algorithm and optimizer lists, the roles' settings and the built
objects agree with it."""

from __future__ import annotations

import inspect
import json
import os
import subprocess
import sys

import pytest

from tmrl.algorithms import ALGORITHMS, BROAgent, SimbaV2Agent, CrossQAgent, DroQAgent, DrQAgent, REDQSACAgent, SACAgent, TQCAgent
from tmrl.algorithms.sac import _OPTIMIZERS
from tmrl.config import schema
from tmrl.config.settings import NetSettings
from tmrl.errors import UserError
from tmrl.memory import GenericTorchMemory
from tmrl.networking import Buffer, RolloutWorker, Server, Trainer
from tmrl.training_offline import TorchTrainingOffline

CLASSES = {
    cls.__name__: cls
    for cls in (SACAgent, REDQSACAgent, DroQAgent, TQCAgent, CrossQAgent, DrQAgent, BROAgent, SimbaV2Agent, TorchTrainingOffline,
                GenericTorchMemory, Server, Trainer, RolloutWorker, Buffer)
}


def _parameters(cls: type) -> dict[str, inspect.Parameter]:
    if cls is TorchTrainingOffline:  # a dataclass: its fields are its arguments
        return dict(inspect.signature(cls).parameters)
    return dict(inspect.signature(cls.__init__).parameters)


def test_every_fed_argument_exists_and_its_class_default_is_the_tables():
    table = schema.fed_arguments()
    assert set(table) == set(CLASSES), "a class named in feeds is not checked here (add it to CLASSES)"
    for cls_name, args in table.items():
        params = _parameters(CLASSES[cls_name])
        for arg, (key, class_default) in args.items():
            assert arg in params, f"{key} feeds {cls_name}.{arg}, which {cls_name} does not take"
            if class_default is not schema.NO_CLASS_DEFAULT:
                assert params[arg].default == class_default, (
                    f"{cls_name}({arg}=...) defaults to {params[arg].default!r}, the table says {class_default!r}"
                )


def test_every_hyperparameter_of_the_agents_is_in_the_table():
    """An agent argument the config cannot set is a setting missing from the table."""
    not_settings = {"self", "observation_space", "action_space", "device", "model_cls", "fused"}
    for cls in (SACAgent, REDQSACAgent, DroQAgent, TQCAgent, DrQAgent, BROAgent, SimbaV2Agent):
        fed = set(schema.fed_arguments()[cls.__name__])
        assert set(_parameters(cls)) - not_settings == fed


def test_algorithm_optimizer_and_update_order_lists_come_from_the_table():
    assert tuple(ALGORITHMS) == schema.ALGORITHMS
    assert {name: cls.__name__ for name, cls in ALGORITHMS.items()} == schema.AGENT_CLASSES
    assert tuple(_OPTIMIZERS) == schema.OPTIMIZERS
    assert schema.SCHEMA.fields["ALG"].fields["UPDATE_ORDER"].options == schema.UPDATE_ORDERS
    for order in schema.UPDATE_ORDERS:
        SACAgent(_box(3), _box(2), "cpu", update_order=order)


def _box(n: int):
    import gymnasium
    import numpy as np

    return gymnasium.spaces.Box(-1.0, 1.0, (n,), np.float32)


def test_arguments_collects_the_keys_that_feed_a_class():
    cfg = schema.defaults()
    cfg["ALG"]["LR_ACTOR"] = 0.123
    cfg["ALG"]["REDQ_N"] = 7
    cfg["BATCH_SIZE"] = 33
    sac = schema.arguments(cfg, "SACAgent")
    assert sac["lr_actor"] == 0.123 and "n" not in sac and sac["update_order"] == "simultaneous"
    redq = schema.arguments(cfg, "REDQSACAgent")
    assert redq["n"] == 7 and "update_order" not in redq
    assert schema.arguments(cfg, "GenericTorchMemory") == {"memory_size": cfg["MEMORY_SIZE"], "batch_size": 33,
                                                           "on_device": "auto"}
    assert schema.arguments(cfg, "NoSuchClass") == {}


def test_the_redq_subset_rule_is_written_once_and_says_the_same_in_both_places():
    problem = schema.redq_subset_problem(2, 3)
    assert problem == "ALG.REDQ_M must be at most ALG.REDQ_N (2), got 3"
    assert schema.redq_subset_problem(3, 3) is None and schema.redq_subset_problem(3, 0) is not None
    with pytest.raises(UserError) as err:
        REDQSACAgent(_box(3), _box(2), "cpu", n=2, m=3)
    assert problem in str(err.value)


def test_net_settings_derive_the_roles_values_from_a_config(tmp_path):
    cfg = schema.defaults()
    cfg.update(PORT=4242, TLS=True, NB_WORKERS=-1, LOCALHOST_WORKER=False, PUBLIC_IP_SERVER="10.0.0.9",
               RUN_NAME="myrun", HEADER_SIZE=12)
    s = NetSettings.from_config(cfg, tmp_path)
    assert (s.port, s.security, s.max_workers) == (4242, "TLS", None)
    assert (s.server_ip_for_worker, s.server_ip_for_trainer) == ("10.0.0.9", "127.0.0.1")
    assert s.model_path_worker == tmp_path / "weights" / "myrun.tmod"
    assert s.checkpoint_path == tmp_path / "checkpoints" / "myrun_t.tcpt"
    assert s.credentials_directory == tmp_path / "credentials"
    assert s.header_size == 12 and s.link_options()["max_frame_bytes"] == cfg["MAX_FRAME_BYTES"]


def test_config_constants_and_a_role_built_without_arguments_read_the_same_settings(tmp_path):
    """The compatibility constants and the roles' defaults come from one derivation
    (a fresh process, so that this data folder and override are the ones read)."""
    code = (
        "import tmrl.config.config_constants as c\n"
        "from tmrl.config.settings import NetSettings\n"
        "s = NetSettings.load()\n"
        "print(c.PORT == s.port == 4343, c.HEADER_SIZE == s.header_size == 12, c.NB_WORKERS is s.max_workers is None,\n"
        "      c.CHECKPOINT_PATH == s.checkpoint_path, c.SERVER_IP_FOR_WORKER == s.server_ip_for_worker)\n"
    )
    env = {"TMRL_DATA": str(tmp_path), "TMRL_CONFIG_OVERRIDE": json.dumps({"PORT": 4343, "NB_WORKERS": -1}),
           "PATH": os.environ.get("PATH", "")}
    if "SYSTEMROOT" in os.environ:  # Windows: Python cannot start without it
        env["SYSTEMROOT"] = os.environ["SYSTEMROOT"]
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120,
                         check=False)
    assert out.stdout.split() == ["True"] * 5, out.stderr


def test_a_buffer_without_maxlen_takes_the_configs(monkeypatch, tmp_path):
    monkeypatch.setenv("TMRL_DATA", str(tmp_path))
    monkeypatch.setenv("TMRL_CONFIG_OVERRIDE", json.dumps({"BUFFERS_MAXLEN": 77}))
    assert Buffer().maxlen == 77


def test_the_generated_reference_names_the_arguments_and_their_class_defaults():
    text = schema.markdown_reference()
    row = next(line for line in text.splitlines() if line.startswith("| `ALG.LEARN_ENTROPY_COEF`"))
    assert "`SACAgent(learn_entropy_coef=true)`" in row and "| `false` |" in row
    row = next(line for line in text.splitlines() if line.startswith("| `HEADER_SIZE`"))
    assert "`Server(header_size)`" in row and "| `12` |" in row
