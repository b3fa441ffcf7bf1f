"""The harness every benchmark runs on.

What it guarantees, so that a figure can be checked:

- **Sides** (:class:`Side`): this tmrl, the original tmrl 0.7.1, Stable-Baselines3 or rtgym, each
  run by its own interpreter in its own processes (``bench/anchors/install_*.sh`` install the
  others), with one settings dict applied to every side.
- **Alternating order** (:func:`alternate`): round 1 runs the sides in order, round 2 in reverse,
  and so on, so that a load that rises or falls during the run favours no side.
- **Medians and spread** (:class:`Recorder`): every measurement is recorded with the load average
  at that moment; the table gives, per figure and side, the median, min and max over the rounds
  and the load average range, plus ratios of medians.
- **A machine-readable result**: every record goes to ``bench/out/NAME-<timestamp>.jsonl`` as it
  is taken (``{"kind": "measure", ...}``), followed by the summary rows (``{"kind": "summary"}``).

Only the standard library is imported here: the harness also runs inside the other sides'
interpreters, where this project's dependencies may be missing (:func:`resolve_device` and
:func:`device_settings` import our tmrl or torch when called, in the parent only).

- **One device per record**: ``--device`` (:func:`add_device_argument`) puts every side's memory
  and agent on the same device; the record's settings name it (and the GPU), and so does the
  first line a benchmark prints.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import queue
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, TypeVar

REPO = Path(__file__).resolve().parent.parent
BENCH = REPO / "bench"
OUT = BENCH / "out"
CHILD = BENCH / "_child.py"
RESULT = "@@RESULT "

DEFAULT_ANCHOR_DIR = "/tmp/tmrl-anchor"
DEFAULT_SB3_DIR = "/tmp/sb3-anchor"
DEFAULT_RTGYM_PYTHON = DEFAULT_ANCHOR_DIR + "/venv/bin/python"  # install_tmrl.sh installs rtgym beside tmrl 0.7.1

T = TypeVar("T")


# --- sides ----------------------------------------------------------------------------------------


@dataclass
class Side:
    """One implementation under test and how to start its processes.

    Attributes:
        name: label in tables and records (``ours``, ``tmrl``, ``sb3``, ``rtgym``).
        python: its interpreter.
        env: environment of its processes.
        cwd: working directory of its processes (outside this repository for the other sides, so
            that ``import tmrl`` finds the installed original, not this checkout).
    """

    name: str
    python: str
    env: dict[str, str]
    cwd: str

    def command(self, module: str, *args: str) -> list[str]:
        """The command that runs ``bench.<module>``'s ``child_main(args)`` in this side's
        interpreter (see ``bench/_child.py``)."""
        return [self.python, str(CHILD), module, *args]


def ours_side(python: str | None = None) -> Side:
    """This checkout's tmrl, run by ``python`` (default: the current interpreter)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return Side("ours", python or sys.executable, env, str(REPO))


def before_side(checkout: str) -> Side:
    """An earlier commit of this repository, checked out at ``checkout`` (``git worktree add
    /tmp/tmrl-before COMMIT``), measured by this checkout's benchmark code: the "before" of a
    before/after comparison of a change.

    Raises:
        SystemExit: ``checkout`` holds no tmrl package.
    """
    root = Path(checkout).resolve()
    if not (root / "tmrl" / "__init__.py").is_file():
        raise SystemExit(f"no tmrl package in {root}: pass a checkout of this repository (git worktree add)")
    env = _other_env()
    env["PYTHONPATH"] = str(root)
    return Side("before", sys.executable, env, str(root))


def _other_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "TMRL_DATA", "TMRL_CONFIG_OVERRIDE")}
    env.update(extra)
    return env


