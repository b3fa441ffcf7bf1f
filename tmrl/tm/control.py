"""Control of TrackMania 2020: a virtual Xbox 360 gamepad (analog) or the keyboard (binary).

Actions are ``[gas, brake, steer]`` in ``[-1, 1]`` (the original tmrl action space). The gamepad
maps gas to the right trigger, brake to the left trigger and steer to the left stick's X axis;
respawn is button B, closing the finish pop-up is button A.

Both controllers take an injectable backend, so tests record calls instead of driving a device:

- :class:`GamepadControl` takes any object with vgamepad's ``VX360Gamepad`` methods
  (``right_trigger_float``, ``left_trigger_float``, ``left_joystick_float``, ``press_button``,
  ``release_button``, ``update``, ``reset``); :func:`make_vgamepad` builds the real one.
- :class:`KeyboardControl` takes an object with ``press(key)`` and ``release(key)``;
  :func:`make_keyboard` builds the platform's (SendInput through ctypes on Windows, XTest through
  python-xlib or xdotool on Linux).

Driver problems (ViGEmBus missing on Windows, no access to ``/dev/uinput`` on Linux) raise
:class:`ControlUnavailable`, a one-line :class:`~tmrl.errors.UserError` naming the fix. The driver
is looked for before vgamepad is imported: on Windows, vgamepad starts ViGEmBus's interactive
installer when it is imported without the driver, which would block a worker or ``--doctor``
behind a dialog. :func:`vigembus_installed` reads the Windows registry instead, and vgamepad is
imported with ``VGAMEPAD_SKIP_VIGEMBUS_INSTALL`` set.
"""

from __future__ import annotations

import logging
import os
import platform
import shutil
import subprocess
import time
from typing import Any, Callable, Protocol, Sequence

from tmrl.errors import UserError
from tmrl.tm import TRACKMANIA_EXTRA_HINT

__all__ = [
    "BUTTON_A",
    "BUTTON_B",
    "DPAD_DOWN",
    "DPAD_UP",
    "ControlUnavailable",
    "GamepadControl",
    "KeyboardControl",
    "check_gamepad_driver",
    "vigembus_installed",
    "make_keyboard",
    "make_vgamepad",
]

logger = logging.getLogger(__name__)

# XUSB button bits (the values of vgamepad.XUSB_BUTTON), kept here so no import is needed.
DPAD_UP = 0x0001
"""Button code of the D-pad's up direction."""
DPAD_DOWN = 0x0002
"""Button code of the D-pad's down direction."""
BUTTON_A = 0x1000
"""Button code of A (confirms; closes the finish pop-up)."""
BUTTON_B = 0x2000
"""Button code of B (respawns)."""

UINPUT_PATH = "/dev/uinput"
UDEV_RULE = 'KERNEL=="uinput", MODE="0660", GROUP="input", OPTIONS+="static_node=uinput"'
VIGEMBUS_URL = "https://github.com/nefarius/ViGEmBus/releases"
# vgamepad's switch that stops it from running the ViGEmBus installer when it is imported.
_SKIP_INSTALLER_ENV = "VGAMEPAD_SKIP_VIGEMBUS_INSTALL"
_VIGEMBUS_SERVICE = r"SYSTEM\CurrentControlSet\Services\ViGEmBus"
_UNINSTALL_KEYS = (r"SOFTWARE\Microsoft\Windows\CurrentVersion\Uninstall",
                   r"SOFTWARE\WOW6432Node\Microsoft\Windows\CurrentVersion\Uninstall")


class ControlUnavailable(UserError):
    """The gamepad or keyboard cannot be driven on this machine; the message names the fix."""


class GamepadBackend(Protocol):
    def right_trigger_float(self, value_float: float) -> None: ...
    def left_trigger_float(self, value_float: float) -> None: ...
    def left_joystick_float(self, x_value_float: float, y_value_float: float) -> None: ...
    def press_button(self, button: int) -> None: ...
    def release_button(self, button: int) -> None: ...
    def update(self) -> None: ...
    def reset(self) -> None: ...


class KeyboardBackend(Protocol):
    def press(self, key: str) -> None: ...
    def release(self, key: str) -> None: ...


