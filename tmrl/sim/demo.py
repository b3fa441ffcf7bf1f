"""``python -m tmrl --demo``: watch the whole distributed pipeline learn to drive, no game needed.

The demo starts a server, a trainer and a worker as three processes on localhost, the worker
driving the built-in simulator (lidar observations, fast mode, the default track unless told
otherwise). While it trains it shows a live status line: elapsed time, episodes, last and best
return, laps completed, updates/s and samples/s. It stops at the end of its budget (time or
environment steps) or on Ctrl-C, SIGTERM, SIGHUP or Ctrl-Break (exit codes 130, 143, 129, 149), then writes to its
output folder the trained weights, a learning-curve PNG, a top-down PNG of the best lap (or of the
farthest run when no lap was completed) and the roles' logs, removes its run folder, and prints a
summary with the time to the first completed lap and the best lap time. Its roles also stop, and
remove the run folder, when the demo itself dies (:mod:`tmrl.sim.lifeline`).

The roles talk over plain TCP on 127.0.0.1 with a random password (nothing leaves the machine);
each role runs ``python -m tmrl.sim.demo --role ...`` and reports through small JSON status files
written atomically in the run folder.
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import math
import os
import secrets
import shutil
import signal
import socket
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tmrl import platform
from tmrl.config.schema import ALGORITHMS
from tmrl.errors import UserError
from tmrl.util import atomic_write_bytes

__all__ = ["CPU_REALTIME_SETTINGS", "DEMO_SETTINGS", "GPU_REALTIME_SETTINGS", "REALTIME_SETTINGS", "main"]

#: Training settings of the demo (SAC with a small replay memory, a fast update rhythm).
DEMO_SETTINGS: dict[str, Any] = dict(
    img_hist_len=4, act_buf_len=2, ep_max_length=1000, batch_size=256, memory_size=200_000,
    algorithm="SAC", lr=1e-3, gamma=0.99, polyak=0.995, alpha=0.2, learn_entropy_coef=True,
    steps_per_round=200, rounds=10,
    update_model_interval=20, update_buffer_interval=20, max_training_steps_per_env_step=1.0,
    realtime_max_training_steps_per_env_step=4.0, realtime_alpha=0.01, realtime_learn_entropy_coef=False,
    start_training=1000, max_env_steps_per_training_step=3.0,
)
# Fast mode: the worker keeps pace with the trainer (MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP, carried
# with the weights): at most 3 samples per update, at most one update per sample; the simulator
# costs nothing, so wall time is what counts there. Real time: the clock sets the pace (20 samples/s)
# and environment steps are what count; the trainer, otherwise idle, does up to 4 updates per sample
# (bench/track_learning.py: SAC laps `classic` in fewer steps at 4 updates per step than at 1), with
# tmrl's fixed entropy coefficient 0.01: at that ratio a learned one laps sooner but falls back after
# ~7,000 steps and drives a slower best lap (the benchmark's SAC-UTD4-FA against SAC-UTD4). In fast
# mode (at most one update per sample) the learned coefficient lapped sooner in wall time and steps.
# A model every 20 updates keeps the worker moving smoothly.

#: The real-time setting on a GPU trainer, on lidar (``--realtime`` with the trainer on CUDA and no
#: ``--algorithm``): the benchmark's recommendation where the trainer can afford it,
#: ``REDQSAC-UTD8-CAP-R250`` (docs/benchmarks.md): REDQ-SAC's ten critics at up to 8 updates per
#: sample, each with its policy update, the entropy coefficient learned from 0.2 and held at or
#: under 0.01 once it has come down there, training from the 250th sample. It lapped ``classic``
#: first after a median 1,500 steps (75 s at 20 steps/s) where SAC at 4 took 2,000 to 4,000; it
#: needs 160 ten-critic updates per second, which two CPU cores do not give (1.3 per sample there).
GPU_REALTIME_SETTINGS: dict[str, Any] = {
    "algorithm": "REDQSAC", "realtime_max_training_steps_per_env_step": 8.0, "realtime_alpha": 0.2,
    "realtime_learn_entropy_coef": True, "alpha_max": 0.01, "start_training": 250, "label": "REDQSAC-UTD8-CAP-R250",
}

#: BRO's setting in real time on a CPU trainer (the benchmark's ``BRO-W128-UTD8-CAP-R250``): not the
#: default. It laps ``classic`` in fewer environment steps than SAC (a median 1,500) at 0.42 of
#: REDQ-SAC's compute per step, but on the 2-core development machine its trainer gave it 1.2 to 2.8
#: updates per sample and ``--demo --realtime`` with it lapped once in three 5-minute runs (after 176
#: s of training; docs/benchmarks.md), where the demo's SAC at 4 laps after a median 298 s. Kept for
#: ``--algorithm BRO`` runs and for measuring it again on another machine.
CPU_REALTIME_SETTINGS: dict[str, Any] = {
    "algorithm": "BRO", "realtime_max_training_steps_per_env_step": 8.0, "realtime_alpha": 0.2,
    "realtime_learn_entropy_coef": True, "alpha_max": 0.01, "start_training": 250,
    "agent_kwargs": {"critic_width": 128}, "label": "BRO-W128-UTD8-CAP-R250",
}

#: The real-time setting on a CPU trainer, on lidar (``--realtime`` with the trainer on the CPU and
#: no ``--algorithm``): SAC with actor and critics 128 wide (about half the time of an update 256
#: wide on a CPU) at up to 8 updates per sample, its entropy coefficient learned from 0.2 and held
#: at or under 0.01, 250 random samples first (the benchmark's ``SAC-W128-UTD8-CAP-R250``). On the
#: 2-core development machine it lapped ``classic`` in real time after 149 and 218 s of training and
#: not in a third 5-minute run (after 109, 183 and 136 s in three that evening), at 67 to 85 updates
#: per second, where the demo's own SAC (4 updates
#: per sample, fixed coefficient, 1,000 random samples) lapped in none of three, at 34 to 37
#: (2026-12-02, docs/benchmarks.md).
SAC_W128_REALTIME_SETTINGS: dict[str, Any] = {
    "algorithm": "SAC", "realtime_max_training_steps_per_env_step": 8.0, "realtime_alpha": 0.2,
    "realtime_learn_entropy_coef": True, "alpha_max": 0.01, "start_training": 250, "hidden_sizes": (128, 128),
    "label": "SAC-W128-UTD8-CAP-R250",
}

#: The real-time settings by trainer: ``--realtime``, lidar, no ``--algorithm``. On a CPU the one
#: that lapped first in real time there (``"sac-w128"``), on a GPU the one that laps first in steps
#: (``"gpu"``). ``"bro-cpu"`` (:data:`CPU_REALTIME_SETTINGS`) is chosen by nothing: ``--setting
#: NAME`` trains any of them, to measure them again.
REALTIME_SETTINGS: dict[str, dict[str, Any]] = {"gpu": GPU_REALTIME_SETTINGS, "bro-cpu": CPU_REALTIME_SETTINGS,
                                                 "sac-w128": SAC_W128_REALTIME_SETTINGS}

_INTERFACES = ("SIMLIDAR", "SIMLIDARPROGRESS", "SIMFULL")
#: In real time the worker sends its samples and takes the newest weights every second (20 steps),
#: not only between episodes (:class:`~tmrl.distributed.RolloutWorker`'s ``sync_every``).
REALTIME_SYNC_STEPS = 20
# Seconds the roles get to stop after the parent's stop request, all together, before they are ended.
_ROLES_GRACE = 7.0


# ------------------------------------------------------------------------------------------------
# inside the role processes


def _parts(interface: str) -> dict[str, Any]:
    from tmrl.sim.interfaces import pipeline_parts

    return pipeline_parts(interface)


def _demo_config(interface: str, track: str, config_path: str | None = None) -> dict[str, Any]:
    """The ``ENV`` part of a tmrl config for the demo's environment: the demo's settings, or the
    ``ENV`` section of the config file given with ``--config`` (interface and track as resolved
    by the parent)."""
    from tmrl.sim.interfaces import DEFAULT_SIM_RTGYM_CONFIG

    if config_path:
        from tmrl.config.loader import load_config

        env = dict(load_config(config_path)["ENV"])
        rtgym = dict(env["RTGYM_CONFIG"])
        rtgym["interface_kwargs"] = dict(rtgym.get("interface_kwargs") or {}, track=track)
        env.update(RTGYM_INTERFACE=interface, RTGYM_CONFIG=rtgym)
        return {"ENV": env}
    s = DEMO_SETTINGS
    rtgym = dict(DEFAULT_SIM_RTGYM_CONFIG, act_buf_len=s["act_buf_len"], ep_max_length=s["ep_max_length"],
                 interface_kwargs={"track": track})
    return {"ENV": {"RTGYM_INTERFACE": interface, "IMG_HIST_LEN": s["img_hist_len"], "IMG_WIDTH": 64,
                    "IMG_HEIGHT": 64, "RTGYM_CONFIG": rtgym, "REWARD_CONFIG": {}}}


def _make_env(interface: str, track: str, realtime: bool = False) -> Any:
    """The fast environment, or the real-time one (``tmrl.realtime``, wall-clock physics)."""
    from tmrl.sim.interfaces import fast_env, realtime_config

    cfg = _demo_config(interface, track, os.environ.get("TMRL_DEMO_CONFIG") or None)
    if not realtime:
        return fast_env(cfg)
    from tmrl.realtime import RealTimeEnv

    return RealTimeEnv(realtime_config(cfg))


def _race(env: Any) -> Any:
    inner = env.unwrapped
    return inner.race if hasattr(inner, "race") else inner.interface.race


def _stats_env(interface: str, track: str, workdir: Path, realtime: bool = False) -> Any:
    """The worker's environment, wrapped to publish episode statistics and the best lap's path."""
    import gymnasium

    env = _make_env(interface, track, realtime)

    class Stats(gymnasium.Wrapper):
        def __init__(self, inner: Any) -> None:
            super().__init__(inner)
            self.t0 = time.monotonic()
            self.steps = 0
            self.returns: list[float] = []
            self.episode_return = 0.0
            self.path: list[tuple[float, float]] = []
            self.laps = 0
            self.best_lap: float | None = None
            self.first_lap_s: float | None = None
            self.best_progress = -1.0
            self.last_write = 0.0
            self.best_path: bytes | None = None  # the best lap's path, until it is written

        def reset(self, **kwargs: Any) -> Any:
            out = self.env.reset(**kwargs)
            self.episode_return = 0.0
            self.path = [tuple(_race(self.env).car.state.position)]
            return out

        def step(self, action: Any) -> Any:
            obs, rew, terminated, truncated, info = self.env.step(action)
            race = _race(self.env)
            self.steps += 1
            self.episode_return += rew
            self.path.append(tuple(race.car.state.position))
            if terminated or truncated:
                self._episode_end(race, info)
            now = time.monotonic()
            # also every 50 steps: the worker pauses between models, and a count written only
            # on time would stay behind during the pause
            if now - self.last_write > 0.5 or terminated or truncated or self.steps % 50 == 0:
                self._write(now)
            return obs, rew, terminated, truncated, info

        def _episode_end(self, race: Any, info: dict) -> None:
            self.returns.append(float(self.episode_return))
            lap = info.get("lap_time") if info.get("lap_completed") else None
            better = False
            if lap is not None:
                self.laps += 1
                if self.first_lap_s is None:
                    self.first_lap_s = time.monotonic() - self.t0
                better = self.best_lap is None or lap < self.best_lap
                self.best_lap = lap if better else self.best_lap
            elif self.best_lap is None and race.progress > self.best_progress:
                better = True  # no lap yet: keep the farthest run
            if better:
                self.best_progress = max(self.best_progress, race.progress)
                buf = io.BytesIO()
                np.save(buf, np.asarray(self.path, dtype=np.float64), allow_pickle=False)
                self.best_path = buf.getvalue()

        def _write(self, now: float) -> None:
            self.last_write = now
            # The path first: the status that counts its lap must never be read before it exists.
            if self.best_path is not None and _publish(workdir / "best_path.npy", self.best_path):
                self.best_path = None
            if self.best_path is None:
                status = {"steps": self.steps, "episodes": len(self.returns), "returns": self.returns[-2000:],
                          "laps": self.laps, "best_lap": self.best_lap, "first_lap_s": self.first_lap_s}
                _publish(workdir / "worker.json", json.dumps(status).encode())

    return Stats(env)


def _publish(path: Path, data: bytes) -> bool:
    """Replace a status file; False (and nothing lost: the caller writes again soon) while another
    process holds it longer than :data:`tmrl.platform.BUSY_DELAYS` allow (Windows)."""
    try:
        atomic_write_bytes(path, data)
        return True
    except OSError as err:
        logging.getLogger(__name__).debug("could not write %s yet: %s", path.name, err)
        return False


def _agent_cls(interface: str, algorithm: str, realtime: bool = False) -> Any:
    """The demo's training agent: ``algorithm`` (an ``ALG.ALGORITHM`` value) with the model it
    trains on ``interface``'s observations, counting its updates for the status line."""
    from tmrl.algorithms import agent_class
    from tmrl.driving.models import lidar_model_cls
    from tmrl.util import partial

    s = DEMO_SETTINGS
    base = agent_class(algorithm)
    if interface == "SIMFULL":
        if base.__name__ not in ("SACAgent", "REDQSACAgent"):
            raise UserError(f"the demo trains SAC or REDQSAC on SIMFULL images, not {algorithm}")
        model_cls = _parts(interface)["model_cls"]
    else:
        model_cls = lidar_model_cls(algorithm)
        if s.get("hidden_sizes"):  # a setting's narrower actor and critics (the worker's actor too)
            model_cls = partial(model_cls, hidden_sizes=tuple(s["hidden_sizes"]))

    class Counting(base):  # type: ignore[misc, valid-type]
        """The agent, publishing its number of updates (for the demo's status line)."""

        updates = 0
        last_write = 0.0
        workdir: Path | None = None

        def train(self, batch: tuple) -> dict[str, Any]:
            out = super().train(batch)
            Counting.updates += 1
            now = time.monotonic()
            if Counting.workdir is not None and now - Counting.last_write > 0.5:
                Counting.last_write = now
                _publish(Counting.workdir / "trainer.json", json.dumps({"updates": Counting.updates}).encode())
            return out

    Counting.__name__ = Counting.__qualname__ = f"Counting{base.__name__}"
    mode = "realtime_" if realtime else ""
    extra = {"alpha_max": s["alpha_max"]} if s.get("alpha_max") is not None else {}
    extra.update(s.get("agent_kwargs") or {})
    return partial(Counting, model_cls=model_cls, gamma=s["gamma"], polyak=s["polyak"], alpha=s[mode + "alpha"],
                   lr_actor=s["lr"], lr_critic=s["lr"], lr_entropy=s["lr"],
                   learn_entropy_coef=s[mode + "learn_entropy_coef"], target_entropy=None, **extra)


