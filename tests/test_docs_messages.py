"""docs/troubleshooting.md quotes real messages: each test here makes tmrl print one of them for real
(the command line in a subprocess, or the library call that raises or logs it, in a temporary data
folder) and checks that the page quotes it. When a message changes, the page must change with it.

Only what differs from run to run is normalised before comparing: the data folder (the page shows
``/home/me/TmrlData``), port numbers (the page shows the defaults) and the time at the start of log
lines (left out on the page).
"""

from __future__ import annotations

import json
import logging
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "troubleshooting.md"
PAGE_DATA = "/home/me/TmrlData"
PASSWORD = "the right password for this test"


def _normal(text: str, data: Path | None = None) -> str:
    """``text`` with the run-specific parts replaced by placeholders."""
    if data is not None:
        text = text.replace(str(data), PAGE_DATA)
    text = re.sub(r"127\.0\.0\.1:\d+", "127.0.0.1:<port>", text)
    return re.sub(r"\bport \d+", "port <port>", text)


def _assert_quoted(line: str, data: Path | None = None) -> None:
    """The page quotes ``line`` (normalised) word for word."""
    page = _normal(PAGE.read_text(encoding="utf-8"))
    expected = _normal(line.strip(), data)
    assert expected, "no message was produced"
    assert expected in page, f"docs/troubleshooting.md does not quote this message (update the page):\n{expected}"


def _tmrl(data: Path, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    env = {**os.environ, "TMRL_DATA": str(data)}
    env.pop("TMRL_CONFIG_OVERRIDE", None)
    return subprocess.run([sys.executable, "-m", "tmrl", *args], capture_output=True, text=True, env=env,
                          cwd=data.parent, timeout=timeout, check=False)


def _error_lines(proc: subprocess.CompletedProcess) -> list[str]:
    """The ``tmrl: error:`` line and the hint line after it, checking the exit code of a mistake."""
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("tmrl: error:"))
    return lines[start:]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for(cond: Any, what: str, timeout: float = 30.0) -> Any:
    """Poll ``cond`` (an effect of another process) until it is truthy."""
    deadline = time.monotonic() + timeout
    while not (value := cond()):
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)
    return value


def _log_line(caplog: Any, fragment: str) -> str | None:
    """The first captured record containing ``fragment``, as the page shows log lines."""
    for r in caplog.records:
        if fragment in r.getMessage():
            return f"{r.levelname} {r.name}: {r.getMessage()}"
    return None


# --- the command line and the configuration -------------------------------------------------------


def test_unknown_option_and_missing_command(tmp_path):
    data = tmp_path / "TmrlData"
    for line in _error_lines(_tmrl(data, "--serve")) + _error_lines(_tmrl(data)):
        _assert_quoted(line)
    _assert_quoted(_error_lines(_tmrl(data, "--worker", "--wandb"))[0])
    assert not data.exists(), "a command-line mistake created the data folder"


def test_config_file_mistakes(tmp_path):
    data = tmp_path / "TmrlData"
    assert _tmrl(data, "--install", "--env", "simlidar").returncode == 0
    path = data / "config" / "config.json"
    good = path.read_text(encoding="utf-8")
    assert '"TLS": false,\n' in good and '"BATCH_SIZE"' in good and '"CUDA_TRAINING": false' in good
    for broken in (good.replace('"BATCH_SIZE"', '"BATCHSIZE"'),
                   good.replace('"CUDA_TRAINING": false', '"CUDA_TRAINING": "yes"'),
                   good.replace('"TLS": false,\n', '"TLS": false\n')):
        path.write_text(broken, encoding="utf-8")
        (line,) = _error_lines(_tmrl(data, "--trainer"))
        _assert_quoted(line, data)


def test_override_mistakes(tmp_path):
    data = tmp_path / "TmrlData"
    for override in ('{"ALG": {"GAMA": 0.9}}', '{"PORT": "abc"}', '{"ALG": {"ALGORITHM": "PPO"}}',
                     '{"ALG": {"ALGORITHM": "REDQSAC", "REDQ_M": 20}}', "not a dict"):
        (line,) = _error_lines(_tmrl(data, "--trainer", "-d", override))
        _assert_quoted(line)


# --- starting the server ----------------------------------------------------------------------------


def test_port_in_use(tmp_path):
    data = tmp_path / "TmrlData"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        (line,) = _error_lines(_tmrl(data, "--server", "-d", json.dumps({"PORT": port})))
    assert f"port {port} is already in use" in line
    _assert_quoted(line)


def test_tls_credentials_missing(tmp_path):
    data = tmp_path / "TmrlData"
    (line,) = _error_lines(_tmrl(data, "--server", "-d", json.dumps({"TLS": True, "PORT": _free_port()})))
    _assert_quoted(line, data)


# --- connecting, spaces, weights -------------------------------------------------------------------


@pytest.fixture
def relay(caplog):
    from tmrl.transport import RelayServer

    caplog.set_level(logging.INFO, logger="tmrl")
    made: list[Any] = []
    relay = RelayServer(_free_port(), PASSWORD, security=None)
    made.append(relay)
    yield relay, made
    for obj in reversed(made):
        obj.close() if hasattr(obj, "close") else obj.stop()


