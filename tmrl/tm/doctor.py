"""``--doctor``: check this machine's setup piece by piece, before a training run fails.

Each check is a plain function returning a :class:`CheckResult` (pass, fail or skip, what was
found, and for a failure the one-line fix). :func:`run_checks` runs them in order and
:func:`run_doctor` prints the list and returns the exit code (0: nothing failed, 3: at least one
check failed; 1 stays reserved for bugs in tmrl). No check raises: an unexpected error becomes a
failed check whose fix asks to report it. Nothing is created.

The checks, in order: the packages, whether the original tmrl (PyPI's ``tmrl``) shares this
Python environment, the data folder, config sanity; for TrackMania interfaces only, the OpenPlanet
plugins in ``OpenplanetNext/Plugins`` (and their versions), the OpenPlanet connection and frame
rate, the game window and its size, the gamepad driver (ViGEmBus is looked for in the registry
before vgamepad is imported, which would otherwise start its installer), screen-capture time per
frame and the reward file of the map in use (with telemetry, the car must be near the trajectory);
other interfaces skip them; then the GPU, server reachability and TLS credentials.
"""

from __future__ import annotations

import logging
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, TextIO

from tmrl.errors import UserError

__all__ = [
    "CHECKS_FAILED",
    "CheckResult",
    "check_data_folder",
    "check_packages",
    "check_capture_speed",
    "check_config",
    "check_gamepad",
    "check_gpu",
    "check_openplanet",
    "check_original_tmrl",
    "check_plugins",
    "check_reward_file",
    "check_server",
    "check_tls",
    "check_window",
    "format_report",
    "run_checks",
    "run_doctor",
]

logger = logging.getLogger(__name__)

TM_INTERFACES = ("TM20FULL", "TM20LIDAR", "TM20LIDARPROGRESS")

#: Exit code of ``--doctor`` when a check failed (0: none did; 1 is kept for bugs in tmrl).
CHECKS_FAILED = 3


@dataclass(frozen=True)
class CheckResult:
    """Outcome of one check.

    Attributes:
        name: short name of what was checked.
        status: ``"pass"``, ``"fail"`` or ``"skip"``.
        detail: what was found (one line).
        fix: for a failure, the one-line fix.
    """

    name: str
    status: str
    detail: str
    fix: str = ""
    data: Any = field(default=None, compare=False, repr=False)
    """What a later check may use (the OpenPlanet check's first telemetry frame)."""

    @property
    def ok(self) -> bool:
        return self.status != "fail"


def _pass(name: str, detail: str) -> CheckResult:
    return CheckResult(name, "pass", detail)


def _fail(name: str, detail: str, fix: str) -> CheckResult:
    return CheckResult(name, "fail", detail, fix)


def _skip(name: str, detail: str) -> CheckResult:
    return CheckResult(name, "skip", detail)


def _split(message: str) -> tuple[str, str]:
    """Split a one-line UserError message ``cause: fix`` into its two halves."""
    depth = 0
    for i, ch in enumerate(message):
        if ch in "([":
            depth += 1
        elif ch in ")]":
            depth = max(depth - 1, 0)
        elif depth == 0 and message.startswith(": ", i):
            return message[:i], message[i + 2 :]
    return message, "`python -m tmrl --help trackmania` walks through the setup"


# ---------------------------------------------------------------------------------------- checks
def check_openplanet(
    host: str = "127.0.0.1", port: int = 9000, wait: float = 3.0, measure: float = 1.0, min_rate: float = 20.0
) -> CheckResult:
    """Connect to the TMRL_GrabData plugin, wait up to ``wait`` s for a frame, count frames for
    ``measure`` s; fail below ``min_rate`` frames per second (one frame per 50 ms time step)."""
    from tmrl.tm.openplanet import OpenPlanetClient, TelemetryTimeout

    name = "OpenPlanet telemetry"
    with OpenPlanetClient(
        host=host, port=port, first_timeout=wait, timeout=wait, retry_interval=0.2
    ) as client:
        try:
            first = client.retrieve_data(timeout=wait)
        except TelemetryTimeout as err:
            return _fail(name, *_split(str(err)))
        rate = client.measure_rate(measure)
    if rate < min_rate:
        return _fail(
            name,
            f"only {rate:.1f} frames/s from {host}:{port} (need {min_rate:g})",
            "raise the game's frame rate (windowed, lower graphics settings, no frame limiter below 30 fps)",
        )
    return CheckResult(
        name, "pass",
        f"{host}:{port}, {rate:.0f} frames/s, speed {first.speed:.1f}, "
        f"position ({first.x:.1f}, {first.y:.1f}, {first.z:.1f})",
        data=first,
    )