def tmrl_side(anchor_dir: str) -> Side:
    """The original tmrl 0.7.1 installed by ``bench/anchors/install_tmrl.sh anchor_dir``, with its
    own home (its TmrlData never touches yours).

    Raises:
        SystemExit: it is not installed there.
    """
    python = Path(anchor_dir) / "venv" / "bin" / "python"
    if not python.exists():
        raise SystemExit(
            f"no tmrl 0.7.1 at {python}: run `bash bench/anchors/install_tmrl.sh {anchor_dir}` "
            "(or pass --anchor-dir, or --no-tmrl)"
        )
    return Side("tmrl", str(python), _other_env(HOME=str(Path(anchor_dir) / "home")), str(anchor_dir))


def sb3_side(sb3_dir: str) -> Side:
    """Stable-Baselines3 installed by ``bench/anchors/install_sb3.sh sb3_dir``.

    Raises:
        SystemExit: it is not installed there.
    """
    python = Path(sb3_dir) / "venv" / "bin" / "python"
    if not python.exists():
        raise SystemExit(
            f"no Stable-Baselines3 at {python}: run `bash bench/anchors/install_sb3.sh {sb3_dir}` "
            "(or pass --sb3-dir, or --no-sb3)"
        )
    return Side("sb3", str(python), _other_env(), str(sb3_dir))


def rtgym_side(python: str) -> Side:
    """rtgym, installed in the venv of ``python``.

    Raises:
        SystemExit: ``python`` does not exist.
    """
    if not Path(python).exists():
        raise SystemExit(
            f"{python} not found: run `bash bench/anchors/install_tmrl.sh` (it installs rtgym too), "
            "or pass --rtgym-python"
        )
    return Side("rtgym", python, _other_env(), str(Path(python).parent))


def add_side_arguments(parser: argparse.ArgumentParser, tmrl: bool = True, sb3: bool = False) -> None:
    """``--anchor-dir``/``--no-tmrl`` and ``--sb3-dir``/``--no-sb3`` options."""
    if tmrl:
        parser.add_argument("--anchor-dir", default=DEFAULT_ANCHOR_DIR,
                            help="where bench/anchors/install_tmrl.sh installed tmrl 0.7.1")
        parser.add_argument("--no-tmrl", action="store_true", help="leave tmrl 0.7.1 out")
    if sb3:
        parser.add_argument("--sb3-dir", default=DEFAULT_SB3_DIR,
                            help="where bench/anchors/install_sb3.sh installed Stable-Baselines3")
        parser.add_argument("--no-sb3", action="store_true", help="leave Stable-Baselines3 out")
    parser.add_argument("--before", metavar="CHECKOUT", default=None,
                        help="also an earlier commit of this repository checked out there (git worktree add), "
                             "labelled before, measured by this checkout's benchmark code")


def add_device_argument(parser: argparse.ArgumentParser, default: str) -> None:
    """``--device cpu|cuda|cuda:N|auto``: where every side's memory and agent train (``auto``:
    the GPU when PyTorch sees one); resolved by :func:`resolve_device`."""
    parser.add_argument("--device", default=default, metavar="DEVICE",
                        help=f"cpu, cuda, cuda:N or auto (the GPU when there is one); every side trains there "
                             f"(default: {default})")


def resolve_device(parser: argparse.ArgumentParser, device: str) -> str:
    """The torch device ``--device`` names on this machine (``auto`` resolved), checked by our
    tmrl's :func:`tmrl.util.resolve_device`; a device this machine lacks ends the command with
    the parser's one-line error. Run by the parent only (it imports our tmrl): each side's child
    is handed the resolved name."""
    from tmrl.errors import UserError
    from tmrl.util import resolve_device as resolve

    try:
        return resolve(device)
    except UserError as e:
        parser.error(str(e))
        raise  # unreachable: parser.error exits