# ---------------------------------------------------------------------------------------- drivers
def _uinput_fix(path: str = UINPUT_PATH) -> str | None:
    """None when ``path`` is writable, else the one-line fix."""
    if not os.path.exists(path):
        return (
            f"{path} does not exist: load the uinput module (sudo modprobe uinput), "
            "or use the keyboard (--use-keyboard)"
        )
    if not os.access(path, os.R_OK | os.W_OK):
        return (
            f"no read/write access to {path}: add the udev rule '{UDEV_RULE}' to "
            f"/etc/udev/rules.d/99-uinput.rules, add yourself to the input group "
            f"(sudo usermod -aG input $USER), "
            f"then log in again; or use the keyboard (--use-keyboard)"
        )
    return None


def vigembus_installed() -> bool | None:
    """Whether the ViGEmBus driver is installed, from the Windows registry (its service key, or
    its entry among the installed programs); None where there is no registry to read."""
    try:
        import winreg  # type: ignore[import-not-found]
    except ImportError:
        return None
    hklm = winreg.HKEY_LOCAL_MACHINE  # type: ignore[attr-defined]
    try:
        winreg.CloseKey(winreg.OpenKey(hklm, _VIGEMBUS_SERVICE))  # type: ignore[attr-defined]
        return True
    except OSError:
        pass
    for path in _UNINSTALL_KEYS:
        try:
            root = winreg.OpenKey(hklm, path)  # type: ignore[attr-defined]
        except OSError:
            continue
        with root:
            for i in range(winreg.QueryInfoKey(root)[0]):  # type: ignore[attr-defined]
                try:
                    with winreg.OpenKey(root, winreg.EnumKey(root, i)) as sub:  # type: ignore[attr-defined]
                        name = str(winreg.QueryValueEx(sub, "DisplayName")[0])  # type: ignore[attr-defined]
                except OSError:
                    continue
                if "virtual gamepad emulation bus" in name.lower() or "vigembus" in name.lower():
                    return True
    return False


def _no_vigembus_fix() -> str:
    return (f"the ViGEmBus driver is not installed: install it ({VIGEMBUS_URL}) and restart, or drive with "
            "the keyboard (VIRTUAL_GAMEPAD false in config.json)")


def check_gamepad_driver(system: str | None = None, uinput_path: str = UINPUT_PATH) -> tuple[bool, str]:
    """Whether a virtual gamepad can be created here, without creating one on Linux.

    Args:
        system: the operating system as :func:`platform.system` names it; None for this one.
        uinput_path: the Linux uinput device the gamepad is created through.

    Returns:
        ``(True, description)`` or ``(False, one-line fix)``.
    """
    system = system or platform.system()
    if system == "Linux":
        fix = _uinput_fix(uinput_path)
        if fix is not None:
            return False, fix
        try:
            import vgamepad  # noqa: F401
        except ImportError as err:
            return False, _import_fix(err)
        except OSError as err:  # libevdev's shared library is missing
            return False, f"vgamepad cannot load libevdev ({err}): install it (sudo apt install libevdev2)"
        return True, f"{uinput_path} is writable and vgamepad imports"
    if system == "Windows":
        if vigembus_installed() is False:  # never import vgamepad then: it would start the installer
            return False, _no_vigembus_fix()
        try:
            pad = make_vgamepad()
        except ControlUnavailable as err:
            return False, str(err)
        del pad
        return True, "ViGEmBus answered: a virtual Xbox 360 gamepad was created"
    return False, f"no virtual gamepad on {system}: TrackMania 2020 runs on Windows (or Linux through Proton)"


def _import_fix(err: ImportError) -> str:
    missing = getattr(err, "name", None) or str(err)
    if missing and "libevdev" in missing:
        return f"vgamepad needs the libevdev Python package on Linux ({err}): {TRACKMANIA_EXTRA_HINT}"
    return f"vgamepad is not installed ({err}): {TRACKMANIA_EXTRA_HINT}"


