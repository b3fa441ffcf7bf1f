"""The trajectory reward shared by TrackMania and the simulator.

The reward follows a recorded centre line, a polyline whose points are evenly spaced (0.1 m by
default, as the reward recorder writes them). Each step, the car's position is matched to the
nearest point of the line ahead of the last matched point, and the reward is the number of points
passed times ``spacing / 10``: 1.0 per 10 m of progress. The matching rules are those of tmrl 0.7:

- the forward search starts at the current point and keeps looking ``check_forward`` points past
  the best match found so far (so cuts up to that length are found and rewarded);
- if the best match is farther than ``max_stray`` from the car, the car is considered not to have
  moved;
- when there is no progress, the match is rewound (at most ``check_backward`` points past the
  best backward match) so that the reward stays Markovian, and after ``min_steps`` steps of the
  episode, more than ``failure_countdown`` consecutive steps without progress terminate it.

The finish bonus (``END_OF_TRACK``) and the per-step ``CONSTANT_PENALTY`` are added by the
interfaces, which know when the race is finished; :meth:`TrajectoryReward.finish_bonus` and
:attr:`TrajectoryReward.constant_penalty` hold them so that both pipelines add the same values.

NumPy only; no game dependency.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tmrl.errors import UserError

__all__ = [
    "DEFAULT_REWARD_CONFIG",
    "TrajectoryReward",
    "patient_argmin",
    "resample_polyline",
]

DEFAULT_REWARD_CONFIG: dict[str, float] = {
    "END_OF_TRACK": 100.0,
    "CONSTANT_PENALTY": 0.0,
    "CHECK_FORWARD": 500,
    "CHECK_BACKWARD": 10,
    "FAILURE_COUNTDOWN": 10,
    "MIN_STEPS": 70,
    "MAX_STRAY": 100.0,
}
"""The ``REWARD_CONFIG`` defaults of the original TrackMania config.json."""

# Distances are computed over chunks of the polyline so that a step costs O(chunk) whatever the
# track length; a search usually ends inside the first chunk.
_MIN_CHUNK = 256


def resample_polyline(points: np.ndarray, spacing: float = 0.1) -> np.ndarray:
    """Resample a polyline so that consecutive points are ``spacing`` apart along its length.

    Args:
        points: ``(N, D)`` array of positions, in order (N >= 2, D >= 1).
        spacing: distance between output points along the polyline, in metres (> 0).

    Returns:
        ``(M, D)`` float64 array starting at ``points[0]``; its last point is the last point that
        fits on the polyline (the remainder shorter than ``spacing`` is dropped).

    Raises:
        UserError: fewer than two points, a non-positive spacing, or a polyline of zero length.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or len(pts) < 2:
        raise UserError(
            f"a trajectory needs at least 2 positions of shape (N, D), got shape {pts.shape}: "
            "record it again, driving from the start line to the finish"
        )
    if not spacing > 0:
        raise UserError(f"trajectory spacing must be > 0, got {spacing}")
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    cum = np.concatenate(([0.0], np.cumsum(seg)))
    total = float(cum[-1])
    if total <= 0.0:
        raise UserError("the recorded trajectory has zero length (the car never moved): record it again")
    s = np.arange(0.0, total + 1e-9, spacing)
    out = np.empty((len(s), pts.shape[1]), dtype=np.float64)
    for d in range(pts.shape[1]):
        out[:, d] = np.interp(s, cum, pts[:, d])
    return out


def patient_argmin(dists: np.ndarray, patience: int) -> int:
    """Scan ``dists`` in order, keeping the running minimum (ties go to the later element), and
    stop ``patience - 1`` elements after the last improvement.

    This is the search of the original reward, written without a Python loop over points.

    Args:
        dists: 1-D array of distances in scan order (non-empty).
        patience: how many elements the scan covers from an improvement, counting it (>= 1).

    Returns:
        The position in ``dists`` of the best match where the scan stops.
    """
    scan = _PatientScan(patience)
    scan.feed(np.asarray(dists, dtype=np.float64))
    return scan.last