def check_window(
    title: str = "Trackmania",
    width: int = 256,
    height: int = 128,
    resize: bool = True,
    display: str | None = None,
) -> CheckResult:
    """Find the game window, move and resize it as training would, and check its client size."""
    from tmrl.tm.capture import WindowCapture

    name = "game window"
    try:
        with WindowCapture(title, width, height, display=display) as cap:
            geo = cap.move_and_resize(0, 0) if resize else cap.check_size()
    except UserError as err:
        return _fail(name, *_split(str(err)))
    return _pass(name, f"{title!r} at ({geo.left}, {geo.top}), picture {geo.width}x{geo.height}")


def check_capture_speed(
    title: str = "Trackmania",
    width: int = 256,
    height: int = 128,
    img_width: int = 64,
    img_height: int = 64,
    grayscale: bool = True,
    time_step: float = 0.05,
    frames: int = 30,
    display: str | None = None,
) -> CheckResult:
    """Time capture plus preprocessing; fail above a quarter of the time step."""
    from tmrl.tm.capture import WindowCapture, preprocess

    name = "capture time"
    try:
        with WindowCapture(title, width, height, display=display) as cap:
            preprocess(cap.screenshot(), img_width, img_height, grayscale)  # warm-up (mss, cv2)
            t0 = time.perf_counter()
            for _ in range(frames):
                preprocess(cap.screenshot(), img_width, img_height, grayscale)
            ms = (time.perf_counter() - t0) / frames * 1e3
    except UserError as err:
        return _skip(name, f"needs the game window ({_split(str(err))[0]})")
    budget = time_step * 1e3 / 4
    if ms > budget:
        return _fail(
            name,
            f"{ms:.1f} ms per frame, more than a quarter of the {time_step * 1e3:.0f} ms step",
            "close other programs, use a smaller window, "
            "or install OpenCV (pip install opencv-python-headless)",
        )
    return _pass(name, f"{ms:.2f} ms per frame (capture + resize to {img_width}x{img_height})")


def check_gamepad(use_gamepad: bool = True) -> CheckResult:
    """Check the virtual gamepad driver (skipped when the keyboard is configured)."""
    from tmrl.tm.control import check_gamepad_driver

    name = "gamepad driver"
    if not use_gamepad:
        return _skip(name, "VIRTUAL_GAMEPAD is false: the keyboard drives (binary actions)")
    ok, msg = check_gamepad_driver()
    return _pass(name, msg) if ok else _fail(name, *_split(msg))


def check_reward_file(path: str | Path | None = None, position: Any = None, max_stray: float = 100.0) -> CheckResult:
    """Load the reward trajectory and report its length; with the car's ``position`` (x, y, z from
    the telemetry), fail when the car is more than ``max_stray`` metres from the trajectory: the
    file is then another map's."""
    import numpy as np

    from tmrl.tm.record import load_reward

    name = "reward file"
    try:
        traj = load_reward(path)
    except UserError as err:
        cause, fix = _split(str(err))
        return _fail(name, cause, f"{fix}; for the map tmrl-test, `python -m tmrl --install --env tm20lidar` "
                                  "writes it")
    detail = f"{len(traj)} points ({(len(traj) - 1) * 0.1:.0f} m of track)"
    if position is not None:
        gap = float(np.min(np.linalg.norm(traj - np.asarray(position, dtype=np.float64)[:3], axis=1)))
        if gap > max_stray:
            return _fail(name, f"the car is {gap:.0f} m from the reward trajectory: the reward file is another "
                               "map's",
                         "load the map it was recorded on (tmrl-test for the one --install writes), or record "
                         "this map's with `python -m tmrl --record-reward`")
        detail += f"; the car is {gap:.0f} m from it"
    return _pass(name, detail)