def make_vgamepad() -> Any:
    """Create a real virtual Xbox 360 gamepad with vgamepad.

    Raises:
        ControlUnavailable: vgamepad is missing, ViGEmBus is not installed (Windows) or
            ``/dev/uinput`` cannot be opened (Linux); the message names the fix.
    """
    system = platform.system()
    if system == "Linux":
        fix = _uinput_fix()
        if fix is not None:
            raise ControlUnavailable(fix)
    if system == "Windows":
        if vigembus_installed() is False:
            raise ControlUnavailable(_no_vigembus_fix())
        os.environ.setdefault(_SKIP_INSTALLER_ENV, "true")  # the driver is there: no installer wanted
    try:
        import vgamepad
    except ImportError as err:
        raise ControlUnavailable(_import_fix(err)) from None
    except OSError as err:
        raise ControlUnavailable(
            f"vgamepad cannot load its driver library ({err}): {_driver_fix(system)}"
        ) from None
    try:
        return vgamepad.VX360Gamepad()
    except PermissionError as err:
        raise ControlUnavailable(_uinput_fix() or f"permission denied ({err})") from None
    except Exception as err:  # vgamepad reports a missing ViGEmBus with assorted exception types
        raise ControlUnavailable(
            f"could not create a virtual gamepad ({type(err).__name__}: {err}): {_driver_fix(system)}"
        ) from None


def _driver_fix(system: str) -> str:
    if system == "Windows":
        return (
            f"install the ViGEmBus driver ({VIGEMBUS_URL}) and restart, or use the keyboard (--use-keyboard)"
        )
    return (
        f"install libevdev (sudo apt install libevdev2) and make {UINPUT_PATH} writable "
        f"(udev rule '{UDEV_RULE}')"
    )


# ---------------------------------------------------------------------------------------- gamepad
def _clip(value: float) -> float:
    return -1.0 if value < -1.0 else 1.0 if value > 1.0 else float(value)


class GamepadControl:
    """Analog control through a virtual Xbox 360 gamepad.

    Args:
        backend: a ``VX360Gamepad``-like object; default: :func:`make_vgamepad`.
        sleep: the function used to wait between a button press and its release (injectable so
            tests need not wait).
        press_time: seconds a button is held.
    """

    def __init__(
        self,
        backend: GamepadBackend | None = None,
        sleep: Callable[[float], None] = time.sleep,
        press_time: float = 0.1,
    ) -> None:
        self.pad = make_vgamepad() if backend is None else backend
        self._sleep = sleep
        self.press_time = press_time

    def send(self, action: Sequence[float]) -> None:
        """Set the triggers and the stick.

        Args:
            action: ``[gas, brake, steer]``, clipped to [-1, 1]; negative gas or brake is 0,
                steer > 0 turns right.
        """
        gas, brake, steer = (_clip(float(a)) for a in action[:3])
        self.pad.right_trigger_float(value_float=max(gas, 0.0))
        self.pad.left_trigger_float(value_float=max(brake, 0.0))
        self.pad.left_joystick_float(x_value_float=steer, y_value_float=0.0)
        self.pad.update()

    def tap(self, button: int) -> None:
        """Press one button, hold it ``press_time`` seconds, release it.

        Args:
            button: a vgamepad button code (:data:`BUTTON_A`, :data:`BUTTON_B`...).
        """
        self.pad.press_button(button=button)
        self.pad.update()
        self._sleep(self.press_time)
        self.pad.release_button(button=button)
        self.pad.update()

    def respawn(self) -> None:
        """Release everything, then press B (respawn at the start of a map without checkpoints)."""
        self.pad.reset()
        self.tap(BUTTON_B)

    def close_finish_pop_up(self) -> None:
        """Release everything, then press A (closes the pop-up shown after the finish line)."""
        self.pad.reset()
        self.tap(BUTTON_A)

    def save_replay(self, settle_time: float = 5.0, step_time: float = 0.2) -> None:
        """Save the replay from the finish screen: wait, D-pad down, A, D-pad up, A.

        Args:
            settle_time: seconds to wait for the finish screen before the first press.
            step_time: seconds between two presses.
        """
        self._sleep(settle_time)
        self.pad.reset()
        for i, button in enumerate((DPAD_DOWN, BUTTON_A, DPAD_UP, BUTTON_A)):
            if i:
                self._sleep(step_time)
            self.tap(button)


# ---------------------------------------------------------------------------------------- keyboard
# Default keys per system (TrackMania 2020's default bindings): Windows drives with W/A/S/D and
# respawns with Delete; Linux (Proton) drives with the arrows and respawns with BackSpace.
KEYS = {
    "Windows": {"gas": "w", "brake": "s", "left": "a", "right": "d", "respawn": "delete"},
    "Linux": {"gas": "Up", "brake": "Down", "left": "Left", "right": "Right", "respawn": "BackSpace"},
}


