"""Gamepad and keyboard control through injected backends that record every call."""

from __future__ import annotations

import os
import sys

import pytest

from tmrl.errors import UserError
from tmrl.tm import control
from tmrl.tm.control import (
    BUTTON_A,
    BUTTON_B,
    DPAD_DOWN,
    DPAD_UP,
    ControlUnavailable,
    GamepadControl,
    KeyboardControl,
    check_gamepad_driver,
)


class RecordingPad:
    def __init__(self):
        self.calls: list[tuple] = []

    def __getattr__(self, name):
        def record(*args, **kwargs):
            self.calls.append((name, *args, *kwargs.values()))

        return record


class RecordingKeys:
    def __init__(self):
        self.calls: list[tuple[str, str]] = []

    def press(self, key):
        self.calls.append(("press", key))

    def release(self, key):
        self.calls.append(("release", key))


@pytest.fixture
def pad():
    return RecordingPad()


def test_analog_action_maps_to_triggers_and_stick(pad):
    c = GamepadControl(backend=pad, sleep=lambda s: None)
    c.send([0.75, 0.25, -0.5])
    assert pad.calls == [
        ("right_trigger_float", 0.75),
        ("left_trigger_float", 0.25),
        ("left_joystick_float", -0.5, 0.0),
        ("update",),
    ]


def test_negative_pedals_are_zero_and_values_are_clipped(pad):
    c = GamepadControl(backend=pad, sleep=lambda s: None)
    c.send([-0.3, 2.0, 1.7])
    assert pad.calls[:3] == [
        ("right_trigger_float", 0.0),
        ("left_trigger_float", 1.0),
        ("left_joystick_float", 1.0, 0.0),
    ]


def test_respawn_presses_b_and_close_pop_up_presses_a(pad):
    waits = []
    c = GamepadControl(backend=pad, sleep=waits.append)
    c.respawn()
    c.close_finish_pop_up()
    assert pad.calls == [
        ("reset",),
        ("press_button", BUTTON_B),
        ("update",),
        ("release_button", BUTTON_B),
        ("update",),
        ("reset",),
        ("press_button", BUTTON_A),
        ("update",),
        ("release_button", BUTTON_A),
        ("update",),
    ]
    assert waits == [0.1, 0.1]


def test_save_replay_sequence(pad):
    waits = []
    GamepadControl(backend=pad, sleep=waits.append).save_replay()
    pressed = [c[1] for c in pad.calls if c[0] == "press_button"]
    released = [c[1] for c in pad.calls if c[0] == "release_button"]
    assert pressed == released == [DPAD_DOWN, BUTTON_A, DPAD_UP, BUTTON_A]
    assert pad.calls[0] == ("reset",)
    assert waits[0] == 5.0  # the finish screen settles before the menu is used


def test_keyboard_sends_only_changes():
    kb = RecordingKeys()
    keys = {"gas": "Up", "brake": "Down", "left": "Left", "right": "Right", "respawn": "BackSpace"}
    c = KeyboardControl(backend=kb, keys=keys, sleep=lambda s: None)
    c.send([1.0, 0.0, 0.9])
    c.send([1.0, 0.0, 0.9])  # nothing changes: nothing sent
    c.send([0.0, 0.5, -0.9])
    assert kb.calls == [
        ("press", "Up"),
        ("press", "Right"),
        ("release", "Up"),
        ("press", "Down"),
        ("release", "Right"),
        ("press", "Left"),
    ]
    kb.calls.clear()
    c.respawn()
    assert kb.calls == [
        ("release", "Down"),
        ("release", "Left"),
        ("press", "BackSpace"),
        ("release", "BackSpace"),
    ]


def test_uinput_missing_names_the_fix(tmp_path):
    ok, msg = check_gamepad_driver(system="Linux", uinput_path=str(tmp_path / "uinput"))
    assert not ok and "modprobe uinput" in msg and "\n" not in msg


@pytest.mark.linux  # /dev/uinput
@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root can open any file")
def test_uinput_without_permission_names_the_udev_rule(tmp_path):
    dev = tmp_path / "uinput"
    dev.write_bytes(b"")
    dev.chmod(0o400)
    ok, msg = check_gamepad_driver(system="Linux", uinput_path=str(dev))
    assert not ok and 'KERNEL=="uinput"' in msg and "input group" in msg


def test_uinput_fix_for_an_unwritable_node(tmp_path, monkeypatch):
    dev = tmp_path / "uinput"
    dev.write_bytes(b"")
    monkeypatch.setattr(control.os, "access", lambda path, mode: False)
    msg = control._uinput_fix(str(dev))
    assert 'KERNEL=="uinput"' in msg and "usermod -aG input" in msg


def test_missing_vigembus_is_one_line(monkeypatch):
    class BrokenVgamepad:
        class VX360Gamepad:
            def __init__(self):
                raise AssertionError("VIGEM_ERROR_BUS_NOT_FOUND")

    monkeypatch.setattr(control.platform, "system", lambda: "Windows")
    monkeypatch.setitem(sys.modules, "vgamepad", BrokenVgamepad)
    with pytest.raises(ControlUnavailable) as err:
        control.make_vgamepad()
    assert isinstance(err.value, UserError)
    assert "ViGEmBus" in str(err.value) and "\n" not in str(err.value)


def test_missing_vgamepad_names_the_extra(monkeypatch):
    monkeypatch.setattr(control.platform, "system", lambda: "Windows")
    monkeypatch.setitem(sys.modules, "vgamepad", None)  # import raises ImportError
    with pytest.raises(ControlUnavailable, match=r"pip install \"\.\[trackmania\]\""):
        control.make_vgamepad()


def test_sendinput_structures_have_the_windows_sizes():
    import ctypes

    keybd, inp = control._sendinput_structs()
    wide = ctypes.sizeof(ctypes.c_void_p) == 8
    assert ctypes.sizeof(inp) == (40 if wide else 28)
    assert ctypes.sizeof(keybd) == (24 if wide else 16)


def test_sendinput_keyboard_sends_scan_codes_with_extended_flags():
    import ctypes

    sent = []
    kb = object.__new__(control._SendInputKeyboard)
    kb._ctypes = ctypes
    kb._KEYBDINPUT, kb._INPUT = control._sendinput_structs()

    def fake_send(n, ref, size):
        struct_ = ref._obj
        sent.append((n, struct_.type, struct_.u.ki.wScan, struct_.u.ki.dwFlags, size))
        return 1

    kb._send = fake_send
    kb.press("w")
    kb.release("Delete")
    assert sent == [
        (1, 1, 0x11, 0x0008, ctypes.sizeof(kb._INPUT)),
        (1, 1, 0x53, 0x0008 | 0x0002 | 0x0001, ctypes.sizeof(kb._INPUT)),
    ]
    with pytest.raises(ControlUnavailable, match="unknown key"):
        kb.press("F13")
