"""Plot a run's learning curve from its metrics (CSV always, TensorBoard events when installed).

    python examples/metrics_plot.py my_run                       # <data folder>/logs/my_run/metrics.csv
    python examples/metrics_plot.py path/to/metrics.csv --out curve.png
    python examples/metrics_plot.py --demo-data                  # first a tiny real run on Pendulum

A ``tmrl.metrics.MetricsLogger`` given a data folder appends one row per training round to
``<data folder>/logs/<run_name>/metrics.csv`` (and writes TensorBoard events next to it when
tensorboard is installed). This script reads them and draws the return against the environment
steps, and the losses against the training steps, into a PNG.

``--demo-data`` first runs tmrl's three roles (server, trainer, one worker) in this process on
Pendulum-v1 for a few rounds, with a MetricsLogger fed by a trainer callback, so that there is a
CSV to plot. The data folder is ``$TMRL_DATA`` (default ``~/TmrlData``).
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import math
import secrets
import socket
import sys
import threading
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no window
import matplotlib.pyplot as plt

from tmrl.config.loader import data_folder
from tmrl.metrics import MetricsLogger

DEMO_RUN = "metrics_plot_demo"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def demo_run(folder: Path, rounds: int) -> Path:
    """Train SAC on Pendulum-v1 for one epoch of ``rounds`` rounds, logging to ``folder``;
    returns the CSV path."""
    import torch

    from tmrl.algorithms.sac import SACAgent
    from tmrl.envs import GenericGymEnv
    from tmrl.memory import GenericTorchMemory
    from tmrl.models import MLPActorCritic, SquashedGaussianMLPActor
    from tmrl.networking import RolloutWorker, Server, Trainer
    from tmrl.training_offline import TorchTrainingOffline
    from tmrl.util import partial

    torch.set_num_threads(1)  # trainer and worker share this process: one thread each is enough
    hidden = (64, 64)
    port, password = _free_port(), secrets.token_hex(16)
    net = {"server_ip": "127.0.0.1", "server_port": port, "password": password, "security": None}
    training_cls = partial(
        TorchTrainingOffline,
        env_cls=partial(GenericGymEnv, id="Pendulum-v1"),
        memory_cls=partial(GenericTorchMemory, memory_size=100_000, batch_size=64),
        training_agent_cls=partial(SACAgent, model_cls=partial(MLPActorCritic, hidden_sizes=hidden)),
        epochs=1, rounds=rounds, steps=100,
        update_buffer_interval=10, update_model_interval=10,
        max_training_steps_per_env_step=1.0, start_training=200,
        sleep_between_buffer_retrieval_attempts=0.01, device="cpu",
    )
    # --8<-- [start:logger]
    metrics = MetricsLogger(DEMO_RUN, folder=folder, console=False)  # TensorBoard too, when installed
    server = Server(port=port, password=password, security=None)
    trainer = Trainer(training_cls=training_cls, model_path=str(folder / "weights" / f"{DEMO_RUN}_t.tmod"),
                      checkpoint_path=None, **net)
    trainer.add_callback(lambda round_metrics: metrics.log_round(round_metrics.as_row()))
    # --8<-- [end:logger]
    worker = RolloutWorker(env_cls=partial(GenericGymEnv, id="Pendulum-v1"),
                           actor_module_cls=partial(SquashedGaussianMLPActor, hidden_sizes=hidden),
                           max_samples_per_episode=200, model_history=0,
                           model_path=str(folder / "weights" / f"{DEMO_RUN}.tmod"), **net)
    threading.Thread(target=worker.run_synchronous, kwargs={"initial_steps": 200, "max_steps_per_update": 20,
                                                            "end_episodes": False}, daemon=True).start()
    try:
        trainer.run()
    finally:
        metrics.close()
        worker.close()
        server.stop()
    assert metrics.csv_path is not None
    return metrics.csv_path


# --8<-- [start:read]
def read_csv(path: Path) -> dict[str, list[float]]:
    """The CSV's columns as lists of floats (an empty cell, a metric that had no value, is NaN)."""
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    columns: dict[str, list[float]] = {name: [] for name in (rows[0] if rows else {})}
    for row in rows:
        for name, values in columns.items():
            try:
                values.append(float(row[name]))
            except (TypeError, ValueError):
                values.append(math.nan)
    return columns


