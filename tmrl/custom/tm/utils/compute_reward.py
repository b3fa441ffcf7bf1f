"""Compatibility name of the original ``tmrl.custom.tm.utils.compute_reward``.

``RewardFunction`` is :class:`tmrl.driving.reward.TrajectoryReward` built from a reward file
with the original's argument names.
"""

from __future__ import annotations

import os

from tmrl.driving.reward import TrajectoryReward

__all__ = ["RewardFunction"]


class RewardFunction(TrajectoryReward):
    """tmrl 0.7's reward function: :class:`~tmrl.driving.reward.TrajectoryReward` on the
    trajectory recorded in ``reward_data_path`` (``reward.npy``, or the original's ``reward.pkl``,
    read without unpickling code).

    Args:
        reward_data_path: the reward file.
        nb_obs_forward, nb_obs_backward, nb_zero_rew_before_failure, min_nb_steps_before_failure,
            max_dist_from_traj: the original's names of ``check_forward``, ``check_backward``,
            ``failure_countdown``, ``min_steps`` and ``max_stray``.

    Raises:
        tmrl.tm.record.RewardFileError: no reward file there, or not a reward trajectory.
    """

    def __init__(self, reward_data_path: str | os.PathLike[str], nb_obs_forward: int = 10,
                 nb_obs_backward: int = 10, nb_zero_rew_before_failure: int = 10,
                 min_nb_steps_before_failure: int = 70, max_dist_from_traj: float = 60.0) -> None:
        from tmrl.tm.record import load_reward

        super().__init__(load_reward(reward_data_path), check_forward=nb_obs_forward,
                         check_backward=nb_obs_backward, failure_countdown=nb_zero_rew_before_failure,
                         min_steps=min_nb_steps_before_failure, max_stray=max_dist_from_traj)
