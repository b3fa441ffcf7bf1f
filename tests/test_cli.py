"""python -m tmrl, run as a real subprocess with its own TMRL_DATA and HOME."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tmrl.config import schema

FLAGS = ["--server", "--trainer", "--wandb", "--worker", "--expert", "--test", "--benchmark", "--record-reward",
         "--use-keyboard", "--check-environment", "--install", "--config", "--demo", "--doctor", "--print-config"]


@pytest.fixture
def tmrl_env(_isolated_data_folder, tmp_path):
    """Environment of the subprocesses; a folder on PYTHONPATH for fake hook modules."""
    hooks = tmp_path / "hooks"
    hooks.mkdir()
    env = dict(os.environ)
    env.pop("TMRL_CONFIG_OVERRIDE", None)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(hooks), env.get("PYTHONPATH", "")]))
    return {"env": env, "data": _isolated_data_folder, "hooks": hooks, "home": Path(env["HOME"])}


def tmrl(ctx, *args: str, code: str | None = None) -> subprocess.CompletedProcess:
    if code is None:
        cmd = [sys.executable, "-m", "tmrl", *args]
    else:
        cmd = [sys.executable, "-c", code, *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=ctx["env"], timeout=120, stdin=subprocess.DEVNULL,
                          check=False)


def one_error_line(result: subprocess.CompletedProcess) -> str:
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr
    # Log lines (e.g. "wrote config.json") may precede it; the mistake itself is one line.
    lines = [line for line in result.stderr.splitlines() if line.strip() and " INFO " not in line]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("tmrl: error: ")
    return lines[0]


def write_config(ctx, content) -> Path:
    path = ctx["data"] / "config" / "config.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(content if isinstance(content, str) else json.dumps(content), encoding="utf-8")
    return path


def print_config(ctx, *args: str) -> dict:
    out = tmrl(ctx, "--print-config", *args)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_help_explains_every_flag(tmrl_env):
    out = tmrl(tmrl_env, "--help")
    assert out.returncode == 0
    for flag in FLAGS:
        assert flag in out.stdout
    assert not tmrl_env["data"].exists()


def test_no_command_is_a_usage_error(tmrl_env):
    out = tmrl(tmrl_env)
    assert out.returncode == 2 and "choose a command" in out.stderr


def usage_error(result: subprocess.CompletedProcess) -> list[str]:
    """The lines of a command-line mistake: ``tmrl: error: ...``, then at most a hint line."""
    assert result.returncode == 2, (result.stdout, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert lines[0].startswith("tmrl: error: ") and len(lines) <= 2 and "usage:" not in result.stderr, lines
    return lines


@pytest.mark.parametrize("args, first, hint", [
    (["--serve"], "unrecognized arguments: --serve", "did you mean --server?"),  # no prefix matching
    (["--work"], "unrecognized arguments: --work", "did you mean --worker?"),
    (["--server", "--trainer"], "not allowed with argument", "--help"),
    (["--install", "--env", "mars"], "argument --env: invalid choice: 'mars'", "--help"),
    (["--worker", "--env", "simlidar"], "--env goes with --install", None),
    (["--demo", "--minutes", "-1"], "argument --minutes: must be above 0, got -1", "--demo --help"),
    (["--demo", "--minute", "3"], "unrecognized arguments: --minute 3", "did you mean --minutes?"),
    (["--demo", "--device", "gpu"], "--device 'gpu' is not a device: use auto, cpu, cuda, cuda:N", None),
])
def test_argument_mistakes_are_one_line_with_a_hint_when_it_helps(tmrl_env, args, first, hint):
    lines = usage_error(tmrl(tmrl_env, *args))
    assert first in lines[0]
    assert (hint is None and len(lines) == 1) or (hint is not None and hint in lines[1])
    assert not tmrl_env["data"].exists()  # a mistake creates nothing


def test_demo_on_a_gpu_this_machine_lacks_is_one_line_and_starts_nothing(tmrl_env):
    pytest.importorskip("torch")
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU: --device cuda is valid here")
    lines = usage_error(tmrl(tmrl_env, "--demo", "--device", "cuda"))
    assert "--device cuda: PyTorch" in lines[0] and "sees no CUDA GPU" in lines[0] and "--device auto" in lines[0]
    assert not tmrl_env["data"].exists()


def test_demo_help_creates_nothing(tmrl_env):
    out = tmrl(tmrl_env, "--demo", "--help")
    assert out.returncode == 0 and "--minutes" in out.stdout
    assert not tmrl_env["data"].exists()


def test_demo_config_file_is_the_demos_and_a_dict_is_ours(hooked, tmp_path):
    conf = tmp_path / "mine.json"
    conf.write_text("{}")
    out = tmrl(hooked, "--demo", "--config", str(conf), "--config", '{"RUN_NAME": "x"}', code=RUN_WITH_HOOKS)
    assert out.returncode == 0, out.stderr
    seen = hook_output(out)
    assert seen["argv"] == ["--config", str(conf)]  # the file went to the demo...
    assert json.loads(seen["override"])["RUN_NAME"] == "x"  # ...the dict to the override


def test_install_env_creates_then_switches_keeping_password_and_edits(tmrl_env):
    out = tmrl(tmrl_env, "--install", "--env", "simlidar")
    assert out.returncode == 0, out.stderr
    assert "created for simlidar" in out.stdout and "python -m tmrl --server" in out.stdout
    path = tmrl_env["data"] / "config" / "config.json"
    first = json.loads(path.read_text())
    assert first["ENV"]["RTGYM_INTERFACE"] == "SIMLIDAR" and first["PASSWORD"] != schema.PASSWORD_PLACEHOLDER
    assert first["MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP"] > 0  # the simulator's pacing comes with it
    edited = dict(first, BATCH_SIZE=128, PORT=41234, TLS=True)
    path.write_text(json.dumps(edited))
    out = tmrl(tmrl_env, "--install", "--env", "tm20lidar")
    assert out.returncode == 0, out.stderr
    assert "switched to tm20lidar" in out.stdout and "BATCH_SIZE" in out.stdout and "PASSWORD" in out.stdout
    now = json.loads(path.read_text())
    assert now["ENV"]["RTGYM_INTERFACE"] == "TM20LIDAR" and now["ENV"]["WINDOW_WIDTH"] == 958
    assert (now["PASSWORD"], now["BATCH_SIZE"], now["PORT"], now["TLS"]) == (first["PASSWORD"], 128, 41234, True)
    assert now["RUN_NAME"] == "SAC_4_LIDAR_pretrained"  # never edited: the new environment's value
    assert now["MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP"] == 0  # TrackMania runs in real time: no pacing
    assert json.loads((path.parent / "config.previous.json").read_text()) == edited
    again = tmrl(tmrl_env, "--install", "--env", "tm20lidar")
    assert "already tm20lidar" in again.stdout and json.loads(path.read_text()) == now


def test_wandb_without_trainer_is_refused(tmrl_env):
    out = tmrl(tmrl_env, "--worker", "--wandb")
    assert out.returncode == 2 and "--wandb goes with --trainer" in out.stderr


def test_print_config_without_folder_shows_defaults_and_creates_nothing(tmrl_env):
    cfg = print_config(tmrl_env)
    assert cfg["PORT"] == 55555 and cfg["ALG"]["ALGORITHM"] == "SAC"
    assert cfg["PASSWORD"] == "<hidden>"
    assert not tmrl_env["data"].exists()
    assert not tmrl_env["home"].exists() or not any(tmrl_env["home"].iterdir())


@pytest.mark.parametrize(
    "content, expected",
    [
        ('{"PORT": 55555,\n "TLS": nope}', "invalid JSON at line 2, column 9"),
        ({"ALG": {"LR_ACTR": 0.1}}, "ALG.LR_ACTR is not a known key; did you mean ALG.LR_ACTOR?"),
        ({"ALG": {"LR_ACTOR": "fast"}}, 'config.json: ALG.LR_ACTOR must be a positive number, got "fast"'),
        ({"ENV": {"RTGYM_CONFIG": {"time_step_duration": -1}}},
         "ENV.RTGYM_CONFIG.time_step_duration must be a positive number, got -1"),
        ({"ALG": {"ALGORITHM": "REDQSAC", "REDQ_N": 2, "REDQ_M": 4}}, "ALG.REDQ_M must be at most ALG.REDQ_N"),
        ("[]", "the top level must be an object"),
    ],
)
def test_each_config_error_exits_2_with_one_line(tmrl_env, content, expected):
    path = write_config(tmrl_env, content)
    line = one_error_line(tmrl(tmrl_env, "--print-config"))
    assert expected in line
    assert str(path) in line




def test_override_changes_nested_key_for_one_run_only(tmrl_env):
    path = write_config(tmrl_env, {"ALG": {"LR_ACTOR": 0.001, "GAMMA": 0.9}})
    before = path.read_text()
    cfg = print_config(tmrl_env, "-d", "{'ALG': {'LR_ACTOR': 0.5}, 'CUDA_TRAINING': True}")
    assert cfg["ALG"]["LR_ACTOR"] == 0.5
    assert cfg["ALG"]["GAMMA"] == 0.9  # siblings kept: a deep merge
    assert cfg["CUDA_TRAINING"] is True
    assert path.read_text() == before
    again = print_config(tmrl_env)
    assert again["ALG"]["LR_ACTOR"] == 0.001 and again["CUDA_TRAINING"] is False


def test_override_accepts_json_and_repeats_in_order(tmrl_env):
    cfg = print_config(tmrl_env, "--config", '{"ENV": {"RTGYM_CONFIG": {"act_buf_len": 5}}}',
                       "-d", '{"ENV": {"RTGYM_CONFIG": {"act_buf_len": 6}}, "SEED": 1}')
    assert cfg["ENV"]["RTGYM_CONFIG"]["act_buf_len"] == 6 and cfg["SEED"] == 1


def test_bad_override_is_refused_with_its_key_path(tmrl_env):
    line = one_error_line(tmrl(tmrl_env, "--print-config", "-d", '{"ENV": {"RTGYM_CONFIG": {"act_buf_len": "two"}}}'))
    assert line == 'tmrl: error: --config: ENV.RTGYM_CONFIG.act_buf_len must be a positive integer, got "two"'
    line = one_error_line(tmrl(tmrl_env, "--print-config", "-d", "{'ALG': {'GAMA': 0.9}}"))
    assert "--config: ALG.GAMA is not a known key; did you mean ALG.GAMMA?" in line
    line = one_error_line(tmrl(tmrl_env, "--print-config", "-d", "{'ALG': "))
    assert "--config: not a JSON or Python dict" in line
    line = one_error_line(tmrl(tmrl_env, "--print-config", "-d", "__import__('os').getcwd()"))
    assert "--config: not a JSON or Python dict" in line
    assert "<ast." not in line and "object at 0x" not in line  # no Python internals in messages


def test_install_twice_keeps_edited_config_and_password(tmrl_env):
    first = tmrl(tmrl_env, "--install")
    assert first.returncode == 0, first.stderr
    data = tmrl_env["data"]
    assert str(data) in first.stdout and "fresh random PASSWORD" in first.stdout
    for sub in ("config", "weights", "checkpoints", "dataset", "reward", "credentials", "logs"):
        assert (data / sub).is_dir()
    path = data / "config" / "config.json"
    cfg = json.loads(path.read_text())
    password = cfg["PASSWORD"]
    assert password != schema.PASSWORD_PLACEHOLDER
    cfg["RUN_NAME"] = "my_run"
    path.write_text(json.dumps(cfg, indent=4))
    edited = path.read_text()

    credentials = sorted((data / "credentials").iterdir())
    if credentials:  # generated once tmrl.transport.ensure_credentials exists
        assert "certificate" in " ".join(p.name for p in credentials)
    kept = {p.name: p.read_bytes() for p in credentials}

    second = tmrl(tmrl_env, "--install")
    assert second.returncode == 0, second.stderr
    assert "kept as it was" in second.stdout
    assert path.read_text() == edited
    assert json.loads(path.read_text())["PASSWORD"] == password
    assert {p.name: p.read_bytes() for p in (data / "credentials").iterdir()} == kept
    assert not tmrl_env["home"].exists() or not any(tmrl_env["home"].iterdir())


def test_install_with_broken_config_says_where_and_what(tmrl_env):
    path = write_config(tmrl_env, '{"PORT": }')
    out = tmrl(tmrl_env, "--install")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert str(path) in out.stdout
    assert "invalid JSON at line 1" in out.stderr
    assert path.read_text() == '{"PORT": }'


# --- dispatch, through fake hook modules ---------------------------------------------------------

RUN_WITH_HOOKS = textwrap.dedent(
    """
    import sys
    import tmrl.cli as cli
    for name in ("server", "trainer", "worker", "expert", "test", "benchmark", "demo", "doctor"):
        module, func = cli.HOOKS[name]
        cli.HOOKS[name] = ("fake_hooks" if module == "tmrl.roles" or name in ("demo", "doctor") else module, func)
    cli.HOOKS["record_reward"] = ("tmrl._no_such_module_", "record_reward")
    sys.exit(cli.main(sys.argv[1:]))
    """
)

FAKE_HOOKS = textwrap.dedent(
    """
    import json, os, subprocess, sys
    from tmrl.errors import UserError

    def _report(**kw):
        child = subprocess.run([sys.executable, "-c",
            "import json; from tmrl.config.loader import load_config; print(json.dumps(load_config()['ALG']))"],
            capture_output=True, text=True, check=True)
        kw["child_alg"] = json.loads(child.stdout)
        print("HOOK " + json.dumps(kw))

    def run_server(cfg):
        raise RuntimeError("boom")

    def run_trainer(cfg, wandb=False):
        _report(lr=cfg["ALG"]["LR_ACTOR"], wandb=wandb, folder=os.path.isdir(os.environ["TMRL_DATA"]),
                password=cfg["PASSWORD"])
        return 0

    def run_worker(cfg, mode, standalone=None):
        if mode == "expert" and not standalone:
            raise UserError("the expert is\\nunhappy")
        print("HOOK " + json.dumps({"mode": mode, "standalone": standalone}))
        return 3 if mode == "test" else None

    def run_benchmark(cfg):
        print("HOOK " + json.dumps({"benchmark": cfg["ENV"]["RTGYM_CONFIG"]["benchmark"]}))

    def main(argv):
        print("HOOK " + json.dumps({"argv": argv, "override": os.environ.get("TMRL_CONFIG_OVERRIDE"),
                                    "data": os.environ.get("TMRL_DATA")}))
        return 0
    """
)


@pytest.fixture
def hooked(tmrl_env):
    (tmrl_env["hooks"] / "fake_hooks.py").write_text(FAKE_HOOKS)
    return tmrl_env


def hook_output(result: subprocess.CompletedProcess) -> dict:
    lines = [line[5:] for line in result.stdout.splitlines() if line.startswith("HOOK ")]
    assert len(lines) == 1, (result.stdout, result.stderr)
    return json.loads(lines[0])


def test_trainer_gets_cfg_with_override_and_children_inherit_it(hooked):
    out = tmrl(hooked, "--trainer", "--wandb", "-d", "{'ALG': {'LR_ACTOR': 0.25}}", code=RUN_WITH_HOOKS)
    assert out.returncode == 0, out.stderr
    seen = hook_output(out)
    assert seen["lr"] == 0.25 and seen["wandb"] is True
    assert seen["child_alg"]["LR_ACTOR"] == 0.25  # a child process sees the override
    assert seen["folder"] is True  # commands that need the data folder create it
    written = json.loads((hooked["data"] / "config" / "config.json").read_text())
    assert seen["password"] == written["PASSWORD"] != schema.PASSWORD_PLACEHOLDER


def test_config_error_stops_a_role_before_it_starts(hooked):
    write_config(hooked, {"BATCH_SIZE": 0})
    out = tmrl(hooked, "--trainer", code=RUN_WITH_HOOKS)
    assert "BATCH_SIZE must be a positive integer, got 0" in one_error_line(out)
    assert "HOOK" not in out.stdout


@pytest.mark.parametrize("flags, mode, standalone, code", [
    (["--worker"], "train", None, 0),
    (["--test"], "test", True, 3),
    # tmrl 0.7: --test beside --worker or --expert runs that worker without a server
    (["--worker", "--test"], "train", True, 0),
    (["--test", "--expert"], "expert", True, 0),
])
def test_worker_modes_and_exit_codes(hooked, flags, mode, standalone, code):
    out = tmrl(hooked, *flags, code=RUN_WITH_HOOKS)
    assert out.returncode == code, out.stderr
    assert hook_output(out) == {"mode": mode, "standalone": standalone}


def test_benchmark_turns_on_rtgym_benchmark(hooked):
    # GYM: the TrackMania interfaces route --benchmark to tmrl.tm.tools (test_config_objects.py)
    out = tmrl(hooked, "--benchmark", "-d", '{"ENV": {"RTGYM_INTERFACE": "GYM"}}', code=RUN_WITH_HOOKS)
    assert out.returncode == 0, out.stderr
    assert hook_output(out) == {"benchmark": True}


def test_user_error_in_a_hook_is_one_line(hooked):
    line = one_error_line(tmrl(hooked, "--expert", code=RUN_WITH_HOOKS))
    assert line == "tmrl: error: the expert is unhappy"


def test_bug_in_a_hook_prints_traceback_and_report_request(hooked):
    out = tmrl(hooked, "--server", code=RUN_WITH_HOOKS)
    assert out.returncode == 1
    assert "Traceback" in out.stderr and "RuntimeError: boom" in out.stderr
    assert "This is a bug in tmrl" in out.stderr and "report it" in out.stderr


def test_feature_not_landed_exits_2_with_one_line(hooked):
    line = one_error_line(tmrl(hooked, "--record-reward", code=RUN_WITH_HOOKS))
    assert "--record-reward is not available yet" in line
    assert not hooked["data"].exists()


def test_simulator_interfaces_use_the_simulator_tools(hooked):
    code = RUN_WITH_HOOKS.replace('cli.HOOKS["record_reward"]', 'cli.SIM_HOOKS["check_environment"] = '
                                  '("fake_hooks", "sim_check")\ncli.HOOKS["record_reward"]')
    (hooked["hooks"] / "fake_hooks.py").write_text(
        FAKE_HOOKS + "\ndef sim_check(cfg):\n    print('HOOK ' + json.dumps({'sim': cfg['ENV']['RTGYM_INTERFACE']}))\n"
    )
    out = tmrl(hooked, "--check-environment", "-d", '{"ENV": {"RTGYM_INTERFACE": "simlidar"}}', code=code)
    assert out.returncode == 0, out.stderr
    assert hook_output(out) == {"sim": "SIMLIDAR"}


def test_demo_gets_its_own_arguments_and_our_override(hooked):
    out = tmrl(hooked, "--demo", "--steps", "10", "-d", '{"SEED": 4}', "--fast", code=RUN_WITH_HOOKS)
    assert out.returncode == 0, out.stderr
    seen = hook_output(out)
    assert seen["argv"] == ["--steps", "10", "--fast"]
    assert json.loads(seen["override"]) == {"SEED": 4}


def test_unknown_arguments_are_refused_outside_demo(tmrl_env):
    out = tmrl(tmrl_env, "--install", "--steps", "3")
    assert out.returncode == 2 and "unrecognized arguments" in out.stderr
    assert not tmrl_env["data"].exists()


# --- documentation stays in step with the parser and CI -----------------------------------------

REPO = Path(__file__).resolve().parents[1]


def readme_commands() -> list[str]:
    """The fenced code blocks of the README before its first section heading."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    head = text.split("\n## ", 1)[0]
    blocks = head.split("```")[1::2]
    return [block.split("\n", 1)[1].strip() for block in blocks]