def device_settings(device: str) -> dict[str, Any]:
    """What a record says of the device its figures were taken on: ``{"device": "cpu"}``, or for
    a GPU also its name, driver, and the CUDA and PyTorch versions (a GPU figure is never compared
    with a CPU one: :class:`Recorder` names the device in its first line and its header)."""
    if not device.startswith("cuda"):
        return {"device": device}
    import torch  # the parent's own torch (our interpreter), asked only for a GPU run

    index = int(device.split(":")[1]) if ":" in device else 0
    driver = None
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader", "-i", str(index)],
                             capture_output=True, text=True, timeout=30, check=False)
        driver = out.stdout.strip() or None
    except (OSError, subprocess.TimeoutExpired):
        pass
    return {"device": device, "gpu": torch.cuda.get_device_name(index), "gpu_driver": driver,
            "cuda": torch.version.cuda, "torch": torch.__version__}


def sides_from_args(args: argparse.Namespace) -> list[Side]:
    """Ours, then each other side the options ask for (their installs checked now)."""
    sides = [ours_side()]
    if hasattr(args, "no_tmrl") and not args.no_tmrl:
        sides.append(tmrl_side(args.anchor_dir))
    if hasattr(args, "no_sb3") and not args.no_sb3:
        sides.append(sb3_side(args.sb3_dir))
    if getattr(args, "before", None):
        sides.append(before_side(args.before))
    return sides


def alternate(items: Sequence[T], rounds: int) -> Iterator[tuple[int, T]]:
    """``(round, item)``: every item once per round, in order on even rounds and in reverse on odd
    ones (ABBA), so that a drift of the machine's load favours none."""
    for rnd in range(rounds):
        for item in items if rnd % 2 == 0 else list(reversed(items)):
            yield rnd, item


def load_averages() -> tuple[float, float, float]:
    """The 1-, 5- and 15-minute load averages (NaN on Windows, which keeps none)."""
    if hasattr(os, "getloadavg"):
        return os.getloadavg()
    return (math.nan, math.nan, math.nan)


def load_average() -> float:
    """The 1-minute load average (NaN on Windows)."""
    return load_averages()[0]


#: The packages whose versions a record's header names (the numbers of a learning run depend on them).
INSTALL_PACKAGES = ("torch", "numpy", "gymnasium", "tmrl-cleanroom", "tmrl")  # this project; the original where installed


def install() -> dict[str, Any]:
    """What a record's figures depend on besides the code and the seed: the Python and package
    versions, the CPU model and when this virtual environment was made. Learning runs are exact on
    one install, not across installs (docs/benchmarks.md: the same seeds on another install)."""
    from importlib import metadata

    packages: dict[str, str | None] = {}
    for name in INSTALL_PACKAGES:
        try:
            packages[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            packages[name] = None
    cpu = None
    if sys.platform.startswith("linux"):  # the model name; elsewhere platform.processor() below says it
        try:
            with open("/proc/cpuinfo", encoding="utf-8") as f:
                cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), None)
        except OSError:
            pass
    cfg = Path(sys.prefix) / "pyvenv.cfg"
    made = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(cfg.stat().st_mtime)) if cfg.exists() else None
    return {"python": platform.python_version(), "packages": packages, "cpu": cpu or platform.processor() or None,
            "environment": sys.prefix, "environment_made": made}


# --- records and the table ------------------------------------------------------------------------


