"""``python -m tmrl``: the command line.

One command per run (``--server``, ``--trainer``, ``--worker``, ...), plus ``-d/--config`` to
override ``config.json`` for that run. This module only parses arguments, prepares the data folder
and the configuration, and hands over to the module that does the work:

==========================  ===============================================================
flag                        calls
==========================  ===============================================================
``--server``                ``tmrl.roles.run_server(cfg)``
``--trainer [--wandb]``     ``tmrl.roles.run_trainer(cfg, wandb=...)``
``--worker``                ``tmrl.roles.run_worker(cfg, "train")``
``--expert``                ``tmrl.roles.run_worker(cfg, "expert")``
``--test``                  ``tmrl.roles.run_worker(cfg, "test")``
``--benchmark``             ``tmrl.roles.run_benchmark(cfg)`` (SIM* interfaces: in real time,
                            ``ENV.SIM_FAST_MODE`` off); ``tmrl.tm.tools.benchmark(cfg, steps=500)``
                            for TM20* interfaces
``--demo [ARGS...]``        ``tmrl.sim.demo.main(argv)`` (the arguments after ``--demo``)
``--check-environment``     ``tmrl.tm.tools.check_environment(cfg)``
                            (``tmrl.sim.tools.check_environment(cfg)`` for SIM* interfaces)
``--record-reward``         ``tmrl.tm.tools.record_reward(cfg, use_keyboard=...)``
``--doctor``                ``tmrl.tm.tools.doctor(cfg)`` (creates no folder)
``--install``               :func:`tmrl.config.loader.install`, then
                            ``tmrl.transport.ensure_credentials(directory)`` when it exists
                            (and, with ``TRANSPORT`` "nats", the NATS users:
                            ``tmrl.transport.nats_backend.write_credentials``); with
                            ``--env tm20lidar`` or ``tm20full`` also
                            ``tmrl.tm.install.install_game_side`` (the original's resources)
``--help TOPIC``            prints a guide: ``trackmania`` (:data:`tmrl.tm.guide.TEXT`) or
                            ``config`` (every key of config.json, from the schema)
==========================  ===============================================================

A hook may return an ``int`` exit code (``None`` means 0). The override given with ``-d`` is
validated, then stored as JSON in ``$TMRL_CONFIG_OVERRIDE`` so that
:func:`tmrl.config.loader.load_config` applies it in this process and in every child process.

Exit codes: 0 success, 2 a user mistake (:class:`tmrl.errors.UserError`, one line on stderr, no
traceback) or a command that has not landed yet, 1 a bug (traceback and a request to report it),
3 ``--doctor`` found a problem, 129 stopped by SIGHUP (its terminal closed; POSIX), 130 interrupted
(Ctrl-C), 143 stopped by SIGTERM, 149 stopped by Ctrl-Break (SIGBREAK; Windows).
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys
import traceback
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NoReturn

from tmrl.config.loader import ENVIRONMENTS
from tmrl.config.schema import PASSWORD_PLACEHOLDER
from tmrl.errors import UserError

__all__ = ["HELP_TOPICS", "HOOKS", "SIM_HOOKS", "TM_HOOKS", "build_parser", "help_topic", "main"]

logger = logging.getLogger(__name__)

ISSUES_HINT = (
    "This is a bug in tmrl, not a mistake of yours. Please report it on the project's issue tracker, "
    "with the traceback above and the command you ran."
)

#: command -> (module, function) it dispatches to.
HOOKS: dict[str, tuple[str, str]] = {
    "server": ("tmrl.roles", "run_server"),
    "trainer": ("tmrl.roles", "run_trainer"),
    "worker": ("tmrl.roles", "run_worker"),
    "expert": ("tmrl.roles", "run_worker"),
    "test": ("tmrl.roles", "run_worker"),
    "benchmark": ("tmrl.roles", "run_benchmark"),
    "demo": ("tmrl.sim.demo", "main"),
    "check_environment": ("tmrl.tm.tools", "check_environment"),
    "record_reward": ("tmrl.tm.tools", "record_reward"),
    "doctor": ("tmrl.tm.tools", "doctor"),
    "import_weights": ("tmrl.roles", "run_import_weights"),
    "export_weights": ("tmrl.roles", "run_export_weights"),
}

#: Replacements of :data:`HOOKS` when ``ENV.RTGYM_INTERFACE`` is one of the simulator's.
SIM_HOOKS: dict[str, tuple[str, str]] = {
    "check_environment": ("tmrl.sim.tools", "check_environment"),
}

#: Replacements of :data:`HOOKS` when ``ENV.RTGYM_INTERFACE`` is one of TrackMania's.
TM_HOOKS: dict[str, tuple[str, str]] = {
    "benchmark": ("tmrl.tm.tools", "benchmark"),
}

#: Steps of ``--benchmark`` in TrackMania.
TM_BENCHMARK_STEPS = 500

_SECRET_KEYS = ("PASSWORD", "WANDB_KEY")

#: The commands whose roles size their PyTorch threads (``--threads``, ``$TMRL_THREADS``).
_THREADED = ("trainer", "worker", "expert", "test", "benchmark", "demo")

_DESCRIPTION = """\
tmrl: distributed real-time reinforcement learning (TrackMania, a simulated track, any Gymnasium
environment). A run has three parts that can live on different machines: a server that relays
samples and weights, a trainer, and one or more workers that collect samples.