def _worker_actor_cls(interface: str) -> Any:
    """The worker's actor: the interface's, as wide as the trainer's (a setting's ``hidden_sizes``)."""
    actor_cls = _parts(interface)["actor_cls"]
    if DEMO_SETTINGS.get("hidden_sizes") and interface != "SIMFULL":
        from tmrl.util import partial

        actor_cls = partial(actor_cls, hidden_sizes=tuple(DEMO_SETTINGS["hidden_sizes"]))
    return actor_cls


def _training_cls(interface: str, track: str, workdir: Path, realtime: bool = False, device: str = "cpu") -> Any:
    from tmrl.training_offline import TorchTrainingOffline
    from tmrl.util import partial

    s = DEMO_SETTINGS
    agent = _agent_cls(interface, s["algorithm"], realtime)
    agent.func.workdir = workdir
    parts = _parts(interface)
    env = _make_env(interface, track)  # only its spaces and settings are used
    spaces = (env.observation_space, env.action_space)
    hist_len, act_buf_len = env.interface.img_hist_len, env.act_buf_len
    return partial(
        TorchTrainingOffline,
        env_cls=spaces,
        memory_cls=partial(parts["memory_cls"], hist_len=hist_len, act_buf_len=act_buf_len,
                           memory_size=s["memory_size"], batch_size=s["batch_size"]),
        training_agent_cls=agent,
        epochs=100_000, rounds=s["rounds"], steps=s["steps_per_round"],
        update_buffer_interval=s["update_buffer_interval"], update_model_interval=s["update_model_interval"],
        max_training_steps_per_env_step=s["realtime_max_training_steps_per_env_step" if realtime
                                          else "max_training_steps_per_env_step"],
        start_training=s["start_training"], device=device,
        max_env_steps_per_training_step=s["max_env_steps_per_training_step"],
    )