def check_plugins(setting: str = "", resources: Path | None = None, save_replays: bool = False,
                  home: Path | None = None) -> CheckResult:
    """The TMRL plugins in ``OpenplanetNext/Plugins``: TMRL_GrabData always, TMRL_SaveGhost with
    ``save_replays``; their versions, and whether they are the copies ``--install`` brought
    (``resources``: ``resources/Plugins`` of the data folder)."""
    from tmrl.tm.plugins import GRABDATA, SAVEGHOST, find_openplanet, plugin_state

    name = "OpenPlanet plugins"
    install = "run `python -m tmrl --install --env tm20lidar` (it copies the signed plugins)"
    found = find_openplanet(setting, home=home)
    if found.plugins is None:
        if found.from_setting:
            return _fail(name, f"OPENPLANET_FOLDER is {setting!r}, which is not a folder",
                         "set OPENPLANET_FOLDER in config.json to the OpenplanetNext folder, or empty it")
        return _fail(name, f"no OpenplanetNext folder in {found.where()}",
                     "install OpenPlanet (https://openplanet.dev) and start the game once, then " + install
                     + "; or set OPENPLANET_FOLDER in config.json")
    states = [plugin_state(found.plugins, p, resources / p if resources is not None else None)
              for p in (GRABDATA, SAVEGHOST)]
    needed = [st for st in states if st.name == GRABDATA or save_replays]
    missing = [st.name for st in needed if not st.present]
    if missing:
        return _fail(name, f"{' and '.join(missing)} not in {found.plugins}", install)
    stale = [st.name for st in needed if st.matches_reference is False]
    if stale:
        return _fail(name, f"{' and '.join(stale)} in {found.plugins} differs from the copy --install fetched",
                     install + " again: it replaces a copy that differs")
    shown = "; ".join(f"{st.name} v{st.version or '?'}" for st in states if st.present)
    return _pass(name, f"{shown} in {found.plugins}")


def original_tmrl_version(path: list[str] | None = None) -> str | None:
    """The version of the original tmrl (PyPI's ``tmrl``, by trackmania-rl) when pip's metadata
    says it is installed in this Python environment (``path``: where to look, default
    ``sys.path``), else None. This project's own distribution is never taken for it."""
    from importlib import metadata

    for dist in metadata.distributions(**({"path": path} if path is not None else {})):
        if (dist.metadata.get("Name") or "").lower().replace("_", "-") != "tmrl":
            continue
        # The header fields only: a long description (this project's README) may name the original.
        meta = dist.metadata
        header = " ".join(str(v) for key in ("Home-page", "Download-URL", "Author", "Author-email", "Project-URL")
                          for v in (meta.get_all(key) or [])).lower()
        files = [str(f) for f in (dist.files or [])]
        if "trackmania-rl" in header or "bouteiller" in header or any("init_package" in f for f in files):
            return dist.version
    return None


def check_original_tmrl(path: list[str] | None = None) -> CheckResult:
    """Fail when the original tmrl is installed beside this project: both put their files in
    the package folder ``tmrl``, so whichever was installed last wins file by file."""
    name = "original tmrl"
    version = original_tmrl_version(path)
    if version is None:
        return _pass(name, "not installed here (PyPI's tmrl, another project)")
    return _fail(
        name,
        f"the original tmrl {version} (PyPI's tmrl) is installed in this Python environment; its files and this "
        "project's share the package folder tmrl",
        "pip uninstall tmrl, then reinstall this project from its checkout: pip install --force-reinstall --no-deps "
        "., or use a separate virtual environment for each",
    )


def check_gpu(cuda_training: bool = False, cuda_inference: bool = False) -> CheckResult:
    """Whether CUDA is there when the config asks for it."""
    name = "GPU"
    try:
        import torch

        available = bool(torch.cuda.is_available())
        device = torch.cuda.get_device_name(0) if available else "none"
    except Exception as err:  # a broken CUDA install raises from deep inside torch
        available, device = False, f"CUDA error ({type(err).__name__}: {err})"
    wanted = [k for k, v in (("CUDA_TRAINING", cuda_training), ("CUDA_INFERENCE", cuda_inference)) if v]
    if wanted and not available:
        return _fail(
            name,
            f"{' and '.join(wanted)} set but no CUDA device ({device})",
            f"install a CUDA build of PyTorch (https://pytorch.org) or set {' and '.join(wanted)} to false",
        )
    return _pass(
        name, f"CUDA device: {device}" + ("" if wanted else " (not used: CUDA_TRAINING/CUDA_INFERENCE false)")
    )


