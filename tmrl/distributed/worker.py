"""The :class:`RolloutWorker`: runs the policy in its environment, sends the samples and loads
the weights the trainer broadcasts (installed by :class:`~tmrl.distributed.weights.WeightsInstaller`)."""

from __future__ import annotations

import itertools
import logging
import math
import os
import secrets
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from tmrl.config.settings import NetSettings
from tmrl.distributed._common import FROM_CONFIG, LOGGER_NAME, _given, _make_link, _settings, check_refused, close_budget
from tmrl.distributed.buffer import Buffer, pack_buffer
from tmrl.distributed.weights import WeightsInstaller
from tmrl.errors import UserError
from tmrl.spaces import describe_spaces, finite_stat
from tmrl.util import show_progress_on_console

logger = logging.getLogger(LOGGER_NAME)

#: Seconds between two lines of a worker that still waits for the trainer's first weights.
WAITING_NOTE_INTERVAL = 30.0


class EpisodeLog:
    """The worker's episode reports: every episode at DEBUG level; at ``level`` (INFO by
    default) the first one, then one summary line every ``interval`` seconds, so that a fast
    environment does not print a wall of lines (thousands an hour).

    Args:
        kind: ``"train"`` or ``"expert"``.
        level: level of the first line and the summaries.
        interval: seconds between two summaries.
    """

    def __init__(self, kind: str, level: int = logging.INFO, interval: float = 30.0) -> None:
        self.kind = kind
        self.level = level
        self.interval = interval
        self._last = -math.inf
        self._returns: list[float] = []
        self._first = 0
        self._sent = 0
        self._test: tuple[float, int] | None = None

    def test(self, ret: float, steps: int) -> None:
        """Record a test episode (reported with the next summary).

        Args:
            ret: its return.
            steps: its length.
        """
        logger.debug("test episode: return %.1f in %d steps", ret, steps)
        self._test = (ret, steps)

    def train(self, episode: int, ret: float, steps: int, sent: int, version: int) -> None:
        """Record a finished train episode; log a summary when one is due.

        Args:
            episode: its index.
            ret: its return.
            steps: its length.
            sent: samples sent since the previous call.
            version: the weights version the worker acts with.
        """
        logger.debug("%s episode %d: return %.1f in %d steps; %d samples sent; weights version %d",
                     self.kind, episode, ret, steps, sent, version)
        if not self._returns:
            self._first = episode
        self._returns.append(float(ret))
        self._sent += sent
        now = time.monotonic()
        if now - self._last < self.interval:
            return
        self._last = now
        returns = self._returns
        span = f"episode {episode}" if len(returns) == 1 else f"episodes {self._first}-{episode}"
        test = "" if self._test is None else f"; test return {self._test[0]:.1f}"
        logger.log(self.level, "%s %s: return last %.1f, mean %.1f, best %.1f%s; %d samples sent; weights version %d",
                   self.kind, span, returns[-1], sum(returns) / len(returns), max(returns), test, self._sent, version)
        self._returns, self._sent, self._test = [], 0, None


class Pace:
    """The worker's side of the trainer's sample budget (Reverb's rate limiter, simplified).

    With ``MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP`` set, the trainer sends with its weights how
    many samples it accepts to have received by now (``pace_budget``) and how many it has
    (``pace_received``). The worker counts the samples it collects after those weights and
    pauses once the budget is used up, until new weights raise it. With several workers each may
    use the whole budget of one broadcast, so they overshoot by at most one budget each; the
    trainer's own ratio (``MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP``) bounds the rest.
    """

    def __init__(self) -> None:
        self.limit = 0.0
        self.allowance = 0
        self.collected = 0

    @property
    def active(self) -> bool:
        """Whether the trainer asked for pacing."""
        return self.limit > 0

    def update(self, header: dict[str, Any]) -> None:
        """Take the pacing fields of a weights header (a header without them turns pacing off)."""
        fields = [header.get(k) for k in ("pace_limit", "pace_budget", "pace_received")]
        if not all(finite_stat(v) is not None and v >= 0 for v in fields):
            self.limit = 0.0
            return
        limit, budget, received = fields
        self.limit = float(limit)
        self.allowance = int(budget) - int(received)
        self.collected = 0

    def count(self, n: int) -> None:
        """``n`` more samples collected."""
        self.collected += n

    def exhausted(self) -> bool:
        """Whether the samples collected since the last weights used up the budget."""
        return self.active and self.collected >= self.allowance