def _run_role(role: str, interface: str, track: str, workdir: Path, port: int, password: str,
              realtime: bool = False, device: str = "cpu") -> None:
    # Stop signals (the parent's SIGINT, or SIGTERM when the parent died) arrive as
    # KeyboardInterrupt (see main()): each role closes its network process within STOP_TIMEOUT.
    from tmrl.distributed import STOP_TIMEOUT, RolloutWorker, Server, Trainer
    from tmrl.roles import size_threads
    from tmrl.util import show_progress_on_console

    show_progress_on_console()  # the role's INFO lines go to its log (the parent keeps it)
    if role != "server":
        size_threads(role)  # 1 (the parent sets OMP_NUM_THREADS=1) unless TMRL_THREADS says otherwise

    common = dict(password=password, security=None)
    if role == "server":
        server = Server(port=port, **common)
        try:
            while True:
                time.sleep(1.0)
        finally:
            server.stop(STOP_TIMEOUT)
    elif role == "trainer":
        trainer = Trainer(training_cls=_training_cls(interface, track, workdir, realtime, device), server_ip="127.0.0.1",
                          server_port=port, model_path=str(workdir / "weights.tmod"), checkpoint_path=None, **common)
        try:
            trainer.run()
        finally:
            trainer.interface.close(STOP_TIMEOUT)
    elif role == "worker":
        parts = _parts(interface)
        actor_cls = _worker_actor_cls(interface)
        worker = RolloutWorker(
            env_cls=lambda: _stats_env(interface, track, workdir, realtime), actor_module_cls=actor_cls,
            sample_compressor=parts["sample_compressor"], obs_preprocessor=parts["obs_preprocessor"],
            server_ip="127.0.0.1", server_port=port, max_samples_per_episode=math.inf,
            model_path=str(workdir / "weights_worker.tmod"), model_history=0,
            sync_every=REALTIME_SYNC_STEPS if realtime else 0, **common)
        # Fast mode: the trainer's pace (sent with the weights) holds the worker back; real time:
        # the clock sets the pace, and the worker pauses between episodes only.
        try:
            worker.run()
        finally:
            worker.close(STOP_TIMEOUT)


