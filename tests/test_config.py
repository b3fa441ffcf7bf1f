"""tmrl.config: schema, data folder, loading, validation errors, overrides, compatibility modules."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from tmrl.config import loader, schema
from tmrl.config.loader import ConfigError
from tmrl.errors import UserError

REPO = Path(__file__).resolve().parents[1]
# The original tmrl 0.7.1 default config.json, as bench/anchors/install_tmrl.sh installs it.
ORIGINAL_CONFIG = REPO / "bench" / "anchors" / "tmrl-0.7.1-config.json"

# The example of the original tmrl 0.7 reference guide (readme/reference_guide.md), comments removed.
ORIGINAL_REFERENCE_EXAMPLE = {
    "RUN_NAME": "SAC_4_imgs_pretrained",
    "RESET_TRAINING": False,
    "BUFFERS_MAXLEN": 500000,
    "RW_MAX_SAMPLES_PER_EPISODE": 1000,
    "CUDA_TRAINING": True,
    "CUDA_INFERENCE": False,
    "VIRTUAL_GAMEPAD": True,
    "LOCALHOST_WORKER": True,
    "LOCALHOST_TRAINER": True,
    "PUBLIC_IP_SERVER": "0.0.0.0",
    "PASSWORD": "YourRandomPasswordHere",
    "TLS": False,
    "TLS_HOSTNAME": "default",
    "TLS_CREDENTIALS_DIRECTORY": "",
    "WANDB_PROJECT": "tmrl",
    "WANDB_ENTITY": "tmrl",
    "WANDB_KEY": "YourWandbApiKey",
    "PORT": 55555,
    "LOCAL_PORT_SERVER": 55556,
    "LOCAL_PORT_TRAINER": 55557,
    "LOCAL_PORT_WORKER": 55558,
    "BUFFER_SIZE": 536870912,
    "HEADER_SIZE": 12,
    "MAX_EPOCHS": 10000,
    "ROUNDS_PER_EPOCH": 100,
    "TRAINING_STEPS_PER_ROUND": 200,
    "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 4.0,
    "ENVIRONMENT_STEPS_BEFORE_TRAINING": 1000,
    "UPDATE_MODEL_INTERVAL": 200,
    "UPDATE_BUFFER_INTERVAL": 200,
    "SAVE_MODEL_EVERY": 0,
    "MEMORY_SIZE": 1000000,
    "BATCH_SIZE": 256,
    "ALG": {
        "ALGORITHM": "SAC",
        "LEARN_ENTROPY_COEF": False,
        "LR_ACTOR": 0.00001,
        "LR_CRITIC": 0.00005,
        "LR_ENTROPY": 0.0003,
        "GAMMA": 0.995,
        "POLYAK": 0.995,
        "TARGET_ENTROPY": -0.5,
        "ALPHA": 0.01,
        "REDQ_N": 10,
        "REDQ_M": 2,
        "REDQ_Q_UPDATES_PER_POLICY_UPDATE": 20,
        "OPTIMIZER_ACTOR": "adam",
        "OPTIMIZER_CRITIC": "adam",
        "BETAS_ACTOR": [0.997, 0.997],
        "BETAS_CRITIC": [0.997, 0.997],
        "L2_ACTOR": 0.0,
        "L2_CRITIC": 0.0,
    },
    "ENV": {
        "RTGYM_INTERFACE": "TM20FULL",
        "WINDOW_WIDTH": 256,
        "WINDOW_HEIGHT": 128,
        "IMG_WIDTH": 64,
        "IMG_HEIGHT": 64,
        "IMG_GRAYSCALE": True,
        "SLEEP_TIME_AT_RESET": 1.5,
        "IMG_HIST_LEN": 4,
        "RTGYM_CONFIG": {
            "time_step_duration": 0.05,
            "start_obs_capture": 0.04,
            "time_step_timeout_factor": 1.0,
            "act_buf_len": 2,
            "benchmark": False,
            "wait_on_done": True,
            "ep_max_length": 1000,
            "interface_kwargs": {"save_replays": False},
        },
        "REWARD_CONFIG": {
            "END_OF_TRACK": 100.0,
            "CONSTANT_PENALTY": 0.0,
            "CHECK_FORWARD": 500,
            "CHECK_BACKWARD": 10,
            "FAILURE_COUNTDOWN": 10,
            "MIN_STEPS": 70,
            "MAX_STRAY": 100.0,
        },
    },
    "__VERSION__": "0.6.0",
}

# The LIDAR example of the original's getting-started guide: several ENV keys left out.
ORIGINAL_LIDAR_ENV = {
    "RTGYM_INTERFACE": "TM20LIDAR",
    "WINDOW_WIDTH": 958,
    "WINDOW_HEIGHT": 488,
    "SLEEP_TIME_AT_RESET": 1.5,
    "IMG_HIST_LEN": 4,
    "RTGYM_CONFIG": {
        "time_step_duration": 0.05,
        "start_obs_capture": 0.04,
        "time_step_timeout_factor": 1.0,
        "act_buf_len": 2,
        "benchmark": False,
        "wait_on_done": True,
    },
}


def write_config(folder: Path, content: object) -> Path:
    path = folder / "config" / "config.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(content if isinstance(content, str) else json.dumps(content, indent=2), encoding="utf-8")
    return path


def error_of(raw: object, tmp_path: Path) -> str:
    path = tmp_path / "config.json"
    path.write_text(raw if isinstance(raw, str) else json.dumps(raw), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        loader.load_config(path)
    message = str(info.value)
    assert "\n" not in message
    return message


def leaves(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and k not in ("interface_kwargs", "GYM_KWARGS"):
            out.update(leaves(v, prefix + k + "."))
        else:
            out[prefix + k] = v
    return out


# --- the original's files load -------------------------------------------------------------------


def test_original_default_config_loads_with_every_value_kept():
    raw = json.loads(ORIGINAL_CONFIG.read_text())
    cfg = loader.load_config(ORIGINAL_CONFIG)
    for key, value in leaves(raw).items():
        assert leaves(cfg)[key] == value, key
    assert cfg["SEED"] is None and cfg["ALLOW_PICKLE"] is False and cfg["ALLOW_PLAIN_TCP"] is False
    assert cfg["MAX_FRAME_BYTES"] == 64 * 1024 * 1024


def test_original_reference_guide_example_loads(tmp_path):
    path = write_config(tmp_path, ORIGINAL_REFERENCE_EXAMPLE)
    cfg = loader.load_config(path)
    for key, value in leaves(ORIGINAL_REFERENCE_EXAMPLE).items():
        assert leaves(cfg)[key] == value, key
    assert cfg["CUDA_TRAINING"] is True
    assert cfg["ALG"]["REDQ_Q_UPDATES_PER_POLICY_UPDATE"] == 20
    assert cfg["ENV"]["RTGYM_CONFIG"]["interface_kwargs"] == {"save_replays": False}
    # keys absent from the original take their defaults
    assert cfg["ENV"]["RTGYM_CONFIG"]["reset_act_buf"] is True
    assert cfg["ENV"]["GYM_ID"] == "Pendulum-v1"


def test_partial_original_lidar_env_takes_defaults(tmp_path):
    raw = dict(ORIGINAL_REFERENCE_EXAMPLE, ENV=ORIGINAL_LIDAR_ENV)
    cfg = loader.load_config(write_config(tmp_path, raw))
    assert cfg["ENV"]["RTGYM_INTERFACE"] == "TM20LIDAR"
    assert cfg["ENV"]["IMG_WIDTH"] == 64
    assert cfg["ENV"]["REWARD_CONFIG"]["MAX_STRAY"] == 100.0
    assert cfg["ENV"]["RTGYM_CONFIG"]["ep_max_length"] == 1000


# --- generated artefacts are up to date ----------------------------------------------------------


def test_shipped_default_config_is_the_schema_defaults():
    shipped = (REPO / "config" / "config.json").read_text(encoding="utf-8")
    assert shipped == schema.default_config_json(), "run: python -m tmrl.config.schema --write"
    assert loader.validate(json.loads(shipped)) == loader.default_config()


def test_generated_files_are_up_to_date_and_valid():
    for rel, text in schema.generated_files().items():
        assert (REPO / rel).read_text(encoding="utf-8") == text, f"{rel}: run python -m tmrl.config.schema --write"
        if rel.endswith(".json"):
            loader.load_config(REPO / rel)
    lidar = loader.load_config(REPO / "config" / "config_tm20lidar.json")
    assert lidar["ENV"]["RTGYM_INTERFACE"] == "TM20LIDAR" and lidar["ENV"]["WINDOW_WIDTH"] == 958
    for name in ("SIMLIDAR", "SIMLIDARPROGRESS", "SIMFULL"):
        sim = loader.load_config(REPO / "config" / f"config_{name.lower()}.json")
        assert sim["ENV"]["RTGYM_INTERFACE"] == name and sim["ENV"]["SIM_FAST_MODE"] is True


def test_config_reference_doc_is_generated_from_schema():
    doc = (REPO / "docs" / "config.md").read_text(encoding="utf-8")
    assert doc == schema.markdown_reference(), "run: python -m tmrl.config.schema --write"
    for key in leaves(loader.default_config()):
        assert f"`{key}`" in doc


def test_every_key_has_a_meaning():
    def walk(section: schema.Section, path: str) -> None:
        for name, spec in section.fields.items():
            assert spec.doc.strip(), path + name
            if isinstance(spec, schema.Section):
                walk(spec, path + name + ".")

    walk(schema.SCHEMA, "")


def test_every_default_passes_its_own_check():
    assert loader.validate(loader.default_config(), "defaults") == loader.default_config()


# --- data folder ---------------------------------------------------------------------------------


def test_data_folder_follows_tmrl_data_and_home(tmp_path, monkeypatch):
    monkeypatch.setenv("TMRL_DATA", str(tmp_path / "x"))
    assert loader.data_folder() == tmp_path / "x"
    monkeypatch.delenv("TMRL_DATA")
    monkeypatch.setenv("HOME", str(tmp_path / "h"))
    assert loader.data_folder() == tmp_path / "h" / "TmrlData"
    assert not (tmp_path / "h").exists()


def test_load_config_without_file_uses_defaults_and_creates_nothing(_isolated_data_folder):
    cfg = loader.load_config()
    assert cfg == loader.default_config()
    assert not _isolated_data_folder.exists()


def test_install_creates_layout_and_fresh_password(_isolated_data_folder):
    report = loader.install()
    assert report.created_config
    for sub in loader.LAYOUT:
        assert (_isolated_data_folder / sub).is_dir()
    cfg = loader.load_config()
    assert cfg["PASSWORD"] != schema.PASSWORD_PLACEHOLDER
    assert len(cfg["PASSWORD"]) >= 24
    other = loader.install(_isolated_data_folder.parent / "other")
    assert loader.load_config(other.paths.config_file)["PASSWORD"] != cfg["PASSWORD"]


def test_install_never_overwrites_an_edited_config(_isolated_data_folder):
    loader.install()
    path = loader.config_path()
    edited = path.read_text().replace('"RUN_NAME": "SAC_4_imgs_pretrained"', '"RUN_NAME": "mine"')
    path.write_text(edited)
    report = loader.install()
    assert not report.created_config
    assert path.read_text() == edited


def test_install_keeps_even_an_invalid_config(_isolated_data_folder):
    path = write_config(_isolated_data_folder, "{ not json")
    loader.ensure_data_folder()
    assert path.read_text() == "{ not json"


def test_concurrent_installs_agree_on_one_password(_isolated_data_folder):
    results: list[loader.InstallReport] = []
    barrier = threading.Barrier(8)

    def go() -> None:
        barrier.wait()
        results.append(loader.install())

    threads = [threading.Thread(target=go) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sum(r.created_config for r in results) == 1
    leftovers = [p.name for p in (_isolated_data_folder / "config").iterdir()]
    assert leftovers == ["config.json"]


def test_install_refuses_a_file_in_the_way(tmp_path, monkeypatch):
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    monkeypatch.setenv("TMRL_DATA", str(blocker))
    with pytest.raises(ConfigError, match="TMRL_DATA"):
        loader.ensure_data_folder()


def test_data_paths_follow_run_name_and_credentials_key(tmp_path):
    cfg = loader.validate({"RUN_NAME": "run1", "TLS_CREDENTIALS_DIRECTORY": str(tmp_path / "creds")})
    p = loader.data_paths(cfg, tmp_path / "data")
    assert p.model_worker == tmp_path / "data" / "weights" / "run1.tmod"
    assert p.model_trainer == tmp_path / "data" / "weights" / "run1_t.tmod"
    assert p.checkpoint == tmp_path / "data" / "checkpoints" / "run1_t.tcpt"
    assert p.credentials == tmp_path / "creds"
    assert loader.data_paths(None, tmp_path).credentials == tmp_path / "credentials"
    assert not (tmp_path / "data").exists()


# --- one-line errors -----------------------------------------------------------------------------


def test_wrong_type_names_full_path_value_and_expectation(tmp_path):
    msg = error_of({"ALG": {"LR_ACTOR": "fast"}}, tmp_path)
    assert msg.endswith('config.json: ALG.LR_ACTOR must be a positive number, got "fast"')


@pytest.mark.parametrize(
    "raw, expected",
    [
        ({"ALG": {"LR_ACTR": 0.1}}, "ALG.LR_ACTR is not a known key; did you mean ALG.LR_ACTOR?"),
        ({"WHATEVER": 1}, "WHATEVER is not a known key; remove it"),
        ({"ENV": {"RTGYM_CONFIG": {"act_buf_len": 0}}}, "ENV.RTGYM_CONFIG.act_buf_len must be a positive integer, got 0"),
        ({"PORT": 70000}, "PORT must be an integer from 1 to 65535, got 70000"),
        ({"CUDA_TRAINING": "yes"}, 'CUDA_TRAINING must be true or false, got "yes"'),
        ({"BATCH_SIZE": True}, "BATCH_SIZE must be a positive integer, got true"),
        ({"BATCH_SIZE": 2.5}, "BATCH_SIZE must be a positive integer, got 2.5"),
        ({"ALG": {"GAMMA": 1.5}}, "ALG.GAMMA must be a number in [0, 1], got 1.5"),
        ({"ALG": {"ALGORITHM": "PPO"}}, 'ALG.ALGORITHM must be one of "SAC", "REDQSAC", "DROQ", "TQC", "CROSSQ", "DRQ", "BRO", "SIMBAV2", got "PPO"'),
        ({"ALG": {"BETAS_ACTOR": [0.9]}}, "ALG.BETAS_ACTOR must be a list of 2 numbers in [0, 1), got [0.9]"),
        ({"ENV": {"RTGYM_INTERFACE": "TM2020"}}, 'ENV.RTGYM_INTERFACE must be one of "TM20FULL"'),
        ({"ENV": []}, "ENV must be an object (a dict of keys), got []"),
        ({"ENV": {"GYM_KWARGS": 3}}, "ENV.GYM_KWARGS must be an object"),
        ({"RUN_NAME": "../x"}, "RUN_NAME must be a non-empty string without / or \\"),
        ({"SEED": "1"}, 'SEED must be a non-negative integer or null, got "1"'),
        ([1, 2], "the top level must be an object"),
        ({"ALG": {"ALGORITHM": "REDQSAC", "REDQ_N": 2, "REDQ_M": 3}}, "ALG.REDQ_M must be at most ALG.REDQ_N (2), got 3"),
        ({"ENV": {"RTGYM_INTERFACE": "GYM", "GYM_ID": ""}}, "ENV.GYM_ID must name a Gymnasium environment"),
        ({"ALG": {"UPDATE_ORDER": "later"}}, 'ALG.UPDATE_ORDER must be one of "simultaneous", "sequential"'),
        ({"ALG": {"ALGORITHM": "REDQSAC", "UPDATE_ORDER": "sequential"}},
         'ALG.UPDATE_ORDER must be "simultaneous" when ALG.ALGORITHM is "REDQSAC"'),
        ({"ALG": {"ALGORITHM": "DROQ", "UPDATE_ORDER": "sequential"}},
         'ALG.UPDATE_ORDER must be "simultaneous" when ALG.ALGORITHM is "DROQ"'),
        ({"ALG": {"ALGORITHM": "TQC", "TQC_QUANTILES": 5, "TQC_DROP_PER_CRITIC": 5}},
         "ALG.TQC_DROP_PER_CRITIC must be below ALG.TQC_QUANTILES (5), got 5: TQC would drop every quantile"),
    ],
)
def test_each_class_of_mistake_is_one_line(tmp_path, raw, expected):
    msg = error_of(raw, tmp_path)
    assert msg.startswith(str(tmp_path / "config.json") + ": ")
    assert expected in msg


def test_invalid_json_gives_line_and_column(tmp_path):
    msg = error_of('{\n  "PORT": 55555,\n  "TLS": tru\n}\n', tmp_path)
    assert "invalid JSON at line 3, column 10" in msg


def test_trailing_comma_is_explained(tmp_path):
    msg = error_of('{"PORT": 55555,}', tmp_path)
    assert "line 1" in msg and "trailing commas" in msg


def test_non_utf8_file_is_one_line(tmp_path):
    path = tmp_path / "config.json"
    path.write_bytes(b'{"RUN_NAME": "\xff"}')
    with pytest.raises(ConfigError, match="not UTF-8"):
        loader.load_config(path)


def test_explicit_missing_file_is_an_error(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        loader.load_config(tmp_path / "nope.json")


def test_config_error_is_a_user_error():
    assert issubclass(ConfigError, UserError)


# --- lenient where the original's values vary ----------------------------------------------------


def test_choices_are_case_insensitive_and_normalised():
    cfg = loader.validate({"ALG": {"ALGORITHM": "redqsac", "OPTIMIZER_ACTOR": "AdamW"},
                           "ENV": {"RTGYM_INTERFACE": " tm20lidarprogress"}})
    assert cfg["ALG"]["ALGORITHM"] == "REDQSAC"
    assert cfg["ALG"]["OPTIMIZER_ACTOR"] == "adamw"
    assert cfg["ENV"]["RTGYM_INTERFACE"] == "TM20LIDARPROGRESS"


def test_numbers_are_normalised():
    cfg = loader.validate({"MEMORY_SIZE": 1e6, "ALG": {"LR_ACTOR": 1, "BETAS_ACTOR": (0.9, 0.99)}})
    assert cfg["MEMORY_SIZE"] == 1000000 and isinstance(cfg["MEMORY_SIZE"], int)
    assert cfg["ALG"]["LR_ACTOR"] == 1.0 and isinstance(cfg["ALG"]["LR_ACTOR"], float)
    assert cfg["ALG"]["BETAS_ACTOR"] == [0.9, 0.99]


def test_nullable_keys():
    cfg = loader.validate({"SEED": None, "ALG": {"TARGET_ENTROPY": None},
                           "ENV": {"RTGYM_CONFIG": {"ep_max_length": None}}})
    assert cfg["SEED"] is None and cfg["ALG"]["TARGET_ENTROPY"] is None
    assert loader.validate({"SEED": 7})["SEED"] == 7


# --- overrides -----------------------------------------------------------------------------------


def test_parse_override_accepts_json_and_python_literals():
    assert loader.parse_override('{"CUDA_TRAINING": true}') == {"CUDA_TRAINING": True}
    assert loader.parse_override("{'CUDA_TRAINING': True, 'SEED': None}") == {"CUDA_TRAINING": True, "SEED": None}
    assert loader.parse_override("  ") == {}


@pytest.mark.parametrize("text", ["__import__('os').system('touch pwned')", "{'a': open('x')}", "{1: "])
def test_parse_override_never_evaluates_code(tmp_path, monkeypatch, text):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match="not a JSON or Python dict"):
        loader.parse_override(text)
    assert list(tmp_path.iterdir()) == []


def test_parse_override_refuses_non_dicts():
    with pytest.raises(ConfigError, match="must be a dict"):
        loader.parse_override("[1, 2]")


def test_override_merges_deeply_and_validates_with_key_path():
    base = loader.default_config()
    cfg = loader.apply_override(base, {"ALG": {"ALGORITHM": "redqsac"}, "ENV": {"RTGYM_CONFIG": {"act_buf_len": 3}}})
    assert cfg["ALG"]["ALGORITHM"] == "REDQSAC"
    assert cfg["ALG"]["LR_ACTOR"] == base["ALG"]["LR_ACTOR"]
    assert cfg["ENV"]["RTGYM_CONFIG"]["act_buf_len"] == 3
    assert cfg["ENV"]["RTGYM_CONFIG"]["time_step_duration"] == 0.05
    assert base["ALG"]["ALGORITHM"] == "SAC"  # the input is not modified
    with pytest.raises(ConfigError) as info:
        loader.apply_override(base, "{'ENV': {'RTGYM_CONFIG': {'act_buf_len': -1}}}")
    assert str(info.value) == "--config: ENV.RTGYM_CONFIG.act_buf_len must be a positive integer, got -1"


def test_free_form_objects_are_replaced_not_merged():
    base = loader.validate({"ENV": {"GYM_KWARGS": {"g": 9.8}}})
    cfg = loader.apply_override(base, {"ENV": {"GYM_KWARGS": {"continuous": True}}})
    assert cfg["ENV"]["GYM_KWARGS"] == {"continuous": True}


def test_override_consistency_checked_after_merge():
    base = loader.validate({"ALG": {"ALGORITHM": "REDQSAC", "REDQ_N": 4}})
    with pytest.raises(ConfigError, match="ALG.REDQ_M must be at most ALG.REDQ_N"):
        loader.apply_override(base, {"ALG": {"REDQ_M": 5}})


def test_env_override_is_applied_by_load_config(_isolated_data_folder, monkeypatch):
    write_config(_isolated_data_folder, {"BATCH_SIZE": 64, "ALG": {"GAMMA": 0.9}})
    monkeypatch.setenv(loader.OVERRIDE_ENV, json.dumps({"ALG": {"LR_ACTOR": 0.5}}))
    cfg = loader.load_config()
    assert (cfg["BATCH_SIZE"], cfg["ALG"]["GAMMA"], cfg["ALG"]["LR_ACTOR"]) == (64, 0.9, 0.5)
    # explicit overrides come last
    assert loader.load_config(overrides={"ALG": {"LR_ACTOR": 0.25}})["ALG"]["LR_ACTOR"] == 0.25


def test_bad_env_override_names_its_source(monkeypatch):
    monkeypatch.setenv(loader.OVERRIDE_ENV, '{"ALG": {"GAMMA": 2}}')
    with pytest.raises(ConfigError, match=r"TMRL_CONFIG_OVERRIDE\): ALG.GAMMA must be a number in \[0, 1\]"):
        loader.load_config()


def test_set_override_env_merges_with_an_inherited_override(monkeypatch):
    loader.set_override_env("{'ALG': {'GAMMA': 0.5}}")
    combined = loader.set_override_env({"ALG": {"LR_ACTOR": 0.1}, "SEED": 3})
    assert combined == {"ALG": {"GAMMA": 0.5, "LR_ACTOR": 0.1}, "SEED": 3}
    assert json.loads(os.environ[loader.OVERRIDE_ENV]) == combined
    with pytest.raises(ConfigError, match="--config: PORT"):
        loader.set_override_env({"PORT": 0})
    assert json.loads(os.environ[loader.OVERRIDE_ENV]) == combined


# --- compatibility modules -----------------------------------------------------------------------


def run_python(code: str, env_extra: dict | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, **(env_extra or {}))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120, check=False)


def test_config_constants_reads_config_and_creates_nothing(_isolated_data_folder):
    code = (
        "import json, pathlib\n"
        "import tmrl.config.config_constants as c\n"
        "print(json.dumps({'run': c.RUN_NAME, 'lr': c.ALG_CONFIG['LR_ACTOR'], 'sec': c.SECURITY,\n"
        "  'model': str(c.MODEL_PATH_WORKER), 'is_path': isinstance(c.CHECKPOINT_PATH, pathlib.Path),\n"
        "  'nbw': c.NB_WORKERS, 'ip': c.SERVER_IP_FOR_WORKER, 'lidar': c.PRAGMA_LIDAR}))\n"
    )
    out = run_python(code, {loader.OVERRIDE_ENV: '{"ALG": {"LR_ACTOR": 0.125}, "TLS": true, "RUN_NAME": "r"}'})
    assert out.returncode == 0, out.stderr
    values = json.loads(out.stdout)
    assert values == {"run": "r", "lr": 0.125, "sec": "TLS",
                      "model": str(_isolated_data_folder / "weights" / "r.tmod"), "is_path": True,
                      "nbw": 64, "ip": "127.0.0.1", "lidar": False}
    assert not _isolated_data_folder.exists()


@pytest.mark.parametrize("interface, lidar, progress", [
    ("TM20FULL", False, False), ("TM20LIDAR", True, False), ("TM20LIDARPROGRESS", True, True),
    ("SIMFULL", False, False), ("SIMLIDAR", True, False), ("SIMLIDARPROGRESS", True, True),
    ("GYM", False, False), ("DRONE", False, False),
])
def test_constants_flag_the_lidar_and_progress_interfaces(interface, lidar, progress):
    from tmrl.config.constants import constants

    c = constants(loader.validate({"ENV": {"RTGYM_INTERFACE": interface}}))
    assert (c.RTGYM_INTERFACE, c.PRAGMA_LIDAR, c.PRAGMA_PROGRESS) == (interface, lidar, progress)


def test_config_constants_exposes_every_constant_of_its_configuration(_isolated_data_folder):
    """The compatibility module is tmrl.config.constants.constants() of the configuration it read,
    name for name (and the roles take theirs from the same function)."""
    code = (
        "import json\n"
        "import tmrl.config.config_constants as c\n"
        "from tmrl.config.constants import constants\n"
        "mine = vars(constants(c.TMRL_CONFIG))\n"
        "public = {n for n in vars(c) if n.isupper() and not n.startswith('_')}\n"
        "print(json.dumps({'missing': sorted(set(mine) - public), 'extra': sorted(public - set(mine)),\n"
        "  'differ': sorted(n for n in mine if repr(getattr(c, n)) != repr(mine[n])),\n"
        "  'same_config': mine['TMRL_CONFIG'] is c.TMRL_CONFIG}))\n"
    )
    out = run_python(code, {loader.OVERRIDE_ENV: '{"ENV": {"RTGYM_INTERFACE": "SIMLIDARPROGRESS"}, "NB_WORKERS": -1}'})
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == {"missing": [], "extra": [], "differ": [], "same_config": True}


def test_config_constants_bad_config_is_a_config_error(_isolated_data_folder):
    write_config(_isolated_data_folder, {"PORT": "x"})
    out = run_python(
        "from tmrl.config.loader import ConfigError\n"
        "try:\n    import tmrl.config.config_constants\nexcept ConfigError as e:\n    print('CE', e)\n"
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("CE ") and 'PORT must be an integer from 1 to 65535, got "x"' in out.stdout


def test_config_objects_refuses_an_unknown_interface_keyword_in_one_line():
    out = run_python(
        "from tmrl.config.loader import ConfigError\n"
        "try:\n    import tmrl.config.config_objects\nexcept ConfigError as e:\n    print('CE', e)\n",
        {loader.OVERRIDE_ENV: '{"ENV": {"RTGYM_INTERFACE": "DRONE", "RTGYM_CONFIG": {"interface_kwargs": {"x": 1}}}}'},
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("CE ") and "interface_kwargs.x" in out.stdout and out.stdout.count("\n") == 1


@pytest.mark.parametrize("name", ["SIMLIDAR", "SIMFULL", "TM20LIDARPROGRESS"])
def test_driving_interfaces_need_the_action_buffer_in_observations(name):
    with pytest.raises(ConfigError, match="ENV.RTGYM_CONFIG.act_in_obs must be true"):
        loader.validate({"ENV": {"RTGYM_INTERFACE": name, "RTGYM_CONFIG": {"act_in_obs": False}}})
    assert loader.validate({"ENV": {"RTGYM_INTERFACE": "DRONE", "RTGYM_CONFIG": {"act_in_obs": False}}})


def test_simfull_needs_grayscale_images():
    with pytest.raises(ConfigError, match="ENV.IMG_GRAYSCALE must be true"):
        loader.validate({"ENV": {"RTGYM_INTERFACE": "SIMFULL", "IMG_GRAYSCALE": False}})
    assert loader.validate({"ENV": {"RTGYM_INTERFACE": "TM20FULL", "IMG_GRAYSCALE": False}})


def test_sim_fast_mode_defaults_to_true():
    assert loader.default_config()["ENV"]["SIM_FAST_MODE"] is True
    assert loader.validate({"ENV": {"SIM_FAST_MODE": False}})["ENV"]["SIM_FAST_MODE"] is False


def _modules_present(*names: str) -> bool:
    import importlib.util

    try:
        return all(importlib.util.find_spec(n) is not None for n in names)
    except ModuleNotFoundError:
        return False


@pytest.mark.skipif(
    not _modules_present("tmrl.envs", "tmrl.memory", "tmrl.training_offline", "tmrl.models", "tmrl.algorithms.sac"),
    reason="the learning modules have not landed yet",
)
@pytest.mark.parametrize("algorithm", ["SAC", "REDQSAC"])
def test_config_objects_gym_partials_carry_the_config(algorithm):
    override = {
        "ENV": {"RTGYM_INTERFACE": "GYM", "GYM_ID": "Pendulum-v1", "GYM_KWARGS": {"g": 9.0}},
        "ALG": {"ALGORITHM": algorithm, "LR_ACTOR": 0.002, "REDQ_N": 5},
        "MEMORY_SIZE": 1234, "BATCH_SIZE": 32, "MAX_EPOCHS": 3,
    }
    code = (
        "import json\n"
        "import tmrl.config.config_objects as o\n"
        "a, t, m, e = o.AGENT.keywords, o.TRAINER.keywords, o.MEMORY.keywords, o.ENV_CLS.keywords\n"
        "print(json.dumps({'agent': o.AGENT.func.__name__, 'lr': a['lr_actor'], 'n': a.get('n'),\n"
        "  'mem': [m['memory_size'], m['batch_size']], 'epochs': t['epochs'], 'device': t['device'],\n"
        "  'env': [e['id'], e['gym_kwargs']], 'model': a['model_cls'].__name__}))\n"
    )
    out = run_python(code, {loader.OVERRIDE_ENV: json.dumps(override)})
    assert out.returncode == 0, out.stderr
    v = json.loads(out.stdout)
    assert v["lr"] == 0.002 and v["mem"] == [1234, 32] and v["epochs"] == 3 and v["device"] == "cpu"
    assert v["env"] == ["Pendulum-v1", {"g": 9.0}]
    if algorithm == "SAC":
        assert (v["agent"], v["n"], v["model"]) == ("SACAgent", None, "MLPActorCritic")
    else:
        assert (v["agent"], v["n"], v["model"]) == ("REDQSACAgent", 5, "REDQMLPActorCritic")


@pytest.mark.skipif(
    not _modules_present("tmrl.envs", "tmrl.memory", "tmrl.training_offline", "tmrl.models", "tmrl.realtime"),
    reason="the real-time and learning modules have not landed yet",
)
def test_config_objects_drone_uses_realtime_memory_and_compressor():
    override = {"ENV": {"RTGYM_INTERFACE": "drone", "RTGYM_CONFIG": {"act_buf_len": 3, "time_step_duration": 0.02}}}
    code = (
        "import json\n"
        "import tmrl.config.config_objects as o\n"
        "c = o.CONFIG_DICT\n"
        "out = o.SAMPLE_COMPRESSOR('a', ('o1', 'b1', 'b2', 'b3'), 1.0, False, True, {})\n"
        "print(json.dumps({'mem': o.MEMORY.func.__name__, 'abl': o.MEMORY.keywords['act_buf_len'],\n"
        "  'tsd': c['time_step_duration'], 'iface': c['interface'].func.__name__,\n"
        "  'id': o.ENV_CLS.keywords['id'], 'obs': list(out[1])}))\n"
    )
    out = run_python(code, {loader.OVERRIDE_ENV: json.dumps(override)})
    assert out.returncode == 0, out.stderr
    v = json.loads(out.stdout)
    assert v == {"mem": "RealTimeTorchMemory", "abl": 3, "tsd": 0.02, "iface": "DroneInterface",
                 "id": "real-time-gym-ts-v1", "obs": ["o1"]}


def test_wheel_ships_the_default_config(tmp_path):
    pytest.importorskip("setuptools", reason="building a wheel needs setuptools")
    import shutil
    import zipfile

    src = tmp_path / "src"
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy(REPO / name, src / name if src.exists() else (src.mkdir() or src / name))
    shutil.copytree(REPO / "config", src / "config")
    shutil.copytree(REPO / "tmrl", src / "tmrl", ignore=shutil.ignore_patterns("__pycache__"))
    out = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path / "whl"),
         str(src)],
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert out.returncode == 0, out.stderr
    (wheel,) = (tmp_path / "whl").glob("tmrl_cleanroom-*.whl")  # the distribution's name (pyproject.toml)
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        assert "tmrl/config_files/config.json" in names
        assert "tmrl/cli.py" in names and "tmrl/config/schema.py" in names
        assert json.loads(z.read("tmrl/config_files/config.json")) == loader.default_config()
        metadata = z.read(next(n for n in names if n.endswith("METADATA"))).decode()
    core = [line for line in metadata.splitlines() if line.startswith("Requires-Dist:") and "extra ==" not in line]
    for banned in ("mss", "vgamepad", "opencv", "pywin32", "xlib", "wandb"):
        assert not any(banned in line.lower() for line in core), core


@pytest.mark.parametrize(
    "raw, expected",
    [
        ({"TRANSPORT": "zeromq"}, 'TRANSPORT must be one of "tlspyo", "nats", got "zeromq"'),
        ({"NATS": {"STREAM": "a.b"}}, "NATS.STREAM must be a non-empty string without . or"),
        ({"NATS": {"MAX_PAYLOAD": 2**30}}, "NATS.MAX_PAYLOAD must be an integer from 1048576 to 67108864"),
        ({"NATS": {"TLS": "maybe"}}, 'NATS.TLS must be one of "auto", "on", "off"'),
        ({"NATS": {"URL": ""}}, "NATS.URL is not a known key; did you mean NATS.URLS?"),
    ],
)
def test_transport_mistakes_are_one_line(tmp_path, raw, expected):
    assert expected in error_of(raw, tmp_path)


def test_the_roles_get_the_nats_options_only_with_the_nats_transport(tmp_path):
    from tmrl.config.settings import NetSettings

    assert NetSettings.from_config(loader.validate({}), tmp_path).transport_options("worker") == {}
    cfg = loader.validate({"TRANSPORT": "NATS", "NATS": {"URLS": "nats://a:4222,nats://b:4222",
                                                         "WORKER_CREDENTIALS": "~/w.json"}})
    settings = NetSettings.from_config(cfg, tmp_path)
    assert settings.transport == "nats"
    worker = settings.transport_options("worker")
    assert worker["urls"] == "nats://a:4222,nats://b:4222" and worker["credentials"] == Path("~/w.json").expanduser()
    assert "credentials" not in settings.transport_options("trainer")
    relay = settings.transport_options("relay")
    assert relay["store_dir"] == tmp_path / "nats" and relay["max_payload"] == 8 * 2**20