@dataclass
class Recorder:
    """Collects measurements, writes them as JSON lines and prints the summary table.

    Args:
        bench: the benchmark's name (file name prefix).
        settings: the settings applied to every side (written in the header record); a
            ``"device"`` key (and ``"gpu"``, :func:`device_settings`) is named in the first line.
        out_dir: where the ``.jsonl`` file goes.
    """

    bench: str
    settings: dict[str, Any]
    out_dir: Path = OUT
    records: list[dict[str, Any]] = field(default_factory=list)
    path: Path = field(init=False)
    _file: IO[str] = field(init=False)
    _better: dict[str, bool] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        # Created exclusively: a second command started in the same second gets "-2" (and so on),
        # not the first one's file (its figure would overwrite the first one's too).
        for n in range(1, 1000):
            self.path = self.out_dir / f"{self.bench}-{stamp}{'' if n == 1 else f'-{n}'}.jsonl"
            try:
                self._file = open(self.path, "x", encoding="utf-8")  # noqa: SIM115 (closed in close())
                break
            except FileExistsError:
                continue
        else:
            raise FileExistsError(f"{self.path}: 999 records of {self.bench} started in one second")
        self._write({
            "kind": "run", "bench": self.bench, "settings": self.settings, "argv": sys.argv[1:],
            "started": time.strftime("%Y-%m-%d %H:%M:%S"), "cpus": os.cpu_count(),
            "machine": platform.processor() or platform.machine(), "load_average": load_averages(),
            "install": install(),
        })
        where = ""
        if "device" in self.settings:
            gpu = self.settings.get("gpu")
            where = f" on {self.settings['device']}" + (f" ({gpu})" if gpu else "")
        print(f"{self.bench}{where}: load average {_loads()} at start; results also go to {self.path}", flush=True)

    def _write(self, record: dict[str, Any]) -> None:
        self._file.write(json.dumps(record, default=str) + "\n")
        self._file.flush()

    def add(self, case: str, metric: str, side: str, value: float | None, *, round: int | None = None,
            higher_is_better: bool = True, unit: str = "", echo: bool = True, **extra: Any) -> None:
        """Record one measurement (``None``: not reached / failed), with the load average now.

        Args:
            case: what was measured (e.g. ``"pendulum/sac full"``).
            metric: the figure's name (e.g. ``"updates_per_s"``).
            side: which side.
            value: the figure.
            round: the round or seed it belongs to.
            higher_is_better: how ratios between sides read.
            unit: shown beside the value.
            echo: also print one line now.
            extra: more fields for the JSON record.
        """
        rec = {"kind": "measure", "case": case, "metric": metric, "side": side, "value": value,
               "round": round, "unit": unit, "load1": load_average(), "t": time.strftime("%H:%M:%S"), **extra}
        self._better[metric] = higher_is_better
        self.records.append(rec)
        self._write(rec)
        if echo:
            shown = fmt(value)
            print(f"  [{case}] {side:18s} {metric} = {shown} {unit}  (round {round}, load {rec['load1']:.2f})",
                  flush=True)

    def summary(self) -> list[dict[str, Any]]:
        """Per (case, metric, side): median, min, max over the recorded values that are not None,
        how many there were and the load average range."""
        groups: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
        for r in self.records:
            groups.setdefault((r["case"], r["metric"], r["side"]), []).append(r)
        rows = []
        for (case, metric, side), recs in groups.items():
            values = [r["value"] for r in recs if r["value"] is not None]
            loads = [r["load1"] for r in recs]
            rows.append({
                "kind": "summary", "case": case, "metric": metric, "side": side, "unit": recs[0]["unit"],
                "median": statistics.median(values) if values else None,
                "min": min(values) if values else None, "max": max(values) if values else None,
                "n": len(values), "of": len(recs), "load_min": min(loads), "load_max": max(loads),
                "higher_is_better": self._better.get(metric, True),
            })
        return rows

    def print_table(self, ratios: Iterable[tuple[str, str]] = (("ours", "tmrl"),)) -> list[dict[str, Any]]:
        """Print the summary (and ``a vs b`` ratios of medians, > 1 when ``a`` is better), write
        it to the JSON lines file, and return its rows."""
        rows = self.summary()
        print(f"\n{self.bench}: medians [min .. max] over rounds, load average beside each; now {_loads()}")
        by_figure: dict[tuple[str, str], list[dict[str, Any]]] = {}
        for row in rows:
            by_figure.setdefault((row["case"], row["metric"]), []).append(row)
        for (case, metric), figure in by_figure.items():
            print(f"{case} | {metric}")
            med = {}
            for row in figure:
                med[row["side"]] = row["median"]
                spread = "" if row["median"] is None else f"[{fmt(row['min'])} .. {fmt(row['max'])}]"
                shown = fmt(row["median"])
                count = f"n={row['n']}" + (f" of {row['of']}" if row["of"] != row["n"] else "")
                print(f"    {row['side']:18s} {shown:>10} {row['unit']:6s} {spread:24s} {count:10s}"
                      f" load {row['load_min']:.2f}-{row['load_max']:.2f}")
            for a, b in ratios:
                if med.get(a) is None or med.get(b) is None:
                    continue
                if med[a] > 0 and med[b] > 0:
                    r = med[a] / med[b] if figure[0]["higher_is_better"] else med[b] / med[a]
                    print(f"    {a} vs {b}: {r:.2f}x (above 1: {a} better)")
                    self._write({"kind": "ratio", "case": case, "metric": metric, "a": a, "b": b, "ratio": r})
                else:  # a ratio of negative figures (returns) reads backwards: the difference instead
                    print(f"    {a} - {b}: {fmt(med[a] - med[b])}")
                    self._write({"kind": "difference", "case": case, "metric": metric, "a": a, "b": b,
                                 "difference": med[a] - med[b]})
        for row in rows:
            self._write(row)
        return rows

    def close(self) -> None:
        """Close the JSON lines file and say where it is."""
        self._file.close()
        print(f"\nresults: {self.path}")