class KeyboardControl:
    """Binary control through the keyboard: gas if ``action[0] > 0``, brake if ``action[1] > 0``,
    right if ``action[2] > 0.5``, left if ``action[2] < -0.5``.

    Args:
        backend: an object with ``press(key)``/``release(key)``; default: :func:`make_keyboard`.
        keys: key names for ``gas``, ``brake``, ``left``, ``right``, ``respawn``; default: the
            platform's TrackMania bindings (:data:`KEYS`).
        sleep: wait function between press and release.
        press_time: seconds the respawn key is held.
    """

    def __init__(
        self,
        backend: KeyboardBackend | None = None,
        keys: dict[str, str] | None = None,
        sleep: Callable[[float], None] = time.sleep,
        press_time: float = 0.05,
    ) -> None:
        self.keys = dict(keys or KEYS.get(platform.system(), KEYS["Linux"]))
        self.kb = make_keyboard() if backend is None else backend
        self._sleep = sleep
        self.press_time = press_time
        self._down: set[str] = set()

    def _set(self, name: str, pressed: bool) -> None:
        key = self.keys[name]
        if pressed and key not in self._down:
            self.kb.press(key)
            self._down.add(key)
        elif not pressed and key in self._down:
            self.kb.release(key)
            self._down.discard(key)

    def send(self, action: Sequence[float]) -> None:
        """Press and release keys for an action (only changes are sent).

        Args:
            action: ``[gas, brake, steer]``: gas if ``gas > 0``, brake if ``brake > 0``, right if
                ``steer > 0.5``, left if ``steer < -0.5``.
        """
        gas, brake, steer = (float(a) for a in action[:3])
        self._set("gas", gas > 0)
        self._set("brake", brake > 0)
        self._set("right", steer > 0.5)
        self._set("left", steer < -0.5)

    def release_all(self) -> None:
        """Release the driving keys that are down."""
        for name in ("gas", "brake", "left", "right"):
            self._set(name, False)

    def respawn(self) -> None:
        """Release the driving keys, then tap the respawn key."""
        self.release_all()
        key = self.keys["respawn"]
        self.kb.press(key)
        self._sleep(self.press_time)
        self.kb.release(key)

    def close_finish_pop_up(self) -> None:
        """Keyboard players close the pop-up by respawning; nothing extra to do."""

    def save_replay(self, settle_time: float = 5.0, step_time: float = 0.2) -> None:
        """Not available with the keyboard (the original clicks with the mouse); logs a warning and
        returns.

        Args:
            settle_time: ignored (the gamepad's signature).
            step_time: ignored.
        """
        logger.warning("saving replays needs the gamepad (ENV.VIRTUAL_GAMEPAD=true); skipped")


class _XTestKeyboard:
    """Linux keyboard through the X Test extension (python-xlib)."""

    def __init__(self) -> None:
        from Xlib import XK, display  # python-xlib, in the trackmania extra on Linux
        from Xlib.ext import xtest

        self._XK, self._xtest = XK, xtest
        self._d = display.Display()

    def _code(self, key: str) -> int:
        sym = self._XK.string_to_keysym(key)
        code = self._d.keysym_to_keycode(sym)
        if not code:
            raise ControlUnavailable(f"no keycode for key {key!r} on this X display: choose another key name")
        return code

    def press(self, key: str) -> None:
        from Xlib import X

        self._xtest.fake_input(self._d, X.KeyPress, self._code(key))
        self._d.sync()

    def release(self, key: str) -> None:
        from Xlib import X

        self._xtest.fake_input(self._d, X.KeyRelease, self._code(key))
        self._d.sync()


class _XdotoolKeyboard:
    def press(self, key: str) -> None:
        subprocess.run(["xdotool", "keydown", key], check=False)

    def release(self, key: str) -> None:
        subprocess.run(["xdotool", "keyup", key], check=False)


