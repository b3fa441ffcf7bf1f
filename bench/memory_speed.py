"""Replay-memory speed (ours): append throughput, ``sample()`` time for a batch, checkpoint time
of a big memory (first save, incremental save, load).

    python -m bench memory_speed                       # 1M samples, 3 rounds
    python -m bench memory_speed --size 200000 --act-buf-len 0   # GenericTorchMemory
    git worktree add /tmp/tmrl-before HEAD~1
    python -m bench memory_speed --before /tmp/tmrl-before   # before/after a change, both whole trees

Observations look like the lidar driving environment: speed (1,), lidar history (4, 19) float32,
then an action buffer rebuilt by RealTimeTorchMemory. Needs about 1 GB of RAM and of disk per
million samples. Each round builds a fresh memory; the table gives medians over rounds.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from bench import harness


class _Buf:
    """The part of ``tmrl.networking.Buffer`` that memories read."""

    def __init__(self, samples: list) -> None:
        self.memory = samples
        self.sources = None
        self.stat_train_return = self.stat_test_return = 0.0
        self.stat_train_steps = self.stat_test_steps = 0

    def __len__(self) -> int:
        return len(self.memory)


def _samples(n: int, start: int, rng: Any, episode_len: int = 1000) -> list[tuple]:
    import numpy as np

    speeds = rng.random((n, 1), dtype=np.float32)
    lidars = rng.random((n, 4, 19), dtype=np.float32)
    acts = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    out = []
    for k in range(n):
        t = (start + k) % episode_len
        out.append((acts[k], (speeds[k], lidars[k]), float(t), t == episode_len - 1, False, {}))
    return out


class _TinyAgent:
    """What a checkpoint needs of an agent."""

    def __init__(self) -> None:
        import torch

        self.model = torch.nn.Linear(100, 3)
        self.optimizer = torch.optim.Adam(self.model.parameters())

    def state_dict(self) -> dict[str, Any]:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])


def _timed(fn: Any, repeat: int = 1) -> float:
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


def one_round(args: argparse.Namespace, rnd: int, rec: harness.Recorder, side: str = "ours") -> None:
    import numpy as np
    import torch

    import tmrl.memory as mod
    from tmrl.checkpoint import load_checkpoint, save_checkpoint

    def make_memory() -> Any:
        if args.act_buf_len > 0:
            return mod.RealTimeTorchMemory(act_buf_len=args.act_buf_len, memory_size=args.size,
                                           batch_size=args.batch_size)
        return mod.GenericTorchMemory(memory_size=args.size, batch_size=args.batch_size)

    torch.set_num_threads(1)
    rng = np.random.default_rng(rnd)
    memory = make_memory()
    case = f"{type(memory).__name__} {args.size:,} samples"
    append = 0.0
    for start in range(0, args.size, 50_000):
        buf = _Buf(_samples(min(50_000, args.size - start), start, rng))
        append += _timed(lambda b=buf: memory.append(b))
    rec.add(case, "append_samples_per_s", side, args.size / append, round=rnd, unit="1/s")
    memory.sample()  # warm-up (valid-index cache)
    rec.add(case, f"sample_ms_batch_{args.batch_size}", side, 1000 * _timed(memory.sample, 200), round=rnd,
            higher_is_better=False, unit="ms")
    folder = Path(tempfile.mkdtemp(prefix="tmrl-bench-"))
    training = SimpleNamespace(agent=_TinyAgent(), memory=memory, epoch=1, total_updates=0, total_samples=args.size)
    try:
        target = folder / "ckpt"
        rec.add(case, "checkpoint_first_save_s", side, _timed(lambda: save_checkpoint(training, target)),
                round=rnd, higher_is_better=False, unit="s",
                bytes_on_disk=sum(p.stat().st_size for p in target.iterdir()))
        memory.append(_Buf(_samples(10_000, args.size, rng)))
        training.epoch = 2
        rec.add(case, "checkpoint_save_after_10k_new_s", side, _timed(lambda: save_checkpoint(training, target)),
                round=rnd, higher_is_better=False, unit="s")
        restored = SimpleNamespace(agent=_TinyAgent(), memory=make_memory(), epoch=0, total_updates=0,
                                   total_samples=0, run_epoch=None)
        rec.add(case, "checkpoint_load_s", side, _timed(lambda: load_checkpoint(target, restored)), round=rnd,
                higher_is_better=False, unit="s")
        assert restored.memory.total == memory.total
    finally:
        shutil.rmtree(folder, ignore_errors=True)


class _Forward:
    """The recorder of a child process: each measurement goes to the parent as one result line."""

    def add(self, case: str, metric: str, side: str, value: float | None, **extra: Any) -> None:
        harness.answer({"case": case, "metric": metric, "side": side, "value": value, **extra})


def child_main(argv: list[str]) -> None:
    """One round in a child process of one side (``--before``): ``argv`` is the settings as JSON."""
    settings = json.loads(argv[0])
    rnd, side = settings.pop("_round"), settings.pop("_side")
    one_round(argparse.Namespace(**settings), rnd, _Forward(), side)  # type: ignore[arg-type]


def _round_in(side: harness.Side, args: argparse.Namespace, rnd: int, rec: harness.Recorder) -> None:
    """Run one round in ``side``'s tree and record what it measured."""
    cmd = side.command("memory_speed", json.dumps({**vars(args), "_round": rnd, "_side": side.name}))
    out = subprocess.run(cmd, env=side.env, cwd=side.cwd, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"the {side.name} side failed:\n{out.stderr[-3000:]}")
    for line in out.stdout.splitlines():
        if line.startswith(harness.RESULT):
            m = json.loads(line[len(harness.RESULT):])
            rec.add(m.pop("case"), m.pop("metric"), m.pop("side"), m.pop("value"), **m)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench memory_speed", description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1_000_000, help="samples in the memory")
    ap.add_argument("--batch-size", type=int, default=256)
    ap.add_argument("--act-buf-len", type=int, default=2, help="0: GenericTorchMemory")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--before", metavar="CHECKOUT", default=None,
                    help="an earlier commit of this repository checked out there (git worktree add): both sides "
                         "then run each round in a fresh child process on their own tree, labelled ours and before")
    args = ap.parse_args(argv)
    rec = harness.Recorder("memory_speed", vars(args))
    settings = argparse.Namespace(**{k: v for k, v in vars(args).items() if k != "before"})
    if args.before:  # both sides in fresh child processes, one per round: the same conditions
        sides = [harness.ours_side(), harness.before_side(args.before)]
        for rnd, side in harness.alternate(sides, args.rounds):
            _round_in(side, settings, rnd, rec)
    else:
        for rnd in range(args.rounds):
            one_round(args, rnd, rec)
    rec.print_table(ratios=(("ours", "before"),) if args.before else ())
    rec.close()