def check_server(host: str, port: int, timeout: float = 2.0) -> CheckResult:
    """Whether something accepts TCP connections at the server's address."""
    name = "server reachable"
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except OSError as err:
        return _fail(
            name,
            f"nothing accepts connections at {host}:{port} ({err.strerror or err})",
            "start the server (python -m tmrl --server), or fix PORT, LOCALHOST_WORKER and PUBLIC_IP_SERVER "
            "in config.json, and open the port in the server's firewall",
        )
    return _pass(name, f"{host}:{port} accepts connections")


def check_tls(cfg: Mapping[str, Any], credentials_dir: Path | None = None) -> CheckResult:
    """TLS settings: credentials present when TLS is on; TLS on when the server is remote."""
    name = "TLS credentials"
    remote = not (cfg.get("LOCALHOST_WORKER", True) and cfg.get("LOCALHOST_TRAINER", True))
    if cfg.get("TLS", False):
        folder = credentials_dir or _credentials_dir(cfg)
        cert = folder / "certificate.pem"
        if not cert.is_file():
            return _fail(
                name,
                f"TLS is on but {cert} is missing",
                f"run python -m tmrl --install on the server machine to create the credentials, then copy its "
                f"certificate.pem to {folder}",
            )
        return _pass(name, f"certificate at {cert}")
    if remote and not cfg.get("ALLOW_PLAIN_TCP", False):
        return _fail(
            name,
            "the server is on another machine but TLS is off",
            "set TLS to true in config.json (or ALLOW_PLAIN_TCP to true on a trusted private network)",
        )
    return _pass(
        name, "TLS off, connections stay on this machine" if not remote else "TLS off, plain TCP allowed"
    )


def _credentials_dir(cfg: Mapping[str, Any]) -> Path:
    try:
        from tmrl.config.loader import data_paths

        return data_paths(cfg).credentials
    except ImportError:  # pragma: no cover (config package always present in a full install)
        return Path.home() / "TmrlData" / "credentials"


def check_config(cfg: Mapping[str, Any]) -> CheckResult:
    """Consistency of the TrackMania-related keys of a validated config."""
    name = "config"
    env = cfg.get("ENV", {})
    problems: list[tuple[str, str]] = []
    interface = str(env.get("RTGYM_INTERFACE", ""))
    rt = env.get("RTGYM_CONFIG", {})
    step, capture = rt.get("time_step_duration", 0.05), rt.get("start_obs_capture", 0.04)
    if capture > step:
        problems.append(
            (
                f"start_obs_capture ({capture}) is after the end of the step ({step})",
                "set ENV.RTGYM_CONFIG.start_obs_capture below time_step_duration",
            )
        )
    if interface.upper() == "TM20FULL" and (
        env.get("IMG_WIDTH", 64) > env.get("WINDOW_WIDTH", 256)
        or env.get("IMG_HEIGHT", 64) > env.get("WINDOW_HEIGHT", 128)
    ):
        problems.append(
            (
                "IMG_WIDTH/IMG_HEIGHT exceed the window size",
                "make ENV.IMG_WIDTH/IMG_HEIGHT at most ENV.WINDOW_WIDTH/WINDOW_HEIGHT",
            )
        )
    if env.get("REWARD_CONFIG", {}).get("CONSTANT_PENALTY", 0.0) > 0:
        problems.append(
            (
                "REWARD_CONFIG.CONSTANT_PENALTY is positive (a reward for standing still)",
                "set ENV.REWARD_CONFIG.CONSTANT_PENALTY to 0 or a negative value",
            )
        )
    try:
        from tmrl.config.schema import PASSWORD_PLACEHOLDER
    except ImportError:  # pragma: no cover
        PASSWORD_PLACEHOLDER = "YourRandomPasswordHere"
    remote = not (cfg.get("LOCALHOST_WORKER", True) and cfg.get("LOCALHOST_TRAINER", True))
    if remote and cfg.get("PASSWORD") == PASSWORD_PLACEHOLDER:
        problems.append(
            (
                "PASSWORD is still the shipped placeholder and the server is remote",
                "run python -m tmrl --install for a random PASSWORD and copy it to every machine",
            )
        )
    if problems:
        detail = "; ".join(p[0] for p in problems)
        return _fail(name, detail, "; ".join(p[1] for p in problems))
    if interface.upper() not in TM_INTERFACES:
        return _pass(name, f"{interface}, step {step * 1e3:.0f} ms")
    return _pass(
        name,
        f"{interface}, window {env.get('WINDOW_WIDTH')}x{env.get('WINDOW_HEIGHT')}, step {step * 1e3:.0f} ms",
    )