# ------------------------------------------------------------------------------------------------
# the parent process


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_listening(port: int, timeout: float, proc: platform.Child, logs_dir: Path | None = None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the demo server exited at start; see server.log in {logs_dir or 'the run folder'}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"the demo server did not listen on port {port} within {timeout:.0f} s")


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(platform.read_bytes(path))  # retried while the writer replaces it (Windows)
    except (OSError, ValueError):
        return {}


def _status_line(elapsed: float, worker: dict[str, Any], trainer: dict[str, Any]) -> str:
    returns = worker.get("returns") or []
    last = f"{returns[-1]:7.1f}" if returns else "      -"
    best = f"{max(returns):7.1f}" if returns else "      -"
    steps, updates = worker.get("steps", 0), trainer.get("updates", 0)
    lap = worker.get("best_lap")
    return (f"{elapsed:6.0f} s | episodes {worker.get('episodes', 0):4d} | return last {last} best {best} | "
            f"laps {worker.get('laps', 0):3d}{f' (best {lap:.1f} s)' if lap else ''} | "
            f"{updates / max(elapsed, 1e-9):6.1f} updates/s | {steps / max(elapsed, 1e-9):6.1f} samples/s")


def _key_figures(worker: dict[str, Any]) -> str:
    """The run's headline, for the charts: first lap and best lap time, or how far it got."""
    first, best = worker.get("first_lap_s"), worker.get("best_lap")
    if first is None:
        return f"NO LAP YET AFTER {worker.get('episodes', 0)} EPISODES"
    return f"FIRST LAP AFTER {first:.0f} S OF TRAINING, BEST LAP {best:.2f} S"