def fmt(value: float | None) -> str:
    """A figure for the table: 4 significant digits, thousands as whole numbers, ``-`` for None."""
    if value is None:
        return "-"
    return f"{value:,.0f}" if abs(value) >= 1e4 else f"{value:.4g}"


def _loads() -> str:
    one, five, fifteen = load_averages()
    return f"{one:.2f}/{five:.2f}/{fifteen:.2f} ({os.cpu_count()} CPUs)"


# --- child processes ------------------------------------------------------------------------------


class ChildWorker:
    """A long-lived child process that answers JSON requests, one per line (see :func:`serve`).

    Args:
        side: whose interpreter and environment.
        module: the ``bench`` module whose ``child_main`` serves.
        args: its arguments.
    """

    def __init__(self, side: Side, module: str, *args: str) -> None:
        self.side = side
        self.proc = subprocess.Popen(side.command(module, *args), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=None, text=True, env=side.env, cwd=side.cwd)

    def ask(self, request: dict[str, Any]) -> dict[str, Any]:
        """Send ``request``, return the answer.

        Raises:
            RuntimeError: the child exited first.
        """
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        for line in self.proc.stdout:
            if line.startswith(RESULT):
                return json.loads(line[len(RESULT):])
        raise RuntimeError(f"the {self.side.name} child exited (code {self.proc.wait()})")

    def close(self) -> None:
        """Ask the child to quit and wait for it (killed after 30 s)."""
        if self.proc.poll() is None and self.proc.stdin is not None:
            try:
                self.proc.stdin.write(json.dumps({"quit": True}) + "\n")
                self.proc.stdin.flush()
                self.proc.wait(timeout=30)
            except (BrokenPipeError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()


def serve(handle: Callable[[dict[str, Any]], dict[str, Any]]) -> None:
    """Child side of :class:`ChildWorker`: answer each request line with ``handle(request)``."""
    for line in sys.stdin:
        request = json.loads(line)
        if request.get("quit"):
            break
        answer(handle(request))


def answer(obj: dict[str, Any]) -> None:
    """Print one result line for the parent."""
    print(RESULT + json.dumps(obj), flush=True)


def print_json(obj: dict[str, Any]) -> None:
    """Print one JSON object on one line (what :class:`JsonLines` reads)."""
    print(json.dumps(obj), flush=True)


def free_port() -> int:
    """A TCP port of 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_listening(port: int, timeout: float, what: str = "the server") -> None:
    """Poll until something accepts connections on ``port`` of 127.0.0.1.

    Raises:
        RuntimeError: nothing did within ``timeout`` seconds.
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"{what} did not listen on port {port} within {timeout:g} s")