def check_packages(interface: str = "") -> CheckResult:
    """The Python version and the packages tmrl needs (the TrackMania extras for TM20*)."""
    import importlib.util
    import platform

    name = "packages"
    need = ["torch", "gymnasium", "numpy", "tlspyo", "safetensors"]
    extras = ["mss", "cv2"] + (["vgamepad"] if platform.system() == "Windows" else [])
    missing = [m for m in need if importlib.util.find_spec(m) is None]
    if missing:
        return _fail(name, f"missing {', '.join(missing)}",
                     "reinstall this project from its checkout: pip install torch==2.13.0 && pip install .")
    if interface.upper() in TM_INTERFACES:
        gone = [m for m in extras if importlib.util.find_spec(m) is None]
        if gone:
            from tmrl.tm import TRACKMANIA_EXTRA_HINT

            return _fail(name, f"TrackMania needs {', '.join(gone)}", TRACKMANIA_EXTRA_HINT)
    import torch

    return _pass(name, f"Python {platform.python_version()}, torch {torch.__version__}")


def check_data_folder(cfg: Mapping[str, Any]) -> CheckResult:
    """The data folder: there and writable (never created here)."""
    import os

    from tmrl.config.loader import data_paths

    name = "data folder"
    paths = data_paths(cfg)
    if not paths.root.exists():
        return _skip(name, f"{paths.root} does not exist yet: `python -m tmrl --install` creates it")
    if not paths.root.is_dir() or not os.access(paths.root, os.W_OK):
        return _fail(name, f"{paths.root} is not a writable folder", "set TMRL_DATA to a folder you can write")
    if not paths.config_file.is_file():
        return _fail(name, f"{paths.root} has no config/config.json", "run `python -m tmrl --install`")
    return _pass(name, f"{paths.root}, config.json there")


# ---------------------------------------------------------------------------------------- runner
def _guard(name: str, fn: Callable[[], CheckResult]) -> CheckResult:
    try:
        return fn()
    except Exception as err:  # a check must never end the report with a traceback
        logger.debug("check %s crashed", name, exc_info=True)
        return _fail(
            name,
            f"unexpected {type(err).__name__}: {err}",
            "please report this at the tmrl issue tracker with the output of --doctor",
        )