def _versus_reference(track: str, best: float) -> str:
    """The best lap as a share of the track's reference lap (:mod:`tmrl.sim.reference`), for the
    summary: ``" = 1.21 x reference 43.20 s"``, or nothing when there is no reference."""
    try:
        from tmrl.sim.reference import reference_lap_time

        ref = reference_lap_time(track)
    except Exception:  # noqa: BLE001 (a summary line is not worth failing the demo for)
        return ""
    return f" = {best / ref:.2f} x reference {ref:.2f} s"


def _finish(workdir: Path, out: Path, track: str, interface: str, worker: dict[str, Any],
            config_path: str | None = None) -> dict[str, Path]:
    from tmrl.driving.reward import DEFAULT_REWARD_CONFIG
    from tmrl.sim.charts import lap_image, learning_curve_image, return_note
    from tmrl.sim.render import write_png
    from tmrl.sim.track import make_track

    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    weights = workdir / "weights.tmod"
    if weights.exists():
        paths["weights"] = out / "weights.safetensors"
        atomic_write_bytes(paths["weights"], platform.read_bytes(weights))
    paths["curve"] = out / "learning_curve.png"
    rewards = {**DEFAULT_REWARD_CONFIG, **(_demo_config(interface, track, config_path)["ENV"].get("REWARD_CONFIG") or {})}
    write_png(paths["curve"], learning_curve_image(worker.get("returns") or [],
                                                   f"TMRL DEMO: {interface} ON TRACK {track}", [_key_figures(worker)],
                                                   return_note(float(rewards["END_OF_TRACK"]))))
    path = np.zeros((0, 2))
    try:
        path = np.load(io.BytesIO(platform.read_bytes(workdir / "best_path.npy")), allow_pickle=False)
    except (OSError, ValueError):
        pass
    best = worker.get("best_lap")
    title = f"BEST LAP ON TRACK {track}" if best is not None else f"FARTHEST RUN ON TRACK {track} (NO LAP YET)"
    note = f"LAP TIME {best:.2f} S (SIMULATED)" if best is not None else "THE CAR'S PATH, START LINE DASHED"
    paths["lap"] = out / "best_lap.png"
    write_png(paths["lap"], lap_image(make_track(track), path, title, [note]))
    return paths


def _number(kind: type, minimum: float, strict: bool) -> Any:
    """An argparse type: a ``kind`` number above (``strict``) or at least ``minimum``."""
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not math.isfinite(value) or value < minimum or (strict and value == minimum):
            raise argparse.ArgumentTypeError(f"must be {'above' if strict else 'at least'} {minimum:g}, got {text}")
        return value
    return parse


def _role_command(role: str, args: argparse.Namespace, workdir: Path, port: int, device: str,
                  setting: str | None) -> list[str]:
    """The command line of one of the demo's processes (settings resolved by the parent)."""
    cmd = [sys.executable, "-m", "tmrl.sim.demo", "--role", role, "--interface", args.interface,
           "--track", str(args.track), "--workdir", str(workdir), "--port", str(port),
           "--start-training", str(args.start_training), "--algorithm", args.algorithm, "--device", device]
    cmd += ["--realtime"] if args.realtime else []
    cmd += ["--setting", setting] if setting else []
    return cmd