def read_tensorboard(run_folder: Path) -> dict[str, list[tuple[int, float]]] | None:
    """TensorBoard scalars ``{tag: [(step, value), ...]}``, or None when tensorboard is not
    installed or the run has no events."""
    if importlib.util.find_spec("tensorboard") is None:
        return None
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = run_folder / "tensorboard"
    if not events.is_dir():
        return None
    acc = EventAccumulator(str(events))
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}
# --8<-- [end:read]


# --8<-- [start:plot]
def plot(columns: dict[str, list[float]], out: Path, title: str) -> list[str]:
    """Return against environment steps (left), losses against training steps (right); returns
    the labels of the curves drawn."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    for kind in ("train", "test"):
        # Until a worker reports an episode of this kind, its return reads 0 and its length 0.
        returns, lengths = columns.get(f"return_{kind}", []), columns.get(f"episode_length_{kind}", [])
        points = [(x, r) for x, r, n in zip(columns["total_samples"], returns, lengths) if n > 0]
        if points:
            left.plot(*zip(*points), marker="o", label=f"{kind} episodes")
    left.set_xlabel("environment steps (samples received by the trainer)")
    left.set_ylabel("episode return (sum of rewards)")
    left.set_title("learning curve")
    left.legend()
    for name in ("loss_actor", "loss_critic"):
        if name in columns:
            right.plot(columns["total_updates"], columns[name], marker=".", label=name)
    right.set_xlabel("training steps (updates)")
    right.set_ylabel("loss (mean over the round, no unit)")
    right.set_title("losses")
    right.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return [line.get_label() for ax in (left, right) for line in ax.get_lines()]
# --8<-- [end:plot]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", nargs="?", help="a run name (in the data folder) or a metrics.csv path")
    parser.add_argument("--demo-data", action="store_true", help="first make a tiny real run to plot")
    parser.add_argument("--demo-rounds", type=int, default=6,
                        help="rounds of 100 training steps in the demo run")
    parser.add_argument("--out", type=Path, default=Path("learning_curve.png"))
    args = parser.parse_args()

    if args.demo_data:
        csv_path = demo_run(data_folder(), args.demo_rounds)
        print(f"demo run: wrote {csv_path}")
    elif args.run is None:
        parser.error("give a run name or a CSV path, or --demo-data")
    elif args.run.endswith(".csv") or Path(args.run).is_file():
        csv_path = Path(args.run)
    else:
        csv_path = data_folder() / "logs" / args.run / "metrics.csv"
    if not csv_path.is_file():
        print(f"no metrics file at {csv_path}", file=sys.stderr)
        return 1

    columns = read_csv(csv_path)
    n_rows = len(next(iter(columns.values()), []))
    print(f"csv: {n_rows} rows, columns: {', '.join(columns)}")
    for needed in ("total_samples", "total_updates", "return_train"):
        if needed not in columns:
            print(f"the CSV has no {needed} column: is it a tmrl metrics file?", file=sys.stderr)
            return 1
    scalars = read_tensorboard(csv_path.parent)
    if importlib.util.find_spec("tensorboard") is None:
        print("tensorboard: not installed, events not read (the CSV holds the same scalars)")
    elif scalars is None:
        print(f"tensorboard: no events in {csv_path.parent / 'tensorboard'}")
    else:
        print(f"tensorboard: {len(scalars)} scalar series, e.g. return_train at steps "
              f"{[s for s, _ in scalars.get('return_train', [])]}")
    last = columns["return_train"][-1]
    print(f"last round: {columns['total_samples'][-1]:.0f} samples, "
          f"{columns['total_updates'][-1]:.0f} updates, return_train {last:.1f}")
    curves = plot(columns, args.out, title=f"run {csv_path.parent.name}")
    print(f"plot: wrote {args.out} (curves: {', '.join(curves)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