def test_readme_opens_with_two_commands_and_ci_runs_the_second_verbatim():
    commands = readme_commands()
    assert len(commands) == 2
    assert all("\n" not in c for c in commands)
    assert commands[0].startswith("pip install torch==2.13.0 && pip install . && python -m tmrl ")
    assert "pytest" in commands[1] and "tests" in commands[1]
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    assert commands[1] in ci.splitlines()
    # torch is installed once, by the README's command (its first step).
    assert commands[1].startswith("pip install torch==2.13.0 && ")
    assert ci.count("pip install torch") == 1
    assert "set -euo pipefail" in ci
    assert os.access(REPO / ".ci" / "run", os.X_OK)


def test_cli_reference_documents_every_option():
    from tmrl.cli import build_parser

    doc = (REPO / "docs" / "cli.md").read_text(encoding="utf-8")
    for action in build_parser()._actions:
        for option in action.option_strings:
            if option not in ("-h", "--help"):
                assert f"`{option}" in doc, option


def test_relative_tmrl_data_is_made_absolute_for_children(hooked, tmp_path):
    env = dict(hooked["env"], TMRL_DATA="rel_data")
    out = subprocess.run([sys.executable, "-c", RUN_WITH_HOOKS, "--demo"], capture_output=True, text=True, env=env,
                         cwd=tmp_path, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    assert hook_output(out)["data"] == str(tmp_path / "rel_data")


def test_placeholder_password_is_warned_about(hooked):
    write_config(hooked, {"PASSWORD": schema.PASSWORD_PLACEHOLDER})
    out = tmrl(hooked, "--worker", code=RUN_WITH_HOOKS)
    assert out.returncode == 0, out.stderr
    assert "public placeholder" in out.stderr