class _PatientScan:
    """State of a patient running-minimum scan fed chunk by chunk (positions count from 0)."""

    def __init__(self, patience: int) -> None:
        self.patience = patience
        self.best = np.inf
        self.last = -1  # position of the last improvement
        self.seen = 0  # number of positions fed so far
        self.stopped = False

    def feed(self, dists: np.ndarray) -> None:
        if self.stopped or len(dists) == 0:
            return
        prefix = np.minimum.accumulate(np.concatenate(([self.best], dists[:-1])))
        improved = self.seen + np.flatnonzero(dists <= prefix)
        chain = np.concatenate(([self.last], improved)) if self.last >= 0 else improved
        # The scan reaches an improvement only if it lies within `patience - 1` positions of the
        # previous one; the first gap that is too long ends it.
        too_far = np.flatnonzero(np.diff(chain) >= self.patience)
        if len(too_far):
            self.last = int(chain[too_far[0]])
            self.stopped = True
        elif len(chain):
            self.last = int(chain[-1])
        self.best = float(dists[self.last - self.seen]) if self.last >= self.seen else self.best
        self.seen += len(dists)
        if self.seen - 1 - self.last >= self.patience - 1:
            self.stopped = True


class TrajectoryReward:
    """Progress reward along a recorded centre line (tmrl 0.7 semantics, vectorised).

    Args:
        trajectory: ``(N, D)`` array of evenly spaced points from the start line to the finish
            (N >= 2). TrackMania uses 3-D positions, the simulator 2-D ones.
        spacing: distance between consecutive points in metres (0.1 for recorded trajectories);
            the reward is ``points passed * spacing / 10``, i.e. 1.0 per 10 m.
        check_forward: ``CHECK_FORWARD``, how many points the forward search looks past its best
            match (500 points = 50 m cuts at 0.1 m spacing).
        check_backward: ``CHECK_BACKWARD``, the same for the rewind when there is no progress.
        failure_countdown: ``FAILURE_COUNTDOWN``, consecutive steps without progress tolerated
            before the episode terminates.
        min_steps: ``MIN_STEPS``, steps at the start of an episode during which it never
            terminates for lack of progress.
        max_stray: ``MAX_STRAY``, farther than this from the best match (metres), the car counts
            as not having moved.
        end_of_track: ``END_OF_TRACK``, bonus the interfaces add when the finish line is crossed.
        constant_penalty: ``CONSTANT_PENALTY``, added by the interfaces at every step.

    Raises:
        UserError: a trajectory with fewer than two points or non-finite values, or a
            non-positive search length.
    """

    def __init__(
        self,
        trajectory: np.ndarray,
        spacing: float = 0.1,
        check_forward: int = 500,
        check_backward: int = 10,
        failure_countdown: int = 10,
        min_steps: int = 70,
        max_stray: float = 100.0,
        end_of_track: float = 100.0,
        constant_penalty: float = 0.0,
    ) -> None:
        data = np.asarray(trajectory, dtype=np.float64)
        if data.ndim != 2 or len(data) < 2 or not np.all(np.isfinite(data)):
            raise UserError(
                f"the reward trajectory must be a finite (N, D) array with N >= 2, got shape {data.shape}: "
                "record the reward again (tmrl --record-reward)"
            )
        if int(check_forward) < 1 or int(check_backward) < 1:
            raise UserError("REWARD_CONFIG CHECK_FORWARD and CHECK_BACKWARD must be >= 1")
        self.data = data
        self.datalen = len(data)
        self.spacing = float(spacing)
        self.check_forward = int(check_forward)
        self.check_backward = int(check_backward)
        self.failure_countdown = int(failure_countdown)
        self.min_steps = int(min_steps)
        self.max_stray = float(max_stray)
        self.end_of_track = float(end_of_track)
        self.constant_penalty = float(constant_penalty)
        self._chunk = max(_MIN_CHUNK, self.check_forward + 64)
        self.cur_idx = 0
        self.step_counter = 0
        self.failure_counter = 0

    @classmethod
    def from_config(cls, trajectory: np.ndarray, reward_config: Mapping[str, Any] | None = None,
                    spacing: float = 0.1) -> TrajectoryReward:
        """Build from a ``REWARD_CONFIG`` dict (missing keys take :data:`DEFAULT_REWARD_CONFIG`).

        Raises:
            UserError: an unknown key in ``reward_config`` (a typo would otherwise be ignored).
        """
        cfg = dict(DEFAULT_REWARD_CONFIG)
        if reward_config:
            unknown = sorted(set(reward_config) - set(DEFAULT_REWARD_CONFIG))
            if unknown:
                raise UserError(
                    f"unknown REWARD_CONFIG key(s) {unknown}: the keys are {sorted(DEFAULT_REWARD_CONFIG)}"
                )
            cfg.update(reward_config)
        return cls(
            trajectory,
            spacing=spacing,
            check_forward=int(cfg["CHECK_FORWARD"]),
            check_backward=int(cfg["CHECK_BACKWARD"]),
            failure_countdown=int(cfg["FAILURE_COUNTDOWN"]),
            min_steps=int(cfg["MIN_STEPS"]),
            max_stray=float(cfg["MAX_STRAY"]),
            end_of_track=float(cfg["END_OF_TRACK"]),
            constant_penalty=float(cfg["CONSTANT_PENALTY"]),
        )

    @property
    def progress(self) -> float:
        """Fraction of the trajectory matched so far, ``cur_idx / datalen`` as in the original."""
        return self.cur_idx / self.datalen

    @property
    def reward_per_point(self) -> float:
        """Reward for passing one point: ``spacing / 10`` (0.01 at 0.1 m)."""
        return self.spacing / 10.0

    def reset(self) -> None:
        """Start a new episode at the first point."""
        self.cur_idx = 0
        self.step_counter = 0
        self.failure_counter = 0

    def _forward_match(self, pos: np.ndarray) -> tuple[int, float]:
        scan = _PatientScan(self.check_forward)
        lo = self.cur_idx
        while not scan.stopped and lo < self.datalen:
            hi = min(self.datalen, lo + self._chunk)
            diff = self.data[lo:hi] - pos
            scan.feed(np.einsum("ij,ij->i", diff, diff))  # squared distances: same order, no sqrt
            lo = hi
        return self.cur_idx + scan.last, float(np.sqrt(scan.best))

    def _backward_match(self, pos: np.ndarray) -> int:
        # The rewind looks at cur_idx, cur_idx - 1, ... down to index 1: the original's loop stops
        # before evaluating index 0 unless it starts there.
        start = self.cur_idx
        scan = _PatientScan(self.check_backward)
        hi = start + 1
        floor = 1 if start > 0 else 0
        while not scan.stopped and hi > floor:
            lo = max(floor, hi - self._chunk)
            diff = self.data[lo:hi][::-1] - pos
            scan.feed(np.einsum("ij,ij->i", diff, diff))
            hi = lo
        return start - scan.last

    def compute_reward(self, pos: np.ndarray) -> tuple[float, bool]:
        """Match ``pos`` to the trajectory and return ``(reward, terminated)``.

        Args:
            pos: position of the car, same dimension as the trajectory.

        Returns:
            The progress reward (``spacing / 10`` per point passed, without finish bonus or
            constant penalty) and whether the episode terminates for lack of progress.
        """
        pos = np.asarray(pos, dtype=np.float64)
        self.step_counter += 1
        terminated = False
        best_idx, best_d = self._forward_match(pos)
        if best_d > self.max_stray:
            best_idx = self.cur_idx
        reward = (best_idx - self.cur_idx) * self.reward_per_point
        if best_idx == self.cur_idx:
            best_idx = self._backward_match(pos)
            if self.step_counter > self.min_steps:
                self.failure_counter += 1
                if self.failure_counter > self.failure_countdown:
                    terminated = True
        else:
            self.failure_counter = 0
        self.cur_idx = best_idx
        return float(reward), terminated