def demo_setting(interface: str, realtime: bool, device: str, algorithm: str | None,
                 start_training: int | None, setting: str | None = None) -> tuple[str, int, str | None]:
    """The demo's agent and samples before training, and which of :data:`REALTIME_SETTINGS`
    applies: in real time, on lidar and with no ``--algorithm`` given, :data:`GPU_REALTIME_SETTINGS`
    with the trainer on a CUDA device and :data:`SAC_W128_REALTIME_SETTINGS` on the CPU; elsewhere
    (fast mode, images, Apple's ``mps``, which was not measured) the demo's own SAC. What the user
    gave wins.

    Args:
        interface: the demo's interface.
        realtime: ``--realtime``.
        device: the trainer's resolved device (``"cpu"``, ``"cuda"``, ``"cuda:N"``).
        algorithm: ``--algorithm``, or ``None``.
        start_training: ``--start-training``, or ``None``.
        setting: ``--setting``: one of :data:`REALTIME_SETTINGS` by name, whatever the device, or
            ``None``.

    Returns:
        ``(algorithm, start_training, setting)``, ``setting`` a key of :data:`REALTIME_SETTINGS`
        or None.

    Raises:
        UserError: ``--setting`` with ``--algorithm``, on images, or without ``--realtime``.
    """
    if setting is not None:
        if algorithm is not None or interface == "SIMFULL" or not realtime:
            raise UserError(f"--setting {setting} is a real-time setting on lidar that names its agent: use it with "
                            "--realtime, without --algorithm and without SIMFULL")
    elif realtime and algorithm is None and interface != "SIMFULL":
        setting = "gpu" if str(device).startswith("cuda") else "sac-w128" if str(device) == "cpu" else None
    base = REALTIME_SETTINGS[setting] if setting else DEMO_SETTINGS
    return (algorithm or base["algorithm"], int(start_training or base["start_training"]), setting)


def _parse(argv: Sequence[str]) -> argparse.Namespace:
    from tmrl.cli import Parser

    p = Parser(prog="python -m tmrl --demo", hint="`python -m tmrl --demo --help` lists the demo's options",
               description="Train a driving policy on the built-in simulator: server, trainer and worker on this "
                           "machine, no game needed.")
    p.add_argument("--interface", choices=_INTERFACES, help="observations (default SIMLIDAR, or the --config's)")
    p.add_argument("--track", help="track name (oval, classic, technical) or integer seed (default classic, "
                                   "or the --config's RTGYM_CONFIG.interface_kwargs.track)")
    p.add_argument("--config", help="a config.json whose ENV section (a SIM* interface) sets the environment")
    p.add_argument("--minutes", type=_number(float, 0.0, True), default=15.0, help="time budget in minutes (default 15)")
    p.add_argument("--steps", type=_number(int, 0, False), default=0,
                   help="stop after this many environment steps (0: no limit)")
    p.add_argument("--out", default="tmrl_demo", help="output folder (default ./tmrl_demo)")
    p.add_argument("--start-training", type=_number(int, 1, False), default=None,
                   help="environment steps collected before training starts (default 1000; 250 with the "
                        "real-time settings)")
    # DRQ (images only, slow on a CPU) is trained through a config, not the demo.
    p.add_argument("--algorithm", type=str.upper, choices=[a for a in ALGORITHMS if a != "DRQ"], default=None,
                   help=f"training agent (default {DEMO_SETTINGS['algorithm']}; with --realtime and lidar, "
                        f"{SAC_W128_REALTIME_SETTINGS['label']} on a CPU trainer and "
                        f"{GPU_REALTIME_SETTINGS['label']} on a GPU); SIMFULL takes SAC or REDQSAC only")
    p.add_argument("--threads", type=_number(int, 1, False),
                   help="PyTorch threads of the trainer and the worker (default 1 each; TMRL_THREADS)")
    p.add_argument("--device", default="auto",
                   help="where the trainer trains: auto (a CUDA GPU when PyTorch sees one, else an Apple GPU "
                        "(mps) on a Mac, else the CPU; the default), cpu, cuda, cuda:N, mps; the worker always acts "
                        "on the CPU")
    p.add_argument("--realtime", action="store_true",
                   help="run the simulator in real time through tmrl.realtime (20 steps/s) instead of fast mode")
    p.add_argument("--setting", choices=tuple(REALTIME_SETTINGS),
                   help="with --realtime: train one of the measured real-time settings by name (docs/benchmarks.md; "
                        "default: the CPU's or the GPU's, by the trainer's device)")
    p.add_argument("--role", choices=("server", "trainer", "worker"), help=argparse.SUPPRESS)
    p.add_argument("--workdir", help=argparse.SUPPRESS)
    p.add_argument("--port", type=int, help=argparse.SUPPRESS)
    return p.parse_args(list(argv))