Configuration: config.json in the data folder ($TMRL_DATA, or ~/TmrlData when unset). Commands that
need the folder create it; --install creates it and says where everything is.
"""

_EPILOG = """\
examples:
  python -m tmrl --install                 create the data folder and config.json (random PASSWORD)
  python -m tmrl --install --env tm20lidar also set up TrackMania: OpenPlanet plugins, reward, pretrained weights
  python -m tmrl --demo                    train on the built-in simulator, all parts on this machine
  python -m tmrl --server                  then, in two other terminals: --trainer and --worker
  python -m tmrl --trainer -d '{"ALG": {"ALGORITHM": "REDQSAC"}}'
  python -m tmrl --print-config -d "{'CUDA_TRAINING': True}"

exit codes: 0 success, 1 a bug in tmrl (please report it), 2 a mistake in the command or the
configuration (one line says what to change), 3 --doctor found a problem (its report says what to
fix), 130 interrupted (Ctrl-C), 143 stopped by SIGTERM, 129 stopped by SIGHUP (the terminal was
closed; Linux and macOS), 149 stopped by Ctrl-Break (Windows).

guides: python -m tmrl --help trackmania (from a clean PC to a car on the track), python -m tmrl --help
config (every key of config.json).

threads: each role sizes its PyTorch threads to this machine's cores (a worker 1, a trainer all
cores but one); --threads N or TMRL_THREADS=N sets them.
"""


class UsageError(UserError):
    """A mistake in the command line (reported as one line, exit code 2)."""

    def __init__(self, message: str, hint: str = "") -> None:
        super().__init__(message)
        self.hint = hint


class Parser(argparse.ArgumentParser):
    """``argparse`` that raises :class:`UsageError` instead of printing its usage block and that
    never accepts an abbreviation of a long option (``--serve`` is not ``--server``)."""

    def __init__(self, *args: Any, hint: str = "", **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
        self.hint = hint

    def error(self, message: str) -> NoReturn:  # type: ignore[override]
        hint = self.hint
        if message.startswith("unrecognized arguments: "):
            import difflib

            options = [o for action in self._actions for o in action.option_strings if o.startswith("--")]
            for word in message.split(": ", 1)[1].split():
                close = difflib.get_close_matches(word.split("=")[0], options, n=1)
                if close:
                    hint = f"did you mean {close[0]}? {hint}".strip()
                    break
        raise UsageError(message, hint)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m tmrl`` (exactly one command per run)."""
    parser = Parser(
        prog="python -m tmrl",
        description=_DESCRIPTION,
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        hint="`python -m tmrl --help` lists the commands",
    )
    commands = parser.add_argument_group("commands (choose one)")
    group = commands.add_mutually_exclusive_group()
    add = group.add_argument
    add("--server", action="store_const", const="server", dest="command",
        help="run the server: relays samples from the workers to the trainer and weights back")
    add("--trainer", action="store_const", const="trainer", dest="command",
        help="run the trainer: learns from the samples and broadcasts the weights; checkpoints "
             "after each epoch (resumes unless RESET_TRAINING is true)")
    add("--worker", action="store_const", const="worker", dest="command",
        help="run a rollout worker: acts in the environment with the latest weights, sends samples")
    add("--expert", action="store_const", const="expert", dest="command",
        help="run a worker that keeps its current model (ignores weight updates) and sends samples; "
             "useful to collect samples from an expert policy")
    add("--test", action="store_const", const="test", dest="command",
        help="run the policy in the environment without training or a server (no samples sent)")
    add("--benchmark", action="store_const", const="benchmark", dest="command",
        help="measure the environment's real-time step durations (sets RTGYM_CONFIG.benchmark)")
    add("--demo", action="store_const", const="demo", dest="command",
        help="train on the built-in simulated track with server, trainer and worker on this machine; "
             "arguments after --demo go to the demo (see --demo --help)")
    add("--record-reward", action="store_const", const="record_reward", dest="command",
        help="record a reward trajectory in TrackMania: start at the start line, cross the finish")
    add("--check-environment", action="store_const", const="check_environment", dest="command",
        help="show what the agent sees (images or lidar) and the rewards, to check the setup")
    add("--install", action="store_const", const="install", dest="command",
        help="create the data folder, config.json (random PASSWORD, never overwritten) and TLS "
             "credentials, and print where they are; with --env tm20lidar or tm20full also fetch the original "
             "tmrl's resources and install the OpenPlanet plugins, the tmrl-test reward and the pretrained weights")
    add("--doctor", action="store_const", const="doctor", dest="command",
        help="check this machine (packages, GPU, data folder, config, ports) and say what to fix")
    add("--import-weights", metavar="FILE", dest="import_weights",
        help="convert a tmrl 0.7 weights file (.tmod) for the configured actor and write it where the worker "
             "reads its weights (or to --out); the file is read as tensors only, never as code")
    add("--export-weights", metavar="FILE", dest="export_weights",
        help="write this tmrl's weights file FILE as a tmrl 0.7 weights file (to --out, default "
             "<name>-tmrl07.tmod next to it)")
    add("--print-config", action="store_const", const="print_config", dest="command",
        help="print the effective configuration (config.json with defaults and --config applied; "
             "secrets hidden) and exit")
    add("--version", action="store_const", const="version", dest="command", help="print the version")

    options = parser.add_argument_group("run options")
    options.add_argument("-d", "--config", metavar="DICT", action="append", default=[],
                         help="override config.json for this run with a JSON or Python dict, e.g. "
                              "'{\"ALG\": {\"LR_ACTOR\": 0.0001}}'; merged key by key and validated like "
                              "the file; may be repeated; child processes inherit it")
    options.add_argument("--wandb", action="store_true",
                         help="with --trainer: log metrics to Weights & Biases (WANDB_* keys of config.json; "
                              "needs pip install \".[wandb]\" in this project's checkout)")
    options.add_argument("--env", metavar="NAME", type=str.lower, choices=tuple(ENVIRONMENTS),
                         help="with --install: the environment of config.json, one of " + ", ".join(ENVIRONMENTS)
                              + " (shipped configs); on an existing data folder it switches config.json to it, "
                              "keeping PASSWORD and your other edits (the old file is kept as config.previous.json)")
    options.add_argument("--out", metavar="PATH",
                         help="with --import-weights or --export-weights: where to write the converted file")
    options.add_argument("--use-keyboard", action="store_true",
                         help="with --record-reward: drive with the keyboard instead of a gamepad")
    options.add_argument("--threads", metavar="N", type=int,
                         help="with --trainer, --worker, --expert, --test, --benchmark or --demo: PyTorch (and "
                              "OpenMP) threads of each role (default: $TMRL_THREADS, else $OMP_NUM_THREADS, else "
                              "1 for a worker and all cores but one for a trainer)")
    options.add_argument("-v", "--verbose", action="store_true", help="show debug messages")
    options.add_argument("-q", "--quiet", action="store_true", help="show only warnings and errors")
    return parser


