"""Regenerate what docs/first_hour.md shows: run the demo and the Quick start's three roles on
this machine, then copy their status lines and pictures into the page.

    python docs/generate_first_hour.py [--minutes 3]

It writes ``docs/images/demo_learning_curve.png``, ``docs/images/demo_best_lap.png`` and
``docs/images/quickstart_learning_curve.png``, and replaces the text between the
``<!-- generated: NAME -->`` and ``<!-- end: NAME -->`` markers of docs/first_hour.md. Nothing in
it is drawn by hand: every line and picture comes from a run.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DOCS = Path(__file__).resolve().parent
PAGE = DOCS / "first_hour.md"
IMAGES = DOCS / "images"


def _run_demo(minutes: float, work: Path) -> list[str]:
    out = work / "demo"
    env = dict(os.environ, TMRL_DATA=str(work / "demo_data"))
    proc = subprocess.run([sys.executable, "-m", "tmrl", "--demo", "--minutes", str(minutes), "--out", str(out)],
                          capture_output=True, text=True, env=env, check=True)
    IMAGES.mkdir(exist_ok=True)
    shutil.copyfile(out / "learning_curve.png", IMAGES / "demo_learning_curve.png")
    shutil.copyfile(out / "best_lap.png", IMAGES / "demo_best_lap.png")
    # the output folder is a temporary one: show it as --out names it
    lines = [ln.replace(str(out), "<out>") for ln in proc.stdout.splitlines() if ln.strip()]
    status = [ln for ln in lines if " s | episodes" in ln]
    # the first status lines, one every minute after that, and the summary
    keep = status[:3] + status[3::6] + [ln for ln in lines if " s | episodes" not in ln]
    return [ln for ln in keep if not ln.startswith("tmrl demo:") or "finished" in ln or "stopped" in ln]


def _run_quickstart(minutes: float, work: Path) -> tuple[list[str], list[str]]:
    data = work / "qs_data"
    env = dict(os.environ, TMRL_DATA=str(data))
    subprocess.run([sys.executable, "-m", "tmrl", "--install", "--env", "simlidar"], env=env, check=True,
                   capture_output=True)
    cfg_file = data / "config" / "config.json"
    cfg = json.loads(cfg_file.read_text())
    cfg["PORT"] = 20000 + os.getpid() % 20000
    cfg_file.write_text(json.dumps(cfg, indent=2))
    logs = {role: open(work / f"{role}.log", "w") for role in ("server", "trainer", "worker")}
    procs = {}
    try:
        for role in ("server", "trainer", "worker"):
            procs[role] = subprocess.Popen([sys.executable, "-m", "tmrl", f"--{role}"], env=env,
                                           stdout=logs[role], stderr=subprocess.STDOUT)
            time.sleep(2.0 if role == "server" else 0.0)
        time.sleep(minutes * 60)
    finally:
        for proc in procs.values():
            proc.send_signal(signal.SIGINT)
        for proc in procs.values():
            proc.wait(30)
        for f in logs.values():
            f.close()
    trainer = (work / "trainer.log").read_text().splitlines()
    worker = (work / "worker.log").read_text().splitlines()
    rounds = [ln for ln in trainer if "tmrl.metrics" in ln]
    shown_trainer = [ln for ln in trainer if "training starts" in ln] + rounds[:2] + rounds[-2:]
    shown_worker = [ln for ln in worker if "tmrl.networking" in ln and ("episode" in ln or "waiting" in ln)]
    returns = [float(m.group(1)) for ln in trainer for m in [re.search(r"return train ([-\d.]+)", ln)] if m]
    from tmrl.sim.charts import Series, learning_curve_chart
    from tmrl.sim.render import write_png

    import numpy as np

    x = np.arange(1, len(returns) + 1)
    write_png(IMAGES / "quickstart_learning_curve.png", learning_curve_chart(
        [Series(x, np.asarray(returns), (20, 60, 180), "RETURN TRAIN", 2)], "QUICK START: SIMLIDAR, THREE ROLES",
        "ROUND (200 UPDATES)", "RETURN", [f"TRAINER'S ROUNDS OVER {minutes:g} MIN"]))
    return shown_trainer, shown_worker[:6]


def _strip_time(line: str) -> str:
    return re.sub(r"^\d\d:\d\d:\d\d ", "", line)


def _replace(page: str, name: str, lines: list[str]) -> str:
    block = "```text\n" + "\n".join(_strip_time(ln) for ln in lines) + "\n```"
    pattern = re.compile(rf"(<!-- generated: {name} -->\n).*?(\n<!-- end: {name} -->)", re.S)
    if not pattern.search(page):
        raise SystemExit(f"docs/first_hour.md has no generated: {name} markers")
    return pattern.sub(lambda m: m.group(1) + block + m.group(2), page)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=3.0, help="length of each run (default 3)")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="tmrl-first-hour-"))
    demo = _run_demo(args.minutes, work)
    trainer, worker = _run_quickstart(args.minutes, work)
    page = PAGE.read_text()
    for name, lines in (("demo", demo), ("trainer", trainer), ("worker", worker)):
        page = _replace(page, name, lines)
    PAGE.write_text(page)
    shutil.rmtree(work, ignore_errors=True)
    print(f"updated {PAGE} and the pictures in {IMAGES}")


if __name__ == "__main__":
    main()