def _role_main(args: argparse.Namespace) -> int:
    """A role's process (``--role``): it stops when the parent asks through its lifeline, on
    SIGTERM, SIGHUP or Ctrl-Break, and when its parent dies (even killed outright); then, with the
    parent gone, it removes the run folder, which nobody else will."""
    from tmrl.realtime.timeouts import summarised_timeouts
    from tmrl.sim.lifeline import stop_on_signals

    workdir = Path(args.workdir)
    # The lifeline's stop request arrives as a KeyboardInterrupt: SIGINT must have Python's handler
    # before it is watched, even in a role started with SIGINT ignored (`nohup ... &`).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    lifeline = platform.watch_lifeline(on_orphaned=lambda: platform.remove_tree(workdir))
    if args.setting:
        DEMO_SETTINGS.update(REALTIME_SETTINGS[args.setting])
    DEMO_SETTINGS["start_training"] = max(1, int(args.start_training or DEMO_SETTINGS["start_training"]))
    DEMO_SETTINGS["algorithm"] = args.algorithm or DEMO_SETTINGS["algorithm"]
    try:
        # stop_on_signals: SIGTERM, SIGHUP and Ctrl-Break raise a KeyboardInterrupt too.
        with stop_on_signals(force_sigint=True), summarised_timeouts():  # --realtime: one line per 10 s
            _run_role(args.role, args.interface, args.track, workdir, args.port,
                      os.environ.get("TMRL_DEMO_PASSWORD", ""), args.realtime, args.device)
    except KeyboardInterrupt:  # the parent stops its roles through their lifelines: a normal end
        pass
    finally:
        if lifeline is not None and lifeline.orphaned.is_set():
            platform.remove_tree(workdir)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the demo (or, with the hidden ``--role``, one of its processes). Returns the exit code.

    Raises:
        UserError: an unknown track.
    """
    args = _parse(sys.argv[1:] if argv is None else argv)
    if args.role:
        return _role_main(args)
    from tmrl.sim.track import make_track

    if args.config:
        from tmrl.config.loader import load_config
        from tmrl.sim.interfaces import interface_kwargs

        cfg = load_config(args.config)
        name = str(cfg["ENV"]["RTGYM_INTERFACE"]).upper()
        args.interface = args.interface or (name if name in _INTERFACES else None)
        if args.interface is None:
            raise UserError(f"{args.config}: ENV.RTGYM_INTERFACE is {name}; the demo needs one of {', '.join(_INTERFACES)}")
        cfg["ENV"]["RTGYM_INTERFACE"] = args.interface
        args.track = args.track or interface_kwargs(cfg).get("track")
        args.config = str(Path(args.config).resolve())
    args.interface = args.interface or "SIMLIDAR"
    args.track = str(args.track or "classic")
    make_track(args.track)  # a bad name fails here, in one line
    if args.interface == "SIMFULL" and (args.algorithm or DEMO_SETTINGS["algorithm"]) not in ("SAC", "REDQSAC"):
        raise UserError(f"--algorithm {args.algorithm} trains on lidar observations only: use SAC or REDQSAC with "
                        "SIMFULL images")
    from tmrl.config.loader import load_config
    from tmrl.sim.lifeline import exit_code, ignore_stop_signals, signal_name, stop_on_signals

    from tmrl.util import resolve_device

    device = resolve_device(args.device, "--device")  # a device this machine lacks: one line, nothing started
    args.algorithm, args.start_training, setting = demo_setting(
        args.interface, args.realtime, device, args.algorithm, args.start_training, args.setting)
    # A configuration mistake is reported before anything starts. The demo writes nothing into the
    # data folder (its roles keep their files in the run folder): no config.json is created there.
    load_config()
    out = Path(args.out).resolve()
    workdir = Path(tempfile.mkdtemp(prefix="tmrl-demo-"))
    port = _free_port()
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1", TMRL_DEMO_PASSWORD=secrets.token_hex(16),
               TMRL_DEMO_CONFIG=args.config or "")
    env.setdefault("TMRL_DATA", str(workdir / "TmrlData"))
    if args.threads:
        env["TMRL_THREADS"] = str(args.threads)  # tmrl.roles.size_threads in each role
    procs: list[platform.Child] = []
    logs = []

    def start(role: str) -> platform.Child:
        log = open(workdir / f"{role}.log", "wb")
        logs.append(log)
        cmd = _role_command(role, args, workdir, port, device, setting)
        # A process group of its own: Ctrl-C in the terminal reaches the demo only, which stops the
        # roles in order through their lifelines; a role stops by itself when the demo dies.
        proc = platform.Child(cmd, env=env, stdout=log, stderr=log)
        procs.append(proc)
        return proc

    budget = args.minutes * 60.0
    tty = sys.stdout.isatty()
    agent = args.algorithm
    if setting:
        chosen = REALTIME_SETTINGS[setting]
        agent = (f"{args.algorithm} at up to {chosen['realtime_max_training_steps_per_env_step']:g} updates per sample, "
                 f"the {setting.upper()} setting {chosen['label']}")
    print(f"tmrl demo: {args.interface} on track {args.track} ({'real time' if args.realtime else 'fast mode'}, {agent}, "
          f"trainer on {device}), budget {args.minutes:g} min"
          f"{f' or {args.steps} steps' if args.steps else ''}; Ctrl-C stops early. Run folder: {workdir}", flush=True)
    t0 = time.monotonic()
    stopped: KeyboardInterrupt | None = None
    worker: dict[str, Any] = {}
    logs_dir = out / "logs"
    try:
        with stop_on_signals():  # SIGTERM and SIGHUP (a closed terminal) stop the demo like Ctrl-C
            try:
                server = start("server")
                _wait_listening(port, 60.0, server, logs_dir)
                start("trainer")
                start("worker")
                last_print = 0.0
                while True:
                    time.sleep(0.5)
                    elapsed = time.monotonic() - t0
                    worker = _read_json(workdir / "worker.json") or worker
                    trainer = _read_json(workdir / "trainer.json")
                    line = _status_line(elapsed, worker, trainer)
                    if tty:
                        print("\r" + line, end="", flush=True)
                    elif elapsed - last_print >= 10.0:
                        print(line, flush=True)
                        last_print = elapsed
                    dead = [p for p in procs if p.poll() is not None]
                    if dead:
                        raise RuntimeError(f"a demo process exited early (code {dead[0].returncode}); see its log "
                                           f"in {logs_dir}")
                    if elapsed >= budget or (args.steps and worker.get("steps", 0) >= args.steps):
                        break
            except KeyboardInterrupt as err:
                stopped = err
            finally:
                ignore_stop_signals()  # the clean-up below finishes, whatever comes next
                platform.stop_children(procs, _ROLES_GRACE)  # newest first; ended after the grace
                for log in logs:
                    log.close()
                _keep_logs(workdir, logs_dir)
            if stopped is not None and signal_name(stopped) == "SIGHUP" and sys.stdout.isatty():
                _detach_from_terminal()  # the terminal is gone: the outputs are still written
            _say("" if tty else None)
            worker = _read_json(workdir / "worker.json") or worker
            paths = _finish(workdir, out, args.track, args.interface, worker, args.config)
    finally:
        if not platform.remove_tree(workdir):
            _say(f"tmrl demo: could not remove the run folder {workdir} (another program holds a file in it)")
    returns = worker.get("returns") or []
    first, best = worker.get("first_lap_s"), worker.get("best_lap")
    how = "finished" if stopped is None else f"stopped ({signal_name(stopped)})"
    _say(f"tmrl demo {how} after {time.monotonic() - t0:.0f} s: "
         f"{worker.get('episodes', 0)} episodes, {worker.get('steps', 0)} steps, best return "
         f"{max(returns) if returns else float('nan'):.1f}, laps completed {worker.get('laps', 0)}")
    _say(f"  first completed lap after {first:.0f} s of training" if first is not None else "  no lap completed yet: "
         "give it more time (--minutes)")
    if best is not None:
        _say(f"  best lap time {best:.2f} s (simulated){_versus_reference(args.track, best)}")
    for name, path in {**paths, "logs": logs_dir}.items():
        _say(f"  {name}: {path}")
    return 0 if stopped is None else exit_code(stopped)


def _keep_logs(workdir: Path, logs_dir: Path) -> None:
    """Copy the roles' logs next to the outputs: they are where to look when something went wrong."""
    for role in ("server", "trainer", "worker"):
        if (workdir / f"{role}.log").exists():
            logs_dir.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(workdir / f"{role}.log", logs_dir / f"{role}.log")


def _say(line: str | None) -> None:
    """Print ``line`` (nothing for None); a closed terminal or pipe silences the rest."""
    if line is None:
        return
    try:
        print(line, flush=True)
    except OSError:
        _detach_from_terminal()


def _detach_from_terminal() -> None:
    """Point stdout and stderr at /dev/null: the terminal was closed (SIGHUP) or the reader of
    the pipe left, and a write there would fail."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for stream in (sys.stdout, sys.stderr):
            try:
                os.dup2(devnull, stream.fileno())
            except (OSError, ValueError, AttributeError):
                pass
    finally:
        os.close(devnull)


if __name__ == "__main__":
    sys.exit(main())