def _configure_logging(verbose: bool, quiet: bool) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S", stream=sys.stderr)


class _NotLanded(UserError):
    """The module behind a command is not part of this version yet."""


def _resolve_hook(command: str, flag: str, interface: str | None = None) -> Callable[..., Any]:
    table: dict[str, tuple[str, str]] = {}
    if interface is not None and interface.startswith("SIM"):
        table = SIM_HOOKS
    elif interface is not None and interface.startswith("TM20"):
        table = TM_HOOKS
    module_name, func_name = table.get(command) or HOOKS[command]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        missing = e.name or ""
        if missing.startswith("tmrl") and (module_name == missing or module_name.startswith(missing + ".")):
            raise _NotLanded(f"{flag} is not available yet in this version of tmrl ({module_name} is missing)") \
                from None
        raise
    func = getattr(module, func_name, None)
    if not callable(func):
        raise _NotLanded(f"{flag} is not available yet in this version of tmrl ({module_name}.{func_name} is missing)")
    return func


def _flag(command: str) -> str:
    return "--" + command.replace("_", "-")


def _hidden(cfg: dict[str, Any]) -> dict[str, Any]:
    out = dict(cfg)
    for key in _SECRET_KEYS:
        if key in out:
            out[key] = "<hidden>"
    return out