def _is_real_time(env: Any) -> bool:
    """Whether ``env`` runs on the wall clock (an rtgym-style environment with ``benchmarks()``)."""
    return callable(getattr(getattr(env, "unwrapped", env), "benchmarks", None))


class RolloutWorker:
    """Runs the current policy in an environment; sends the samples to the server and loads the
    weights the trainer broadcasts. In standalone mode (``standalone=True``) it connects to
    nothing, for deployment and tests.

    Args:
        env_cls: callable building the Gymnasium environment (e.g. ``partial(GenericGymEnv, id=...)``).
        actor_module_cls: callable ``(observation_space=, action_space=)`` building the
            ``ActorModule``.
        sample_compressor: ``fn(prev_act, obs, rew, terminated, truncated, info)`` returning the
            same 6 values, smaller (the memory decompresses); ``None`` sends samples as they are.
        device: device of the policy (``"cpu"``, ``"cuda"``).
        max_samples_per_episode: episodes are cut (``truncated=True``) after this many steps.
        model_path: where the worker keeps its copy of the latest weights (``MODEL_PATH_WORKER``);
            loaded at start when it exists.
        obs_preprocessor: ``fn(obs) -> obs`` applied to every observation from the environment.
        crc_debug: store the full transition ``(prev_obs, act, new_obs, rew, terminated,
            truncated)`` in ``info["crc_sample"]`` before compression, for the memory to check its
            rebuilt transitions against (debugging custom pipelines only).
        model_path_history: prefix of the files of the saved history of weights
            (``MODEL_PATH_SAVE_HISTORY``).
        model_history: save every ``model_history``-th received model (``0`` or negative: never;
            ``MODEL_HISTORY``).
        standalone: do not connect to a server.
        server_ip: the server's address (``SERVER_IP_FOR_WORKER``).
        server_port: the server's port (``PORT``).
        password: the shared password (``PASSWORD``).
        local_port: accepted for compatibility with tmrl 0.7, unused.
        max_buf_len: accepted for compatibility with tmrl 0.7, unused.
        header_size: tlspyo header size (``HEADER_SIZE``).
        security: ``"TLS"`` or ``None`` for plain TCP (``SECURITY``).
        keys_dir: folder holding the TLS certificate (``CREDENTIALS_DIRECTORY``).
        hostname: the name the server's certificate is checked against (``HOSTNAME``).
        sync_every: in a train episode, every ``sync_every`` steps, send the samples collected so
            far and load the newest weights if some arrived, without waiting (0: only between
            episodes, as tmrl 0.7; ``WORKER_SYNC_STEPS``). In real time a policy that crawls for a
            whole episode otherwise acts with weights, and leaves the trainer with samples, up to
            an episode old.

    Raises:
        UserError: bad connection settings (see :mod:`tmrl.transport`), ``sync_every < 0``.
    """

    def __init__(
        self,
        env_cls: Callable[[], Any],
        actor_module_cls: Callable[..., Any],
        sample_compressor: Callable[..., tuple] | None = None,
        device: str = "cpu",
        max_samples_per_episode: float = math.inf,
        model_path: str | os.PathLike[str] | None = None,
        obs_preprocessor: Callable[[Any], Any] | None = None,
        crc_debug: bool = False,
        model_path_history: str | os.PathLike[str] | None = None,
        model_history: int | None = None,
        standalone: bool = False,
        server_ip: str | None = None,
        server_port: int | None = None,
        password: str | None = None,
        local_port: int | None = None,
        header_size: int | None = None,
        max_buf_len: int | None = None,
        security: str | None = FROM_CONFIG,
        keys_dir: str | os.PathLike[str] | None = None,
        hostname: str | None = None,
        *,
        settings: NetSettings | None = None,
        sync_every: int | None = None,
    ):
        show_progress_on_console()
        cfg = _settings(settings)
        sync_every = _given(sync_every, cfg.worker_sync_steps)
        if int(sync_every) < 0:
            raise UserError(f"sync_every must be 0 (between episodes only) or a number of steps, got {sync_every}")
        self.sync_every = int(sync_every)
        self.obs_preprocessor = obs_preprocessor
        self.sample_compressor = sample_compressor
        self.env = env_cls()
        obs_space = self.env.observation_space
        act_space = self.env.action_space
        self.spaces = describe_spaces(obs_space, act_space)
        self.device = device
        self.installer = WeightsInstaller(
            self.spaces,
            device,
            model_path=_given(model_path, cfg.model_path_worker),
            model_path_history=_given(model_path_history, cfg.model_path_save_history),
            model_history=_given(model_history, cfg.model_history),
            keys_dir=_given(keys_dir, cfg.credentials_directory),
        )
        """Checks and loads the weights this worker receives (:class:`~tmrl.distributed.weights.WeightsInstaller`)."""
        actor = actor_module_cls(observation_space=obs_space, action_space=act_space).to_device(device)
        self.actor = self.installer.load_file(actor)
        self.standalone = standalone
        self.max_samples_per_episode = max_samples_per_episode
        self.crc_debug = crc_debug
        self.source_id = secrets.randbelow(2**31 - 1) + 1
        self.buffer = Buffer(cfg.buffers_maxlen)
        self.buffer.source_id = self.source_id
        self._seq = 0
        self.samples_sent = 0
        """Samples handed to the network since this worker was built (what its summaries add up)."""
        self.weights_version = 0
        self.run_id: str | None = None
        """The run identity of the weights this worker acts with (stamped on its samples)."""
        self.pace = Pace()
        self._paused_mid_episode = not _is_real_time(self.env)
        self.debug_ts_cpt = 0
        self.debug_ts_res_cpt = 0
        self.server_ip = _given(server_ip, cfg.server_ip_for_worker)
        self._server_port = _given(server_port, cfg.port)
        self._link: Any = None
        self._closed = False
        if not standalone:
            from tmrl.transport import BACKENDS

            self._link = _make_link(
                BACKENDS[cfg.transport].worker,
                self.server_ip,
                server_port,
                password,
                local_port,
                header_size,
                security,
                keys_dir,
                hostname,
                cfg,
                **cfg.transport_options("worker"),
            )
            logger.info("worker %d connecting to the server at %s", self.source_id, self.server_ip)

    @property
    def model_path(self) -> Path:
        """The worker's copy of the latest weights (``MODEL_PATH_WORKER``)."""
        return self.installer.model_path

    @property
    def model_path_history(self) -> str:
        """Prefix of the files of the saved history of weights (``MODEL_PATH_SAVE_HISTORY``)."""
        return self.installer.model_path_history

    @property
    def model_history(self) -> int:
        """Every how many received models one is kept in the history (``MODEL_HISTORY``)."""
        return self.installer.model_history

    @property
    def rejected_weights(self) -> int:
        """Weights received and refused so far (the actor was kept)."""
        return self.installer.rejected

    # --- connection ------------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """Whether the worker is connected to the server (``False`` in standalone mode)."""
        return self._link is not None and bool(self._link.connected)

    def wait_connected(self, timeout: float | None = None) -> bool:
        """Wait until connected to the server; ``False`` on timeout or in standalone mode."""
        return self._link is not None and bool(self._link.wait_connected(timeout))

    def close(self, timeout: float = 15.0) -> None:
        """Send what was handed to the network, then disconnect (idempotent). The link's process
        flushes for at most ``timeout - 1`` seconds and is killed after ``timeout``."""
        self._closed = True
        if self._link is not None:
            self._link.close(close_budget(self._link, timeout))

    def __enter__(self) -> RolloutWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- stepping --------------------------------------------------------------------------------

    @property
    def get_local_buffer_sample(self) -> Callable[..., tuple] | None:
        """tmrl 0.7's name of :attr:`sample_compressor` (reads and writes it)."""
        return self.sample_compressor

    @get_local_buffer_sample.setter
    def get_local_buffer_sample(self, fn: Callable[..., tuple] | None) -> None:
        self.sample_compressor = fn

    def act(self, obs: Any, test: bool = False) -> Any:
        """The actor's action for ``obs`` (``test=True``: deterministic)."""
        return self.actor.act_(obs, test=test)

    def _record(
        self, act: Any, new_obs: Any, rew: float, terminated: bool, truncated: bool, info: dict
    ) -> None:
        if self.sample_compressor is not None:
            sample = self.sample_compressor(act, new_obs, rew, terminated, truncated, info)
        else:
            sample = (act, new_obs, rew, terminated, truncated, info)
        self.buffer.append_sample(sample)

    def reset(self, collect_samples: bool) -> tuple[Any, dict]:
        """Start an episode; when ``collect_samples``, record its first sample, whose action is
        the environment's ``default_action`` (real-time environments) or ``None``.

        Returns:
            ``(obs, info)`` after the ``obs_preprocessor``.
        """
        act = getattr(self.env.unwrapped, "default_action", None)
        new_obs, info = self.env.reset()
        if self.obs_preprocessor is not None:
            new_obs = self.obs_preprocessor(new_obs)
        if collect_samples:
            if self.crc_debug:
                self.debug_ts_cpt += 1
                self.debug_ts_res_cpt = 0
                info["crc_sample"] = (None, act, new_obs, 0.0, False, False)
                info["crc_sample_ts"] = (self.debug_ts_cpt, self.debug_ts_res_cpt)
            self._record(act, new_obs, 0.0, False, False, info)
            self.pace.count(1)
        return new_obs, info

    def step(self, obs: Any, test: bool, collect_samples: bool, last_step: bool = False) -> tuple:
        """One transition: act on ``obs``, step the environment, record the sample.

        Args:
            obs: the previous observation.
            test: passed to the actor (deterministic action).
            collect_samples: record the sample for the trainer.
            last_step: the episode is cut after this step: ``truncated`` is set unless ``terminated``.

        Returns:
            ``(new_obs, rew, terminated, truncated, info)``.
        """
        self._check_refused()
        act = self.act(obs, test=test)
        new_obs, rew, terminated, truncated, info = self.env.step(act)
        if self.obs_preprocessor is not None:
            new_obs = self.obs_preprocessor(new_obs)
        if last_step and not terminated:
            truncated = True
        if collect_samples:
            if self.crc_debug:
                self.debug_ts_cpt += 1
                self.debug_ts_res_cpt += 1
                info["crc_sample"] = (obs, act, new_obs, rew, terminated, truncated)
                info["crc_sample_ts"] = (self.debug_ts_cpt, self.debug_ts_res_cpt)
            self._record(act, new_obs, rew, terminated, truncated, info)
            if self.pace.active:
                self._keep_pace(end_of_episode=terminated or truncated)
        return new_obs, rew, terminated, truncated, info

    def _check_refused(self) -> None:
        """Stop (:class:`~tmrl.distributed._common.PasswordRefused`) once the server refused the password."""
        if self._link is not None:
            check_refused(self._link, "worker", f"{self.server_ip}:{self._server_port}")

    def _wait_first_weights(self) -> None:
        """After its first episode, a training worker waits for the trainer's first weights: they
        say which run the samples are for and how fast the trainer wants them (its pace); a
        fast environment would otherwise fill the memory with thousands of samples of the
        initial policy before the trainer has even started."""
        if self._link is None:
            return
        logger.info("waiting for the trainer's first weights")
        started = time.monotonic()
        next_note = started + WAITING_NOTE_INTERVAL
        while self.weights_version == 0 and not self._closed:
            self._check_refused()
            t0 = time.monotonic()
            envelope = self._link.latest_weights(block=True, timeout=1.0)
            if envelope is not None:
                self._load_weights(envelope, verbose=False)
                continue
            now = time.monotonic()
            if now - t0 < 0.5:  # the link's process is gone: do not spin
                time.sleep(0.5)
            if now >= next_note:  # say why nothing happens, and what to start
                next_note = now + WAITING_NOTE_INTERVAL
                if not self.connected:
                    logger.warning("still waiting for the trainer's first weights after %.0f s: no connection to the "
                                   "server at %s yet; is `python -m tmrl --server` running there, with this config's "
                                   "PORT and PASSWORD?", now - started, self.server_ip)
                else:
                    logger.warning("still waiting for the trainer's first weights after %.0f s: connected to the "
                                   "server, no trainer yet; is `python -m tmrl --trainer` running?", now - started)

    def _keep_pace(self, end_of_episode: bool) -> None:
        """Pause while this worker is ahead of the trainer's budget of samples (see :class:`Pace`):
        send what it has, then wait for weights that raise the budget. A real-time environment is
        only paused between episodes (its clock must not stop mid-episode)."""
        self.pace.count(1)
        if not self.pace.exhausted() or not (self._paused_mid_episode or end_of_episode):
            return
        while self.pace.exhausted() and self._link is not None and not self._closed:
            if len(self.buffer):
                self.send_and_clear_buffer()
            self.update_actor_weights(verbose=False, blocking=True)

    @staticmethod
    def _steps(max_samples: float) -> Iterable[int]:
        return itertools.count() if max_samples == math.inf else range(int(max_samples))

    def collect_train_episode(self, max_samples: float | None = None, *, test: bool = False) -> None:
        """Run one train episode of at most ``max_samples`` steps into the buffer (cut episodes
        end with ``truncated=True``) and record its return and length.

        Args:
            max_samples: most steps of the episode (default: ``max_samples_per_episode``).
            test: act with the test (deterministic) policy and report the episode as a test one;
                the samples are collected all the same (see :meth:`run`'s ``test_samples``).
        """
        max_samples = self.max_samples_per_episode if max_samples is None else max_samples
        ret, steps = 0.0, 0
        obs, _ = self.reset(collect_samples=True)
        for i in self._steps(max_samples):
            obs, rew, terminated, truncated, _ = self.step(
                obs, test=test, collect_samples=True, last_step=i == max_samples - 1
            )
            ret += rew
            steps += 1
            if terminated or truncated or self._closed:
                break
            if self.sync_every and steps % self.sync_every == 0 and self._link is not None:
                self.send_and_clear_buffer()
                self.update_actor_weights(verbose=False)
        if test:  # reported as the test episode it is
            self.buffer.stat_test_return, self.buffer.stat_test_steps = ret, steps
        else:
            self.buffer.stat_train_return, self.buffer.stat_train_steps = ret, steps

    def run_episode(self, max_samples: float | None = None, train: bool = False) -> float:
        """Run one episode without recording samples (a test episode unless ``train``); record
        its return and length as test statistics. Returns the episode's return.

        Args:
            max_samples: most steps of the episode (default: ``max_samples_per_episode``).
            train: act with the training (stochastic) policy instead of the test one.
        """
        max_samples = self.max_samples_per_episode if max_samples is None else max_samples
        ret, steps = 0.0, 0
        obs, _ = self.reset(collect_samples=False)
        for _ in self._steps(max_samples):
            obs, rew, terminated, truncated, _ = self.step(obs, test=not train, collect_samples=False)
            ret += rew
            steps += 1
            if terminated or truncated:
                break
        self.buffer.stat_test_return = ret
        self.buffer.stat_test_steps = steps
        return ret

    def run_episodes(
        self, max_samples_per_episode: float | None = None, nb_episodes: float = math.inf, train: bool = False
    ) -> None:
        """Run ``nb_episodes`` episodes with :meth:`run_episode` (deployment).

        Args:
            max_samples_per_episode: most steps per episode (default: the worker's).
            nb_episodes: how many episodes (default: until stopped).
            train: act with the training (stochastic) policy instead of the test one.
        """
        for _ in self._steps(nb_episodes):
            self.run_episode(max_samples_per_episode, train=train)

    def run(
        self,
        test_episode_interval: int = 0,
        nb_episodes: float = math.inf,
        verbose: bool = True,
        expert: bool = False,
        *,
        test_samples: bool = False,
    ) -> None:
        """Collect train episodes, sending each to the server and loading new weights between
        episodes.

        Args:
            test_episode_interval: run a test episode before every ``test_episode_interval``-th
                train episode (0: never; never in CRC debug mode).
            nb_episodes: number of train episodes.
            verbose: log one line per episode at INFO level (DEBUG otherwise).
            expert: send samples but never load weights nor run test episodes.
            test_samples: test episodes collect and send their samples like train episodes (and
                sync every ``sync_every`` steps); ``False`` (tmrl 0.7) drops them. In real time a
                test episode otherwise costs driving time that feeds the trainer nothing.
        """
        summary = EpisodeLog("expert" if expert else "train", level=logging.INFO if verbose else logging.DEBUG)
        for episode in self._steps(nb_episodes):
            if self._closed:  # close() from another thread: stop between episodes
                break
            if (
                not expert
                and test_episode_interval
                and episode % test_episode_interval == 0
                and not self.crc_debug
            ):
                if test_samples:
                    self.collect_train_episode(self.max_samples_per_episode, test=True)
                    self.send_and_clear_buffer()
                    summary.test(self.buffer.stat_test_return, self.buffer.stat_test_steps)
                else:
                    ret = self.run_episode(self.max_samples_per_episode, train=False)
                    summary.test(ret, self.buffer.stat_test_steps)
            sent_before = self.samples_sent
            self.collect_train_episode(self.max_samples_per_episode)
            self.send_and_clear_buffer()
            # counted where samples are handed to the network: the pace may flush mid-episode
            n = self.samples_sent - sent_before
            if expert:
                self.ignore_actor_weights()
            elif episode == 0 and self.weights_version == 0:
                self._wait_first_weights()
            else:
                self.update_actor_weights(verbose=False)
            summary.train(episode, self.buffer.stat_train_return, self.buffer.stat_train_steps, n, self.weights_version)

    def run_synchronous(
        self,
        test_episode_interval: int = 0,
        nb_steps: float = math.inf,
        initial_steps: int = 1,
        max_steps_per_update: float = math.inf,
        end_episodes: bool = True,
        verbose: bool = False,
        *,
        newest_each_episode: bool = True,
    ) -> None:
        """Collect ``nb_steps`` steps while keeping pace with the trainer: at most
        ``max_steps_per_update`` environment steps per model received (for environments that can
        be stepped as fast as wanted).

        Args:
            test_episode_interval: a test episode every ``test_episode_interval`` train episodes
                (0: never; needs ``end_episodes``).
            nb_steps: steps to collect after the initial ones.
            initial_steps: steps collected before waiting for the first model.
            max_steps_per_update: most environment steps per received model (may be fractional).
            end_episodes: only pause (send and wait for a model) between episodes.
            verbose: log at INFO level.
            newest_each_episode: start every episode with the newest weights received, if newer
                ones came. ``False`` is tmrl 0.7's behaviour: weights are loaded only when the
                worker has to wait for them, so a worker ahead of its budget acts with older ones.
                Either way the models are counted when received, so the pace is the same.
        """
        log = logger.info if verbose else logger.debug
        iteration, obs, done = self._collect_initial_samples(initial_steps, end_episodes, log)
        models = self._wait_for_models(iteration, 1, max_steps_per_update, send=True, verbose=verbose)
        iteration, episode, steps, ret = 0, 0, 0, 0.0
        while iteration < nb_steps:
            if done:
                if newest_each_episode:
                    models += self._take_newest(verbose)
                if test_episode_interval > 0 and episode % test_episode_interval == 0 and end_episodes:
                    log("running a test episode")
                    self.run_episode(self.max_samples_per_episode, train=False)
                obs, _ = self.reset(collect_samples=True)
                done, steps, ret = False, 0, 0.0
                iteration += 1
                episode += 1
            while not done:  # _wait_for_models holds the ratio: an episode always runs to its end
                obs, rew, terminated, truncated, _ = self._training_step(obs, steps)
                iteration += 1
                steps += 1
                ret += rew
                done = terminated or truncated
                if not end_episodes:
                    models = self._wait_for_models(iteration, models, max_steps_per_update, send=not done, verbose=verbose)
            if end_episodes:
                models = self._wait_for_models(iteration, models, max_steps_per_update, send=not done, verbose=verbose)
            if done:
                self.buffer.stat_train_return = ret
                self.buffer.stat_train_steps = steps
            self.send_and_clear_buffer()

    def _training_step(self, obs: Any, steps: int) -> tuple:
        """One collecting step of a training episode that has run ``steps`` steps so far."""
        return self.step(obs, test=False, collect_samples=True, last_step=steps == self.max_samples_per_episode - 1)

    def _collect_initial_samples(self, initial_steps: int, end_episodes: bool, log: Callable[..., None]) -> tuple:
        """:meth:`run_synchronous`'s first ``initial_steps`` steps (whole episodes unless
        ``end_episodes`` is False), sent as they end. Returns ``(steps, obs, done)``."""
        iteration, done = 0, False
        obs: Any = None
        while iteration < initial_steps:
            obs, _ = self.reset(collect_samples=True)
            done, steps, ret = False, 0, 0.0
            iteration += 1
            while not done and (end_episodes or iteration < initial_steps):
                obs, rew, terminated, truncated, _ = self._training_step(obs, steps)
                iteration += 1
                steps += 1
                ret += rew
                done = terminated or truncated
            self.buffer.stat_train_return = ret
            self.buffer.stat_train_steps = steps
            log("sending %d initial samples", len(self.buffer))
            self.send_and_clear_buffer()
        return iteration, obs, done

    def _take_newest(self, verbose: bool) -> int:
        """Load the newest weights received, if any; returns how many models they stand for
        (the versions since the current ones: only the newest broadcast is kept)."""
        before = self.weights_version
        if self.update_actor_weights(verbose=verbose, blocking=False):
            return max(1, self.weights_version - before)
        return 0

    def _wait_for_models(self, steps_done: int, models: int, limit: float, send: bool, verbose: bool) -> int:
        """While more than ``limit`` environment steps were taken per model received, send the
        buffer (when ``send``) and wait for the next model. Returns the models received so far."""
        while (steps_done + 1) / models > limit:
            if send:
                self.send_and_clear_buffer()
            before = self.weights_version
            if self.update_actor_weights(verbose=verbose, blocking=True):
                # only the newest broadcast is kept: the versions skipped in between were models
                # too (counting receptions alone waited forever for broadcasts already made)
                models += max(1, self.weights_version - before)
        return models

    def run_env_benchmark(self, nb_steps: int, test: bool = False, verbose: bool = True) -> Any:
        """Step the environment ``nb_steps`` times (one episode at most) and return its
        ``benchmarks()`` (rtgym-style environments created with ``"benchmark": True``).

        Args:
            nb_steps: how many steps (a positive integer).
            test: act with the test (deterministic) policy.
            verbose: accepted for compatibility with tmrl 0.7 (the caller prints the result).

        Raises:
            UserError: ``nb_steps`` is not a positive finite number, or the environment has no
                ``benchmarks()`` method.
        """
        if not isinstance(nb_steps, int) or nb_steps <= 0:
            raise UserError(f"run_env_benchmark needs a positive integer number of steps, got {nb_steps!r}")
        obs, _ = self.reset(collect_samples=False)
        for _ in range(nb_steps):
            obs, _, terminated, truncated, _ = self.step(obs, test=test, collect_samples=False)
            if terminated or truncated:
                break
        bench = getattr(self.env.unwrapped, "benchmarks", None)
        if bench is None:
            raise UserError(
                "this environment has no benchmarks(): benchmarks need a real-time "
                'environment created with "benchmark": true in its config'
            )
        res = bench()
        if verbose:
            logger.info("benchmark results: %s", res)
        return res

    # --- network ---------------------------------------------------------------------------------

    def send_and_clear_buffer(self) -> None:
        """Hand the buffered samples to the network and clear the buffer.

        While the server is unreachable the transport keeps them (bounded) and sends them on
        reconnection. In standalone mode, or once the worker is closed (from another thread while
        it runs), the samples are simply dropped.
        """
        if self._link is None or self._closed:
            self.buffer.clear()
            return
        try:
            payload = pack_buffer(self.buffer, self.source_id, self._seq, run=self.run_id)
            try:
                self._link.send_samples(payload)
            except RuntimeError:
                if not self._closed:
                    raise
                self.buffer.clear()  # closed while sending: the run is over for this worker
                return
        except TypeError as err:
            raise UserError(
                f"a sample holds something that cannot be sent ({err}): keep observations, actions "
                "and info values to numbers, strings, bytes, NumPy arrays and containers of those "
                "(drop the rest in a sample_compressor)"
            ) from err
        self._seq += 1
        self.samples_sent += len(self.buffer)
        self.buffer.clear()

    def _load_weights(self, envelope: bytes, verbose: bool) -> bool:
        """Install received weights through :attr:`installer`; ``False`` when they were refused
        (the current actor is kept)."""
        installed = self.installer.install(self.actor, envelope, self.weights_version, verbose)
        if installed is None:
            return False
        self.actor, msg = installed
        version = msg.get("version")
        self.weights_version = version if type(version) is int else self.weights_version + 1
        run = msg.get("run")
        self.run_id = run if isinstance(run, str) and 0 < len(run) <= 64 else None
        self.pace.update(msg)
        if verbose:
            logger.info("weights updated (version %d)", self.weights_version)
        return True

    def update_actor_weights(self, verbose: bool = True, blocking: bool = False) -> int:
        """Load the newest weights broadcast by the trainer, if any arrived.

        Args:
            verbose: log at INFO level.
            blocking: wait until weights arrive.

        Returns:
            The number of models loaded (0 or 1: only the newest broadcast matters). Weights that
            fail a check (signature, spaces, non-finite values, a file the actor cannot load) are
            not loaded: the worker keeps its actor and logs why (rate-limited); 0 is returned.
        """
        if self._link is None:
            return 0
        while True:
            self._check_refused()
            t0 = time.monotonic()
            envelope = self._link.latest_weights(block=blocking, timeout=1.0 if blocking else None)
            if envelope is not None or not blocking or self._closed:
                break
            if time.monotonic() - t0 < 0.5:  # the link's process is gone: do not spin
                time.sleep(0.5)
        if envelope is None:
            return 0
        return 1 if self._load_weights(envelope, verbose) else 0

    def ignore_actor_weights(self) -> int:
        """Discard weights received from the trainer (expert workers). Returns how many were discarded."""
        if self._link is None:
            return 0
        return 0 if self._link.latest_weights(block=False) is None else 1
