"""Reward recording: resampling against hand-computed points, refusal of degenerate recordings,
the data-only file format and the restricted reader of legacy reward.pkl files."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest

from tmrl.errors import UserError
from tmrl.tm.record import (
    DegenerateRecording,
    RewardFileError,
    default_reward_path,
    load_reward,
    read_legacy_reward_pickle,
    record_reward,
    resample_path,
    save_reward,
    trim_stationary_start,
    validate_recording,
)


def test_resample_straight_line_every_10_cm():
    out = resample_path(np.array([[0.0, 0, 0], [1.0, 0, 0]]))
    assert out.shape == (11, 3)
    np.testing.assert_allclose(out[:, 0], np.arange(11) * 0.1, atol=1e-12)
    assert np.all(out[:, 1:] == 0)


def test_resample_follows_corners_and_drops_the_short_tail():
    # L-shaped path: 0.25 m along x, then 0.27 m along y (total 0.52 m: the last 2 cm are dropped)
    path = np.array([[0.0, 0, 0], [0.25, 0, 0], [0.25, 0.27, 0]])
    out = resample_path(path)
    expected = np.array(
        [[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.25, 0.05, 0], [0.25, 0.15, 0], [0.25, 0.25, 0]]
    )
    np.testing.assert_allclose(out, expected, atol=1e-12)


def test_resample_ignores_repeated_positions():
    path = np.array([[0.0, 0, 0], [0.0, 0, 0], [0.15, 0, 0], [0.15, 0, 0], [0.3, 0, 0]])
    np.testing.assert_allclose(resample_path(path)[:, 0], [0.0, 0.1, 0.2, 0.3], atol=1e-12)


def test_trim_stationary_start_keeps_the_last_still_point():
    p = np.array([[5.0, 1, 2]] * 4 + [[5.5, 1, 2], [6.0, 1, 2]])
    np.testing.assert_array_equal(trim_stationary_start(p), p[3:])


@pytest.mark.parametrize(
    "positions, finished, needle",
    [
        (np.zeros((2, 3)), True, "only 2 positions"),
        (np.ones((50, 3)), True, "never moved"),
        (np.c_[np.linspace(0, 3, 50), np.zeros(50), np.zeros(50)], True, "only 3.0 m"),
        (np.c_[np.linspace(0, 300, 50), np.zeros(50), np.zeros(50)], False, "finish line was never reached"),
    ],
)
def test_degenerate_recordings_are_refused(positions, finished, needle):
    with pytest.raises(DegenerateRecording) as err:
        validate_recording(positions, finished)
    assert needle in str(err.value)
    assert isinstance(err.value, UserError) and "\n" not in str(err.value)


def test_save_and_load_round_trip_without_pickle(tmp_path):
    traj = np.random.default_rng(0).normal(size=(100, 3))
    path = save_reward(traj, tmp_path / "reward" / "reward.npy")
    np.testing.assert_array_equal(np.load(path, allow_pickle=False), traj)
    np.testing.assert_array_equal(load_reward(path), traj)
    assert [p.name for p in path.parent.iterdir()] == ["reward.npy"]  # no temporary file left


def test_default_path_is_under_the_data_folder(_isolated_data_folder):
    assert default_reward_path() == _isolated_data_folder / "reward" / "reward.npy"


def test_missing_reward_file_says_how_to_record_one(tmp_path):
    with pytest.raises(RewardFileError, match="--record-reward"):
        load_reward(tmp_path / "nothing.npy")
    with pytest.raises(RewardFileError, match="no reward file at"):
        load_reward()


def test_wrong_shape_is_refused(tmp_path):
    np.save(tmp_path / "r.npy", np.zeros((10, 2)))
    with pytest.raises(RewardFileError, match=r"shape \(10, 2\)"):
        load_reward(tmp_path / "r.npy")


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_legacy_pickle_is_read_as_an_array(tmp_path, protocol):
    traj = np.random.default_rng(protocol).normal(size=(37, 3))
    (tmp_path / "reward.pkl").write_bytes(pickle.dumps(traj, protocol=protocol))
    np.testing.assert_array_equal(read_legacy_reward_pickle(tmp_path / "reward.pkl"), traj)
    np.testing.assert_array_equal(load_reward(tmp_path / "reward.pkl"), traj)


@pytest.mark.parametrize(
    "arr",
    [
        np.asfortranarray(np.arange(30, dtype=np.float32).reshape(10, 3)),
        np.arange(30, dtype=">f8").reshape(10, 3),
        np.arange(30, dtype=np.int64).reshape(10, 3),
    ],
)
def test_legacy_pickle_dtypes_and_orders(tmp_path, arr):
    (tmp_path / "r.pkl").write_bytes(pickle.dumps(arr, protocol=4))
    out = read_legacy_reward_pickle(tmp_path / "r.pkl")
    np.testing.assert_array_equal(out, arr)
    assert out.dtype == arr.dtype


def test_legacy_default_path_falls_back_to_reward_pkl(_isolated_data_folder):
    traj = np.arange(30.0).reshape(10, 3)
    (_isolated_data_folder / "reward").mkdir(parents=True)
    (_isolated_data_folder / "reward" / "reward.pkl").write_bytes(pickle.dumps(traj))
    np.testing.assert_array_equal(load_reward(), traj)


class Payload:
    def __init__(self, target):
        self.target = target

    def __reduce__(self):
        return (os.mkdir, (self.target,))


def test_malicious_pickle_is_refused_and_nothing_runs(tmp_path):
    target = tmp_path / "pwned"
    (tmp_path / "reward.pkl").write_bytes(pickle.dumps(Payload(str(target))))
    with pytest.raises(
        RewardFileError, match="refusing to reference posix.mkdir|refusing to reference os.mkdir"
    ):
        load_reward(tmp_path / "reward.pkl")
    assert not target.exists()


@pytest.mark.parametrize(
    "obj, needle",
    [
        (np.array([[1, 2, 3]], dtype=object), "object|dtype|opcode"),
        ({"a": 1}, "opcode"),
        ([1.0, 2.0], "opcode|not a NumPy array"),
    ],
)
def test_non_arrays_are_refused(tmp_path, obj, needle):
    (tmp_path / "r.pkl").write_bytes(pickle.dumps(obj, protocol=4))
    with pytest.raises(ValueError, match=needle):
        read_legacy_reward_pickle(tmp_path / "r.pkl")


def test_truncated_pickle_is_refused(tmp_path):
    raw = pickle.dumps(np.zeros((10, 3)), protocol=4)
    (tmp_path / "r.pkl").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(RewardFileError):
        load_reward(tmp_path / "r.pkl")


class ScriptedTelemetry:
    """Returns scripted 11-value frames like OpenPlanetClient.retrieve_data."""

    def __init__(self, frames):
        self.frames = list(frames)

    def retrieve_data(self, timeout=None):
        return self.frames.pop(0)


def drive(xs, finish=True, distance0=0.0):
    frames = [(0.0, distance0 + x, x, 10.0, -2.0, 0, 1, 0, 0.0, 1, 1000) for x in xs]
    if finish:
        frames.append((0.0, 999.0, xs[-1], 10.0, -2.0, 0, 1, 0, 1.0, 1, 1000))
    return frames


def test_record_reward_end_to_end(tmp_path):
    xs = [0.0] * 5 + list(np.arange(1, 41) * 0.5)  # countdown, then 20 m along x
    path = record_reward(ScriptedTelemetry(drive(xs)), tmp_path / "reward.npy")
    traj = load_reward(path)
    assert traj.shape == (201, 3)  # 20 m every 0.1 m, both ends included
    np.testing.assert_allclose(traj[:, 0], np.arange(201) * 0.1, atol=1e-9)
    assert np.all(traj[:, 1] == 10.0) and np.all(traj[:, 2] == -2.0)


def test_record_restarts_after_a_respawn(tmp_path):
    first_try = drive([0.0, 3.0, 6.0, 9.0], finish=False, distance0=0.0)
    second_try = drive(list(np.arange(0, 31) * 1.0), finish=True)  # distance drops back to 0
    path = record_reward(ScriptedTelemetry(first_try + second_try), tmp_path / "r.npy")
    assert len(load_reward(path)) == 301


def test_record_stopped_before_the_finish_is_refused(tmp_path):
    frames = drive(list(np.arange(0, 100) * 1.0), finish=False)
    calls = iter(range(1000))
    with pytest.raises(DegenerateRecording, match="finish line was never reached"):
        record_reward(ScriptedTelemetry(frames), tmp_path / "r.npy", stop_requested=lambda: next(calls) >= 50)
    assert not (tmp_path / "r.npy").exists()


def test_record_reward_tool_against_a_plugin(tmp_path):
    """The --record-reward entry function over real TCP: stationary at the start, 20 m along x,
    stationary at the finish line, then the finish flag."""
    import io
    import socket
    import threading

    from tmrl.tm.openplanet import pack_frame
    from tmrl.tm.tools import record_reward as record_tool

    xs = [0.0] * 20 + list(np.arange(1, 41) * 0.5) + [20.0] * 20
    frames = [(5.0, x, x, 7.0, 1.0, 0, 1, 0, 0.0, 2, 5000) for x in xs] + [
        (5.0, 20.0, 20.0, 7.0, 1.0, 0, 1, 0, 1.0, 2, 5000)
    ] * 5
    srv = socket.create_server(("127.0.0.1", 0))
    stop = threading.Event()

    def serve():
        conn, _ = srv.accept()
        with conn:
            try:
                for f in frames:
                    conn.sendall(pack_frame(f))
                    stop.wait(0.003)  # one frame per game frame, as the plugin does
            except OSError:  # the recorder hangs up once it has seen the finish flag
                pass

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    out = io.StringIO()
    try:
        code = record_tool(
            {"RUN_NAME": "r"}, path=tmp_path / "reward.npy", port=srv.getsockname()[1], out=out
        )
    finally:
        stop.set()
        t.join(5)
        srv.close()
    assert code == 0 and "saved to" in out.getvalue()
    traj = load_reward(tmp_path / "reward.npy")
    np.testing.assert_allclose(traj[0], [0.0, 7.0, 1.0])
    assert np.linalg.norm(traj[-1] - [20.0, 7.0, 1.0]) < 0.1 + 1e-9
    assert np.allclose(np.linalg.norm(np.diff(traj, axis=0), axis=1), 0.1)


def test_use_keyboard_without_a_terminal_is_a_user_error(monkeypatch, port_factory, tmp_path):
    import builtins

    from tmrl.tm.tools import record_reward as record_tool

    def no_stdin(prompt=""):
        raise EOFError

    monkeypatch.setattr(builtins, "input", no_stdin)
    with pytest.raises(UserError, match="no terminal input"):
        record_tool({"RUN_NAME": "r"}, use_keyboard=True, path=tmp_path / "r.npy", port=port_factory())


def test_record_ignores_a_stale_finish_flag_and_zero_glitches(tmp_path):
    stale = [(0.0, 0.0, 5.0, 0.0, 0.0, 0, 0, 0, 1.0, 1, 1000)] * 3  # pop-up of the previous race
    glitch = [(0.0, 3.0, 0.0, 0.0, 0.0, 0, 1, 0, 0.0, 1, 1000)]  # (0, 0, 0): map still loading
    frames = stale + drive([0.0, 1.0, 2.0])[:3] + glitch + drive(list(np.arange(3, 21) * 1.0))
    path = record_reward(ScriptedTelemetry(frames), tmp_path / "r.npy")
    traj = load_reward(path)
    assert len(traj) == 201 and traj[:, 0].max() == pytest.approx(20.0)
    assert np.all(traj[:, 1] == 10.0)  # no point pulled toward the origin