def _config_state(loader: Any, report: Any, env: str | None) -> str:
    """What ``--install`` did to config.json, in words (switching it when ``env`` asks)."""
    if report.created_config:
        return f"created for {env or 'tm20full'}, with a fresh random PASSWORD"
    if env is None:
        return "kept as it was"
    switch = loader.switch_environment(env, report.paths.root)
    if not switch.changed:
        return f"kept as it was: already {env}"
    kept = ", ".join(switch.kept) if switch.kept else "nothing else"
    return f"switched to {env}; kept your {kept}; the former file is {switch.previous.name}"


def _next_steps(cfg: Mapping[str, Any] | None, game_side: bool = False) -> list[str]:
    interface = str(cfg["ENV"]["RTGYM_INTERFACE"]) if cfg is not None else ""
    if interface.startswith("TM20") and game_side:
        return ["Next: start TrackMania 2020 on the map tmrl-test, check the setup with `python -m tmrl --doctor`, then",
                "`python -m tmrl --worker --test` drives with the pretrained weights (`python -m tmrl --help trackmania`",
                "walks through every step, training included)."]
    if interface.startswith("TM20"):
        return ["Next: `python -m tmrl --install --env tm20lidar` sets up the game side (OpenPlanet plugins, reward,",
                "pretrained weights); `python -m tmrl --help trackmania` walks through it; `python -m tmrl --doctor`",
                "checks it. No game? `python -m tmrl --install --env simlidar` switches to the built-in simulator."]
    return ["Next: run `python -m tmrl --server`, `python -m tmrl --trainer` and `python -m tmrl --worker` in three",
            "terminals (or on three machines with the same config.json)."]


def _install(env: str | None = None) -> int:
    from tmrl.config import loader
    from tmrl.transport import ensure_credentials

    report = loader.install(env=env)
    state = _config_state(loader, report, env)
    error: UserError | None = None
    try:
        cfg: dict[str, Any] | None = loader.load_config()
    except UserError as e:
        # Still say where everything is: the fix is usually an edit of that config.json.
        error, cfg = e, None
    paths = loader.data_paths(cfg, report.paths.root)
    credentials_note = "not prepared: fix config.json first"
    if cfg is not None:
        ensure_credentials(paths.credentials, hostname=cfg["TLS_HOSTNAME"])
        credentials_note = "key and certificate ready; existing files are kept"
        if cfg["TRANSPORT"] == "nats":
            from tmrl.transport.nats_backend import write_credentials

            write_credentials(paths.credentials, cfg["NATS"]["STREAM"], cfg["NATS"]["BUCKET"])
            credentials_note += "; NATS users in nats/ (worker.json to workers, trainer.json to the trainer)"
    current = loader.environment_of(cfg) if cfg is not None else None
    lines = [
        f"tmrl data folder: {paths.root}",
        f"  config        {paths.config_file}  ({state})",
        f"  environment   {current or (cfg['ENV']['RTGYM_INTERFACE'] if cfg else '?')}",
        f"  weights       {paths.weights}",
        f"  checkpoints   {paths.checkpoints}",
        f"  dataset       {paths.dataset}",
        f"  reward        {paths.reward}",
        f"  credentials   {paths.credentials}  (TLS: {credentials_note})",
        f"  logs          {paths.logs}",
        "Edit config.json to configure runs (`python -m tmrl --print-config` shows the result; `python -m tmrl",
        "--help config` lists every key). Use the same PASSWORD on every machine of a run.",
        f"Switch environments with `python -m tmrl --install --env NAME` ({', '.join(loader.ENVIRONMENTS)}).",
        "Set TMRL_DATA to use another data folder.",
    ]
    print("\n".join(lines), flush=True)
    if error is not None:
        raise error
    game_side = False
    from tmrl.tm.install import GAME_ENVIRONMENTS

    if env in GAME_ENVIRONMENTS:
        from tmrl.tm.install import install_game_side

        game_side = install_game_side(env, cfg, paths.root)
    print("\n".join(_next_steps(cfg, game_side)))
    return 0


