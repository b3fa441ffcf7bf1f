"""Tests of tmrl.driving.reward: the trajectory reward against hand-computed progress and against
a plain-loop reading of tmrl 0.7's rules."""

from __future__ import annotations

import numpy as np
import pytest

from tmrl.driving.reward import TrajectoryReward, patient_argmin, resample_polyline
from tmrl.errors import UserError


def straight(length_m: float = 100.0) -> np.ndarray:
    """Points every 0.1 m along +x from the origin."""
    n = int(round(length_m / 0.1)) + 1
    return np.stack([np.arange(n) * 0.1, np.zeros(n)], axis=1)


class LoopReward:
    """tmrl 0.7's reward rules written as plain loops (the reference the vectorised one must match)."""

    def __init__(self, data, fwd, bwd, countdown, min_steps, stray):
        self.data, self.fwd, self.bwd = np.asarray(data, float), fwd, bwd
        self.countdown, self.min_steps, self.stray = countdown, min_steps, stray
        self.cur_idx = self.step_counter = self.failure_counter = 0

    def compute_reward(self, pos):
        terminated = False
        self.step_counter += 1
        best_d, index, budget, best = np.inf, self.cur_idx, self.fwd, 0
        while True:
            d = np.linalg.norm(pos - self.data[index])
            if d <= best_d:
                best_d, best, budget = d, index, self.fwd
            index += 1
            budget -= 1
            if index >= len(self.data) or budget <= 0:
                if best_d > self.stray:
                    best = self.cur_idx
                break
        reward = (best - self.cur_idx) / 100.0
        if best == self.cur_idx:
            best_d, index = np.inf, self.cur_idx
            while True:
                d = np.linalg.norm(pos - self.data[index])
                if d <= best_d:
                    best_d, best, budget = d, index, self.bwd
                index -= 1
                budget -= 1
                if index <= 0 or budget <= 0:
                    break
            if self.step_counter > self.min_steps:
                self.failure_counter += 1
                if self.failure_counter > self.countdown:
                    terminated = True
        else:
            self.failure_counter = 0
        self.cur_idx = best
        return reward, terminated


def test_progress_on_a_straight_line_is_one_per_ten_metres():
    rew = TrajectoryReward(straight(), check_forward=500, check_backward=10)
    assert rew.compute_reward(np.array([0.0, 0.0])) == (0.0, False)
    r, _ = rew.compute_reward(np.array([5.0, 1.0]))  # 50 points ahead, 1 m to the side
    assert r == pytest.approx(0.5)
    assert rew.cur_idx == 50
    r, _ = rew.compute_reward(np.array([12.34, -0.5]))  # nearest point: 12.3 m, index 123
    assert r == pytest.approx(0.73)
    assert rew.progress == pytest.approx(123 / 1001)


def test_cut_is_rewarded_only_within_check_forward():
    # A U: 20 m along +x, a half circle of radius 5 m, 20 m back along -x, 10 m apart.
    a = straight(20.0)
    theta = np.arange(1, 157) * 0.1 / 5.0
    arc = np.stack([20.0 + 5.0 * np.sin(theta), 5.0 - 5.0 * np.cos(theta)], axis=1)
    back = np.stack([20.0 - np.arange(0, 201) * 0.1, np.full(201, 10.0)], axis=1)
    u_turn = np.concatenate([a, arc, back])
    jump_to = np.array([10.0, 10.0])  # on the return leg, 10 m across from the outward leg
    target = int(np.argmin(np.linalg.norm(u_turn - jump_to, axis=1)))
    short = TrajectoryReward(u_turn, check_forward=50)
    short.compute_reward(np.array([10.0, 0.0]))
    r_short, _ = short.compute_reward(jump_to)
    # With 5 m of look-ahead the search stops long before the return leg: the nearest point
    # within reach is the one at x = 10 on the outward leg (10 m away), so no progress.
    assert r_short == 0.0
    long = TrajectoryReward(u_turn, check_forward=500)
    long.compute_reward(np.array([10.0, 0.0]))
    r_long, _ = long.compute_reward(jump_to)
    assert long.cur_idx == target
    assert r_long == pytest.approx((target - 100) / 100.0)


