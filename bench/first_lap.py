"""Time to the first lap: the README's Quick start (three command-line roles on ``simlidar``)
against ``python -m tmrl --demo``, on the same track, the same machine, alternating.

    python -m bench first_lap [--rounds 3] [--timeout 900] [--track classic]

Each round runs both, one after the other (the order alternates between rounds), each from a
fresh data folder:

- ``demo``: ``python -m tmrl --demo --track TRACK``; the first lap is read from the demo's own
  status file in its run folder (``worker.json``, ``first_lap_s`` set).
- ``quickstart``: ``python -m tmrl --install --env simlidar`` (not timed), then ``--server``,
  ``--trainer`` and ``--worker -v`` started together, as in the README (with the track and a free
  port given by ``-d``); the first lap is the worker's first episode whose return passes the lap
  bonus (``REWARD_CONFIG.END_OF_TRACK``, 100: a lap of ``classic`` returns about 160, no lap at
  most about 62).

Both figures are seconds from the start of the processes to the first completed lap, taken when
this process sees it (within half a second). Also recorded: the trainer's updates by then, per
second of the run (start-up included, the same for both). The table gives medians with their spread and the load average; the last line is the ratio
the README's figure is held to (the Quick start within 1.5 times the demo's time).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import harness

LAP_RETURN = 100.0  # REWARD_CONFIG.END_OF_TRACK: only a completed lap earns it
EPISODE = re.compile(r"train episode \d+: return (-?[\d.]+) in \d+ steps")
MODES = ("demo", "quickstart")


def _env(work: Path) -> dict[str, str]:
    env = dict(os.environ, TMRL_DATA=str(work / "data"), TMPDIR=str(work / "tmp"), PYTHONUNBUFFERED="1")
    for key in ("TMRL_CONFIG_OVERRIDE", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "TMRL_THREADS"):
        env.pop(key, None)  # what a newcomer's shell has: the roles size their threads themselves
    (work / "tmp").mkdir(parents=True, exist_ok=True)
    return env


def _tmrl(*args: str) -> list[str]:
    return [sys.executable, "-m", "tmrl", *args]


def run_demo(work: Path, track: str, timeout: float, side: harness.Side) -> dict[str, Any]:
    """One demo run until its first lap (or ``timeout`` seconds); what it measured."""
    env = _env(work)
    log = work / "demo.log"
    t0 = time.monotonic()
    proc = harness.start_group(_tmrl("--demo", "--track", track, "--minutes", str(timeout / 60 + 1), "--out",
                                     str(work / "out")), side, log, env=env, cwd=str(work))
    first = updates = None
    try:
        while time.monotonic() - t0 < timeout and proc.poll() is None:
            time.sleep(0.25)  # polling the demo's status file: it is rewritten every 0.5 s
            updates = demo_lapped(work / "tmp")
            if updates is not None:
                first = time.monotonic() - t0
                break
    finally:
        harness.stop_groups([proc], grace=15.0)
    return {"first_lap_s": first, "updates_per_s": updates / first if first else None}


def demo_lapped(tmpdir: Path) -> int | None:
    """The trainer's updates once the demo whose run folder is in ``tmpdir`` has completed a lap,
    else None (from its status files ``worker.json`` and ``trainer.json``)."""
    for folder in sorted(tmpdir.glob("tmrl-demo-*")):
        try:
            worker = json.loads((folder / "worker.json").read_text())
            trainer = json.loads((folder / "trainer.json").read_text())
        except (OSError, ValueError):
            continue
        if worker.get("first_lap_s") is not None:
            return int(trainer.get("updates", 0))
    return None


def worker_lapped(log: str) -> bool:
    """Whether the worker's log (``-v``) shows an episode whose return passes the lap bonus."""
    return any(float(m.group(1)) > LAP_RETURN for m in EPISODE.finditer(log))


def run_quickstart(work: Path, track: str, timeout: float, side: harness.Side) -> dict[str, Any]:
    """The README's Quick start until the worker's first lap (or ``timeout`` seconds)."""
    env = _env(work)
    subprocess.run(_tmrl("--install", "--env", "simlidar"), env=env, cwd=str(work), check=True,
                   stdout=subprocess.DEVNULL)
    override = json.dumps({"PORT": harness.free_port(), "ENV": {"RTGYM_CONFIG": {"interface_kwargs": {"track": track}}}})
    t0 = time.monotonic()
    procs = [harness.start_group(_tmrl(f"--{role}", "-d", override, *extra), side, work / f"{role}.log", env=env,
                                 cwd=str(work))
             for role, extra in (("server", ()), ("trainer", ()), ("worker", ("-v",)))]
    first = ups = None
    try:
        while time.monotonic() - t0 < timeout and all(p.poll() is None for p in procs):
            time.sleep(0.25)  # polling the worker's log: one line per episode
            if worker_lapped((work / "worker.log").read_text(errors="replace")):
                first = time.monotonic() - t0
                ups = _trainer_updates(work / "data") / first
                break
    finally:
        harness.stop_groups(procs, grace=15.0)
    return {"first_lap_s": first, "updates_per_s": ups}


def _trainer_updates(data: Path) -> int:
    """The trainer's updates so far, from its metrics file (the last round's ``total_updates``)."""
    import csv

    total = 0
    for path in data.glob("logs/*/metrics.csv"):
        try:
            with open(path, newline="") as f:
                for row in csv.DictReader(f):
                    total = max(total, int(float(row.get("total_updates") or 0)))
        except (OSError, ValueError):
            pass
    return total


RUNS = {"demo": run_demo, "quickstart": run_quickstart}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench first_lap", description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3, help="runs of each (the README's figure: the median of 3)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds a run may take to its first lap")
    ap.add_argument("--track", default="classic")
    ap.add_argument("--modes", default=",".join(MODES), help="which to run, among demo,quickstart")
    ap.add_argument("--keep", action="store_true", help="keep each run's folder (logs) instead of removing it")
    args = ap.parse_args(argv)
    modes = [m for m in args.modes.split(",") if m]
    unknown = sorted(set(modes) - set(MODES))
    if unknown:
        sys.exit(f"python -m bench first_lap: unknown --modes {unknown}; use demo, quickstart")
    side = harness.ours_side()
    rec = harness.Recorder("first_lap", {"track": args.track, "timeout": args.timeout, "rounds": args.rounds,
                                         "modes": modes, "cores": len(os.sched_getaffinity(0))
                                         if hasattr(os, "sched_getaffinity") else os.cpu_count()})
    case = f"{args.track}, SIMLIDAR"
    for rnd, mode in harness.alternate(modes, args.rounds):
        work = Path(tempfile.mkdtemp(prefix=f"tmrl-first-lap-{mode}-"))
        try:
            res = RUNS[mode](work, args.track, args.timeout, side)
        finally:
            if not args.keep:
                shutil.rmtree(work, ignore_errors=True)
        rec.add(case, "first_lap_s", mode, res["first_lap_s"], round=rnd, higher_is_better=False, unit="s",
                folder=str(work) if args.keep else None)
        rec.add(case, "updates_per_s", mode, res["updates_per_s"], round=rnd, unit="1/s")
    rows = rec.print_table(ratios=(("quickstart", "demo"),))
    med = {r["side"]: r["median"] for r in rows if r["metric"] == "first_lap_s"}
    if med.get("quickstart") and med.get("demo"):
        ratio = med["quickstart"] / med["demo"]
        print(f"\nfirst lap, Quick start / demo (medians): {ratio:.2f} (the README's bar: at most 1.5)")
    rec.close()