def _run(args: argparse.Namespace, extra: list[str]) -> int:
    from tmrl.config import loader

    command = args.command
    if command == "version":
        from tmrl._version import __version__

        print(f"tmrl {__version__}")
        return 0
    if os.environ.get(loader.DATA_ENV, "").strip():
        # Child processes may run elsewhere: hand them the folder as an absolute path.
        os.environ[loader.DATA_ENV] = str(loader.data_folder())
    for text in args.config:
        loader.set_override_env(text, source="--config")
    if command == "install":
        return _install(args.env)
    if command == "print_config":
        return _print_quietly(json.dumps(_hidden(loader.load_config()), indent=2))

    flag = _flag(command)
    if command in _THREADED:
        from tmrl.roles import THREADS_ENV, role_threads

        if args.threads is not None:
            os.environ[THREADS_ENV] = str(args.threads)  # the demo's roles inherit it
        role_threads(command)  # a bad $TMRL_THREADS is reported here, before anything starts
    if command == "demo":
        # The demo checks its arguments and the configuration, then prepares the data folder
        # itself: --demo --help or a mistake creates nothing.
        return int(_resolve_hook(command, flag)(list(extra)) or 0)
    if command == "doctor":
        # The doctor reports on the data folder; it must not create it.
        cfg = loader.load_config()
        return int(_resolve_hook(command, flag)(cfg) or 0)

    if command == "benchmark":
        # Through the override, so that modules reading config_constants see it too.
        loader.set_override_env({"ENV": {"RTGYM_CONFIG": {"benchmark": True}}}, source="--benchmark")
        if loader.load_config()["ENV"]["RTGYM_INTERFACE"].startswith("SIM"):
            # The benchmark times the real-time clock: the fast simulator has none.
            loader.set_override_env({"ENV": {"SIM_FAST_MODE": False}}, source="--benchmark")
    cfg = loader.load_config()  # a configuration mistake is reported before anything is created
    hook = _resolve_hook(command, flag, cfg["ENV"]["RTGYM_INTERFACE"])
    loader.ensure_data_folder()
    # Read again: config.json may just have been written (by us or by a process started beside us,
    # e.g. by the demo) with a fresh PASSWORD.
    cfg = loader.load_config()
    if cfg["PASSWORD"] == PASSWORD_PLACEHOLDER and command in ("server", "trainer", "worker", "expert") \
            and not args.standalone:
        logger.warning("PASSWORD is the public placeholder %r: anyone who can reach the server can join; put a "
                       "random one in %s (the same on every machine)", PASSWORD_PLACEHOLDER, loader.config_path())
    if command == "trainer":
        result = hook(cfg, wandb=args.wandb)
    elif command in ("worker", "expert", "test"):
        # --worker --test and --expert --test: that worker, standalone (tmrl 0.7's behaviour)
        standalone = True if command == "test" or args.standalone else None
        result = hook(cfg, {"worker": "train", "expert": "expert", "test": "test"}[command], standalone=standalone)
    elif command in ("import_weights", "export_weights"):
        result = hook(cfg, getattr(args, command), out=args.out)
    elif command == "record_reward":
        result = hook(cfg, use_keyboard=args.use_keyboard)
    elif command == "benchmark" and cfg["ENV"]["RTGYM_INTERFACE"].startswith("TM20"):
        result = hook(cfg, steps=TM_BENCHMARK_STEPS)
    else:
        result = hook(cfg)
    return int(result or 0)


def _report_user_error(e: UserError) -> int:
    """One line on stderr (plus a hint line for command-line mistakes); the exit code."""
    message = " ".join(str(e).split()) or type(e).__name__
    print(f"tmrl: error: {message}", file=sys.stderr)
    hint = getattr(e, "hint", "")
    if hint:
        print(f"({hint})", file=sys.stderr)
    return getattr(e, "exit_code", 2) or 2


def _print_quietly(text: str) -> int:
    """Print ``text``; a reader that stops early (``| head``) ends the command quietly, with
    code 0, instead of a BrokenPipeError traceback."""
    try:
        print(text)
        sys.stdout.flush()
    except BrokenPipeError:
        # Point stdout at /dev/null so that the interpreter's final flush does not fail again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, sys.stdout.fileno())
        finally:
            os.close(devnull)
    return 0