def test_max_stray_means_no_progress():
    rew = TrajectoryReward(straight(), max_stray=3.0)
    r, _ = rew.compute_reward(np.array([5.0, 4.0]))  # nearest point 4 m away
    assert r == 0.0 and rew.cur_idx == 0
    r, _ = rew.compute_reward(np.array([5.0, 2.0]))
    assert r == pytest.approx(0.5)


def test_going_back_rewinds_without_negative_reward_and_progress_pays_again():
    rew = TrajectoryReward(straight(), check_backward=10)
    rew.compute_reward(np.array([5.0, 0.0]))
    r, _ = rew.compute_reward(np.array([4.5, 0.0]))  # 5 points back, within CHECK_BACKWARD
    assert r == 0.0 and rew.cur_idx == 45
    r, _ = rew.compute_reward(np.array([5.0, 0.0]))
    assert r == pytest.approx(0.05)


def test_failure_countdown_after_min_steps():
    rew = TrajectoryReward(straight(), failure_countdown=10, min_steps=70)
    flags = [rew.compute_reward(np.array([0.0, 0.0]))[1] for _ in range(81)]
    # steps 71..80 count failures 1..10; the 11th (step 81) exceeds the countdown
    assert flags[:80] == [False] * 80 and flags[80] is True
    rew.reset()
    assert rew.cur_idx == 0 and rew.step_counter == 0 and rew.failure_counter == 0


def test_progress_resets_the_failure_counter():
    rew = TrajectoryReward(straight(), failure_countdown=2, min_steps=0)
    x = 0.0
    for step in range(20):
        x += 0.05 if step % 2 else 0.2  # a slow step (< 1 point) every other step
        _, terminated = rew.compute_reward(np.array([x, 0.0]))
        assert not terminated


@pytest.mark.parametrize("fwd,bwd", [(500, 10), (7, 3), (1, 1), (40, 25)])
def test_matches_the_loop_reading_on_random_drives(fwd, bwd):
    rng = np.random.default_rng(fwd * 100 + bwd)
    wiggle = np.cumsum(rng.normal(size=(3000, 2)) * 0.03, axis=0) + np.stack([np.arange(3000) * 0.1, np.zeros(3000)], 1)
    traj = resample_polyline(wiggle, 0.1)
    ours = TrajectoryReward(traj, check_forward=fwd, check_backward=bwd, failure_countdown=5, min_steps=10, max_stray=4.0)
    ref = LoopReward(traj, fwd, bwd, 5, 10, 4.0)
    pos = traj[0].copy()
    for _ in range(250):
        pos = pos + rng.normal(size=2) * 1.5 + np.array([0.8, 0.0])
        a = ours.compute_reward(pos)
        b = ref.compute_reward(pos)
        assert ours.cur_idx == ref.cur_idx
        assert a[0] == pytest.approx(b[0]) and a[1] == b[1]


def test_patient_argmin_reads_like_the_loop():
    d = np.array([5.0, 4.0, 6.0, 6.0, 3.0, 9.0, 9.0, 9.0, 1.0])
    assert patient_argmin(d, 3) == 1  # the scan covers 1, 2, 3 and stops before 4
    assert patient_argmin(d, 4) == 4  # reaches 4 (three after 1), then 8 is four after 4: stop
    assert patient_argmin(d, 5) == 8
    assert patient_argmin(d, 1) == 0
    assert patient_argmin(np.array([2.0, 2.0]), 2) == 1  # ties go to the later point


def test_resample_polyline_spacing_and_errors():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 2.0]])
    out = resample_polyline(pts, 0.1)
    assert len(out) == 31
    steps = np.linalg.norm(np.diff(out, axis=0), axis=1)
    assert np.allclose(steps[steps > 0.09], 0.1, atol=1e-9) and steps.min() > 0.07  # the corner cuts a little
    with pytest.raises(UserError):
        resample_polyline(np.zeros((1, 3)))
    with pytest.raises(UserError, match="zero length"):
        resample_polyline(np.zeros((5, 3)))


def test_config_errors_are_user_errors():
    with pytest.raises(UserError, match="CHECK_FORWRD"):
        TrajectoryReward.from_config(straight(), {"CHECK_FORWRD": 10})
    with pytest.raises(UserError):
        TrajectoryReward(np.zeros((1, 2)))
    rew = TrajectoryReward.from_config(straight(), {"END_OF_TRACK": 5.0})
    assert rew.end_of_track == 5.0 and rew.check_forward == 500 and rew.max_stray == 100.0