def test_wrong_password_lines_on_both_sides(relay, caplog):
    from tmrl.transport import WorkerLink

    server, made = relay
    link = WorkerLink("127.0.0.1", server.port, "not the right one", security=None)
    made.append(link)
    _wait_for(lambda: link.refused, "the refusal")
    assert link.refused == "wrong password"
    from tmrl.distributed._common import PasswordRefused, check_refused

    with pytest.raises(PasswordRefused) as err:  # what the worker stops with (the CLI prints it)
        check_refused(link, "worker", f"127.0.0.1:{server.port}")
    _assert_quoted(f"tmrl: error: {err.value}")
    _assert_quoted(_wait_for(lambda: _log_line(caplog, ": wrong password"), "the server's line"))


def _lidar_raw(rng: np.random.Generator, progress: bool) -> tuple:
    """A raw observation of the SIMLIDAR (or SIMLIDARPROGRESS) interface: speed, (progress,) the
    4-scan lidar history, the 2-action buffer."""
    speed = np.array([rng.uniform(0, 300)], np.float32)
    lidars = rng.uniform(0, 400, (4, 19)).astype(np.float32)
    acts = (np.zeros(3, np.float32), np.zeros(3, np.float32))
    return (speed, np.array([0.5], np.float32), lidars, *acts) if progress else (speed, lidars, *acts)


def test_worker_of_other_spaces_is_dropped_by_the_trainer(relay, caplog):
    """A SIMLIDARPROGRESS worker's samples reach a SIMLIDAR trainer: the trainer drops the batch
    with the line the page quotes."""
    from gymnasium import spaces

    from tmrl import wire
    from tmrl.networking import Buffer, TrainerInterface, pack_buffer
    from tmrl.sim.interfaces import pipeline_parts
    from tmrl.spaces import SampleSchema
    from tmrl.transport import WorkerLink

    server, made = relay
    act = spaces.Box(-1.0, 1.0, (3,), np.float32)
    obs = spaces.Tuple((spaces.Box(0.0, np.inf, (1,), np.float32), spaces.Box(0.0, np.inf, (4, 19), np.float32),
                        act, act))
    run = pipeline_parts("SIMLIDAR")
    schema = SampleSchema(obs, act, run["obs_preprocessor"], run["sample_compressor"])
    trainer = TrainerInterface("127.0.0.1", server.port, PASSWORD, header_size=10, security=None, schema=schema,
                               sign_weights=False)
    made.append(trainer)
    other = pipeline_parts("SIMLIDARPROGRESS")
    rng = np.random.default_rng(0)
    buf = Buffer(maxlen=100)
    for _ in range(10):
        sample = (act.sample(), other["obs_preprocessor"](_lidar_raw(rng, progress=True)), 0.5, False, False, {})
        buf.append_sample(other["sample_compressor"](*sample))
    worker = WorkerLink("127.0.0.1", server.port, PASSWORD, security=None)
    made.append(worker)
    assert trainer.wait_connected(30) and worker.wait_connected(30)
    worker.send_samples(wire.decode(wire.encode(pack_buffer(buf, 1645928335, 0))))
    _wait_for(lambda: trainer.retrieve_buffer() is not None and trainer.rejected_batches, "the dropped batch")
    line = _log_line(caplog, "dropped a sample batch from worker")
    assert line is not None and "obs has a sequence of 3 where the run expects a sequence of 2" in line
    _assert_quoted(line)


def test_weights_of_other_spaces_sentence():
    from gymnasium import spaces

    from tmrl.spaces import SpacesMismatchError, check_spaces, describe_spaces

    act = spaces.Box(-2.0, 2.0, (1,), np.float32)
    worker = describe_spaces(spaces.Box(-1.0, 1.0, (4,), np.float32), act)
    trainer = describe_spaces(spaces.Box(-1.0, 1.0, (3,), np.float32), act)
    with pytest.raises(SpacesMismatchError) as err:
        check_spaces(worker, trainer)
    _assert_quoted(str(err.value))


# --- checkpoints -------------------------------------------------------------------------------------


def test_checkpoint_messages(_isolated_data_folder):
    from tmrl.checkpoint import CheckpointError, checkpoint_complete, load_checkpoint

    data = _isolated_data_folder
    folder = data / "checkpoints" / "simlidar_sac_t.tcpt"
    folder.mkdir(parents=True)
    (folder / "checkpoint.json").write_text("garbage{", encoding="utf-8")
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(folder, None)
    _assert_quoted(str(err.value), data)
    (folder / "checkpoint.json").unlink()
    (folder / "state-000002.pt").write_bytes(b"saved state")
    with pytest.raises(CheckpointError) as err:
        checkpoint_complete(folder)
    _assert_quoted(str(err.value), data)


# --- TrackMania ----------------------------------------------------------------------------------------


def test_trackmania_messages(_isolated_data_folder):
    from tmrl.tm.openplanet import OpenPlanetClient, TelemetryTimeout
    from tmrl.tm.record import RewardFileError, load_reward

    data = _isolated_data_folder
    port = _free_port()  # nothing listens there: the plugin is "not running"

    def refused(client: OpenPlanetClient) -> str | None:
        try:
            client.retrieve_data(timeout=0.5)
        except TelemetryTimeout as e:  # once the client has tried, the message names the refusal
            return str(e) if "ConnectionRefusedError" in str(e) else None
        raise AssertionError("telemetry arrived from a port where nothing listens")

    with OpenPlanetClient(port=port, timeout=1) as client:
        message = _wait_for(lambda: refused(client), "the refused connection")
    cause, fix = message.replace(str(port), "9000").split(": check that", 1)
    _assert_quoted(cause)
    _assert_quoted("fix: check that" + fix)
    with pytest.raises(RewardFileError) as err:
        load_reward(data / "reward" / "reward.npy")
    _assert_quoted(f"tmrl: error: {err.value}", data)