def start_group(cmd: list[str], side: Side, log: Path, stdout: int | None = None,
                env: dict[str, str] | None = None, cwd: str | None = None) -> subprocess.Popen:
    """Start ``cmd`` in a process group of its own (so that :func:`stop_groups` also ends the
    processes it starts; on Windows, a console process group that Ctrl-Break reaches), stderr (and
    stdout unless piped) to ``log``."""
    if os.name == "posix":
        group: dict[str, Any] = {"start_new_session": True}
    else:
        group = {"creationflags": subprocess.CREATE_NEW_PROCESS_GROUP}
    handle = open(log, "ab")  # noqa: SIM115 (the child holds it; closed by the OS at its exit)
    try:
        return subprocess.Popen(cmd, stdout=stdout if stdout is not None else handle, stderr=handle,
                                env=env or side.env, cwd=cwd or side.cwd, **group)
    finally:
        handle.close()


def stop_groups(procs: Sequence[subprocess.Popen], grace: float = 10.0) -> None:
    """SIGINT each process (Ctrl-Break on Windows), wait up to ``grace`` seconds, then SIGKILL its
    whole group (on Windows, end the process: its network processes follow their parent)."""
    for p in procs:
        if p.poll() is None:
            if os.name == "posix":
                p.send_signal(signal.SIGINT)
            else:
                p.send_signal(signal.CTRL_BREAK_EVENT)
    deadline = time.monotonic() + grace
    for p in procs:
        try:
            p.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
        if os.name == "posix":
            try:  # the relay and link processes a role started are in its group
                os.killpg(p.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        else:
            p.kill()
        p.wait()


class JsonLines:
    """Non-blocking reader of the JSON objects a child prints one per line on stdout (other lines
    are ignored: the original tmrl prints its own)."""

    def __init__(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        self.proc = proc
        self._pending = b""
        self._chunks: queue.SimpleQueue[bytes] | None = None
        if hasattr(os, "set_blocking"):
            os.set_blocking(proc.stdout.fileno(), False)
        else:  # Windows has no non-blocking pipes: a thread reads this one
            self._chunks = queue.SimpleQueue()
            threading.Thread(target=self._pump, args=(proc.stdout, self._chunks), daemon=True).start()

    @staticmethod
    def _pump(stdout: IO[bytes], chunks: queue.SimpleQueue[bytes]) -> None:
        for chunk in iter(lambda: stdout.read1(65536), b""):  # type: ignore[attr-defined]
            chunks.put(chunk)

    def poll(self) -> list[dict[str, Any]]:
        """The objects printed since the last call."""
        assert self.proc.stdout is not None
        if self._chunks is None:
            self._pending += self.proc.stdout.read() or b""
        else:
            while not self._chunks.empty():
                self._pending += self._chunks.get_nowait()
        *lines, self._pending = self._pending.split(b"\n")
        return [json.loads(line) for line in lines if line.startswith(b"{")]

    def wait(self, timeout: float, interval: float = 0.05) -> Iterator[dict[str, Any]]:
        """Yield objects as they come until ``timeout`` seconds passed or the child exited."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            got = self.poll()
            yield from got
            if not got:
                if self.proc.poll() is not None:
                    yield from self.poll()
                    return
                time.sleep(interval)


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file (a reader never sees half of it)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def read_int(path: Path) -> int:
    """The integer in ``path``, 0 when it is missing or being written."""
    try:
        return int(path.read_text())
    except (OSError, ValueError):
        return 0


def child_main(argv: list[str]) -> None:
    """Diagnostic child (``python bench/_child.py harness``): prints, as JSON, where this
    interpreter imports ``tmrl`` and ``bench`` from, to check what a side really runs."""
    import importlib.util

    spec = importlib.util.find_spec("tmrl")
    print_json({"tmrl": spec.origin if spec else None, "bench": str(Path(__file__).resolve().parent),
                "python": sys.executable})
