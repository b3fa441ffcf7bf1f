"""Compatibility names of the original ``tmrl.wrappers`` (no logic here).

- ``AffineObservationWrapper(env, shift, scale)``: :class:`tmrl.envs.AffineObservation`;
- ``Float64ToFloat32``: :class:`tmrl.envs.Float64ToFloat32` (float64 arrays become float32 with
  their shape, and the spaces follow);
- ``float64_to_float32``, ``float_to_float32``: :func:`tmrl.envs.to_float32` on one value.
"""

from tmrl.envs import AffineObservation as AffineObservationWrapper, Float64ToFloat32, to_float32

float64_to_float32 = to_float32
float_to_float32 = to_float32

__all__ = ["AffineObservationWrapper", "Float64ToFloat32", "float64_to_float32", "float_to_float32"]
