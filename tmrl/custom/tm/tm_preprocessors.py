"""Compatibility names of the original ``tmrl.custom.tm.tm_preprocessors`` (no logic here)."""

from tmrl.driving.preprocessors import (
    identity_sample as sample_preprocessor_tm_lidar_act_in_obs,
    preprocess_full_obs as obs_preprocessor_tm_act_in_obs,
    preprocess_lidar_obs as obs_preprocessor_tm_lidar_act_in_obs,
    preprocess_lidar_progress_obs as obs_preprocessor_tm_lidar_progress_act_in_obs,
)

__all__ = [
    "obs_preprocessor_tm_act_in_obs",
    "obs_preprocessor_tm_lidar_act_in_obs",
    "obs_preprocessor_tm_lidar_progress_act_in_obs",
    "sample_preprocessor_tm_lidar_act_in_obs",
]