def _sendinput_structs() -> tuple[type, type]:
    """``(KEYBDINPUT, INPUT)`` of user32 with fixed-size fields (``wintypes`` sizes are wrong off
    Windows, and explicit sizes keep ``sizeof(INPUT)`` right on 32- and 64-bit Windows)."""
    import ctypes

    class KEYBDINPUT(ctypes.Structure):
        _fields_ = [
            ("wVk", ctypes.c_uint16),
            ("wScan", ctypes.c_uint16),
            ("dwFlags", ctypes.c_uint32),
            ("time", ctypes.c_uint32),
            ("dwExtraInfo", ctypes.c_size_t),
        ]

    class MOUSEINPUT(ctypes.Structure):
        _fields_ = [
            ("dx", ctypes.c_int32),
            ("dy", ctypes.c_int32),
            ("mouseData", ctypes.c_uint32),
            ("dwFlags", ctypes.c_uint32),
            ("time", ctypes.c_uint32),
            ("dwExtraInfo", ctypes.c_size_t),
        ]

    class HARDWAREINPUT(ctypes.Structure):
        _fields_ = [("uMsg", ctypes.c_uint32), ("wParamL", ctypes.c_uint16), ("wParamH", ctypes.c_uint16)]

    class _INPUTUNION(ctypes.Union):
        _fields_ = [("ki", KEYBDINPUT), ("mi", MOUSEINPUT), ("hi", HARDWAREINPUT)]

    class INPUT(ctypes.Structure):
        _fields_ = [("type", ctypes.c_uint32), ("u", _INPUTUNION)]

    return KEYBDINPUT, INPUT


class _SendInputKeyboard:
    """Windows keyboard through user32.SendInput with hardware scan codes (no pywin32)."""

    # Set-1 scan codes; the arrows and Delete are "extended" keys (E0 prefix).
    SCAN = {
        "w": 0x11,
        "a": 0x1E,
        "s": 0x1F,
        "d": 0x20,
        "r": 0x13,
        "enter": 0x1C,
        "backspace": 0x0E,
        "delete": 0x53,
        "up": 0x48,
        "down": 0x50,
        "left": 0x4B,
        "right": 0x4D,
    }
    EXTENDED = frozenset({"delete", "up", "down", "left", "right"})
    KEYEVENTF_EXTENDEDKEY, KEYEVENTF_KEYUP, KEYEVENTF_SCANCODE = 0x0001, 0x0002, 0x0008

    def __init__(self) -> None:
        import ctypes

        self._ctypes = ctypes
        self._KEYBDINPUT, self._INPUT = _sendinput_structs()
        self._send = ctypes.windll.user32.SendInput  # type: ignore[attr-defined]
        self._send.argtypes = [ctypes.c_uint, ctypes.c_void_p, ctypes.c_int]
        self._send.restype = ctypes.c_uint

    def _emit(self, key: str, up: bool) -> None:
        name = key.lower()
        if name not in self.SCAN:
            raise ControlUnavailable(f"unknown key {key!r}: use one of {sorted(self.SCAN)}")
        flags = self.KEYEVENTF_SCANCODE | (self.KEYEVENTF_KEYUP if up else 0)
        if name in self.EXTENDED:
            flags |= self.KEYEVENTF_EXTENDEDKEY
        inp = self._INPUT(type=1)  # INPUT_KEYBOARD
        inp.u.ki = self._KEYBDINPUT(0, self.SCAN[name], flags, 0, 0)
        if self._send(1, self._ctypes.byref(inp), self._ctypes.sizeof(inp)) != 1:
            raise ControlUnavailable(
                "Windows refused the key press (SendInput): run tmrl with the same rights as the game "
                "(not one elevated and the other not)"
            )

    def press(self, key: str) -> None:
        self._emit(key, up=False)

    def release(self, key: str) -> None:
        self._emit(key, up=True)


def make_keyboard() -> KeyboardBackend:
    """The platform's keyboard backend.

    Raises:
        ControlUnavailable: no way to send keys here (no X display, neither python-xlib nor xdotool).
    """
    system = platform.system()
    if system == "Windows":
        return _SendInputKeyboard()
    if system == "Linux":
        if not os.environ.get("DISPLAY"):
            raise ControlUnavailable(
                "no X display (DISPLAY is unset): run from the desktop session that shows the game"
            )
        try:
            return _XTestKeyboard()
        except ImportError:
            if shutil.which("xdotool"):
                return _XdotoolKeyboard()
            raise ControlUnavailable(
                f"no way to send keys: {TRACKMANIA_EXTRA_HINT} (python-xlib) or install xdotool"
            ) from None
    raise ControlUnavailable(f"keyboard control is not supported on {system}")