def run_checks(
    cfg: Mapping[str, Any] | None = None,
    *,
    openplanet_host: str = "127.0.0.1",
    openplanet_port: int = 9000,
    openplanet_wait: float = 3.0,
    min_frame_rate: float = 20.0,
    window_title: str = "Trackmania",
    reward_path: str | Path | None = None,
    server_timeout: float = 2.0,
    only: tuple[str, ...] | None = None,
) -> list[CheckResult]:
    """Run every check in order (or those named in ``only``: ``packages``, ``original``, ``data``, ``config``,
    ``plugins``, ``openplanet``, ``window``, ``gamepad``, ``capture``, ``reward``, ``gpu``, ``server``, ``tls``).

    Args:
        cfg: a validated config (``tmrl.config.loader.load_config()``); loaded when None.

    Returns:
        One :class:`CheckResult` per check run.
    """
    if cfg is None:
        from tmrl.config.loader import load_config

        cfg = load_config()
    env = cfg.get("ENV", {})
    width, height = int(env.get("WINDOW_WIDTH", 256)), int(env.get("WINDOW_HEIGHT", 128))
    step = float(env.get("RTGYM_CONFIG", {}).get("time_step_duration", 0.05))
    server_host = (
        "127.0.0.1" if cfg.get("LOCALHOST_WORKER", True) else str(cfg.get("PUBLIC_IP_SERVER", "127.0.0.1"))
    )
    from tmrl.config.loader import data_paths

    paths = data_paths(cfg)
    if reward_path is None:
        reward_path = paths.reward_file
    save_replays = bool(((env.get("RTGYM_CONFIG") or {}).get("interface_kwargs") or {}).get("save_replays", False))
    max_stray = float((env.get("REWARD_CONFIG") or {}).get("MAX_STRAY", 100.0))
    state: dict[str, CheckResult] = {}

    def capture() -> CheckResult:
        if "window" in state and not state["window"].ok:
            return _skip("capture time", "needs the game window (see above)")
        return check_capture_speed(
            window_title,
            width,
            height,
            int(env.get("IMG_WIDTH", 64)),
            int(env.get("IMG_HEIGHT", 64)),
            bool(env.get("IMG_GRAYSCALE", True)),
            step,
        )

    interface = str(env.get("RTGYM_INTERFACE", ""))
    game = interface.upper() in TM_INTERFACES

    def tm_only(title: str, fn: Callable[[], CheckResult]) -> Callable[[], CheckResult]:
        return fn if game else (lambda: _skip(title, f"not needed for {interface}"))

    checks: list[tuple[str, str, Callable[[], CheckResult]]] = [
        ("packages", "packages", lambda: check_packages(interface)),
        ("original", "original tmrl", check_original_tmrl),
        ("data", "data folder", lambda: check_data_folder(cfg)),
        ("config", "config", lambda: check_config(cfg)),
        ("plugins", "OpenPlanet plugins", tm_only("OpenPlanet plugins", lambda: check_plugins(
            str(cfg.get("OPENPLANET_FOLDER", "") or ""), paths.root / "resources" / "Plugins", save_replays))),
        (
            "openplanet",
            "OpenPlanet telemetry",
            tm_only("OpenPlanet telemetry", lambda: check_openplanet(
                openplanet_host, openplanet_port, openplanet_wait, min_rate=min_frame_rate
            )),
        ),
        ("window", "game window", tm_only("game window", lambda: check_window(window_title, width, height))),
        ("gamepad", "gamepad driver",
         tm_only("gamepad driver", lambda: check_gamepad(bool(cfg.get("VIRTUAL_GAMEPAD", True))))),
        ("capture", "capture time", tm_only("capture time", capture)),
        ("reward", "reward file", tm_only("reward file", lambda: check_reward_file(
            reward_path, getattr(state.get("openplanet"), "data", None) and state["openplanet"].data[2:5], max_stray))),
        ("gpu", "GPU", lambda: check_gpu(bool(cfg.get("CUDA_TRAINING")), bool(cfg.get("CUDA_INFERENCE")))),
        (
            "server",
            "server reachable",
            lambda: check_server(server_host, int(cfg.get("PORT", 55555)), server_timeout),
        ),
        ("tls", "TLS credentials", lambda: check_tls(cfg)),
    ]
    results = []
    for key, name, fn in checks:
        if only is not None and key not in only:
            continue
        state[key] = _guard(name, fn)
        results.append(state[key])
    return results


def format_report(results: list[CheckResult]) -> str:
    """The pass/fail list: one line per check, an indented ``fix:`` line under each failure."""
    width = max((len(r.name) for r in results), default=0)
    lines = []
    for r in results:
        lines.append(f"[{r.status.upper():4}] {r.name:<{width}}  {r.detail}")
        if r.status == "fail":
            lines.append(f"       {'':<{width}}  fix: {r.fix}")
    failed = sum(r.status == "fail" for r in results)
    lines.append(f"{len(results) - failed} of {len(results)} checks passed or skipped, {failed} failed")
    return "\n".join(lines)


def run_doctor(cfg: Mapping[str, Any] | None = None, out: TextIO | None = None, **kwargs: Any) -> int:
    """Run the checks, print the report to ``out`` (default stdout), return the exit code:
    0 when nothing failed, :data:`CHECKS_FAILED` (3) otherwise. Keyword arguments go to
    :func:`run_checks`."""
    out = sys.stdout if out is None else out
    results = run_checks(cfg, **kwargs)
    print(format_report(results), file=out, flush=True)
    return 0 if all(r.ok for r in results) else CHECKS_FAILED