def _check_combinations(parser: argparse.ArgumentParser, args: argparse.Namespace, extra: list[str]) -> None:
    """Refuse options that do not go with the command (:class:`UsageError`, one line)."""
    for command in ("import_weights", "export_weights"):
        if getattr(args, command) is not None:
            args.command = command
    if args.command is None:
        raise UsageError("choose a command, e.g. --demo, --install or --server", "`python -m tmrl --help` lists them")
    if extra and args.command != "demo":
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    wrong = [
        (args.out is not None and args.command not in ("import_weights", "export_weights"),
         "--out goes with --import-weights or --export-weights"),
        (args.env is not None and args.command != "install", "--env goes with --install (python -m tmrl --install --env simlidar)"),
        (args.wandb and args.command != "trainer", "--wandb goes with --trainer"),
        (args.use_keyboard and args.command != "record_reward", "--use-keyboard goes with --record-reward"),
        (args.threads is not None and args.command not in _THREADED,
         "--threads goes with --trainer, --worker, --expert, --test, --benchmark or --demo"),
        (args.threads is not None and args.threads < 1, f"--threads {args.threads}: give at least 1"),
        (args.verbose and args.quiet, "choose one of --verbose and --quiet"),
    ]
    for bad, message in wrong:
        if bad:
            raise UsageError(message)


def _is_dict_text(value: str) -> bool:
    return value.lstrip().startswith("{")


def _split_demo_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """Arguments after ``--demo`` belong to the demo's own parser, except ``-d DICT`` and
    ``--config DICT`` (a dict), which stay ours so that ``--demo -d '{...}'`` overrides the
    config as anywhere. ``--demo --config FILE`` (a file name) is the demo's own option."""
    if "--demo" not in argv:
        return argv, []
    i = argv.index("--demo")
    ours, tail = argv[: i + 1], argv[i + 1:]
    extra: list[str] = []
    j = 0
    while j < len(tail):
        token = tail[j]
        value = tail[j + 1] if j + 1 < len(tail) else ""
        if (token == "-d" or (token == "--config" and _is_dict_text(value))) and j + 1 < len(tail):
            ours += [token, value]
            j += 2
            continue
        if token.startswith("--config=") and _is_dict_text(token.split("=", 1)[1]):
            ours.append(token)
        else:
            extra.append(token)
        j += 1
    return ours, extra


def _split_standalone_test(argv: list[str]) -> tuple[list[str], bool]:
    """tmrl 0.7 accepts ``--test`` beside ``--worker`` or ``--expert``: that worker, standalone.
    Returns the arguments without that ``--test`` and whether it was there."""
    if "--test" in argv and ("--worker" in argv or "--expert" in argv):
        return [a for a in argv if a != "--test"], True
    return argv, False


HELP_TOPICS = ("trackmania", "config")
"""The guides ``python -m tmrl --help TOPIC`` prints."""


def help_topic(topic: str) -> str:
    """The text of ``python -m tmrl --help TOPIC``.

    Raises:
        UsageError: an unknown topic.
    """
    if topic == "trackmania":
        from tmrl.tm.guide import TEXT

        return TEXT
    if topic == "config":
        from tmrl.config.schema import markdown_reference

        return markdown_reference()
    raise UsageError(f"--help {topic}: no such guide; the guides are {', '.join(HELP_TOPICS)}",
                     "`python -m tmrl --help` lists the commands")


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``python -m tmrl`` with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) == 2 and argv[0] in ("-h", "--help"):
        try:
            return _print_quietly(help_topic(argv[1].lower()))
        except UserError as e:
            return _report_user_error(e)
    parser = build_parser()
    try:
        argv, extra = _split_demo_args(argv)
        argv, standalone = _split_standalone_test(argv)
        args = parser.parse_args(argv)
        args.standalone = standalone
        _check_combinations(parser, args, extra)
    except UserError as e:
        return _report_user_error(e)
    _configure_logging(args.verbose, args.quiet)
    try:
        return _run(args, extra)
    except UserError as e:
        return _report_user_error(e)
    except KeyboardInterrupt as err:
        # Ctrl-C, or SIGTERM / SIGHUP / SIGBREAK turned into a KeyboardInterrupt that carries its number
        signum = int(getattr(err, "signum", 2))
        try:
            print("tmrl: interrupted" if signum == 2 else f"tmrl: stopped (signal {signum})", file=sys.stderr)
        except OSError:  # a closed terminal
            pass
        return 128 + signum
    except SystemExit:
        raise
    except BaseException:  # noqa: BLE001 (anything else is a bug: report it)
        traceback.print_exc()
        print(ISSUES_HINT, file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
