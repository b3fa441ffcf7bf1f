"""Compatibility names of the original ``tmrl.custom.custom_memories`` (no logic here).

The original's memories map to the array-shaped memories of this package:

==================================  =================================================
tmrl 0.7                            here
==================================  =================================================
``GenericTorchMemory``              :class:`tmrl.memory.GenericTorchMemory`
``MemoryTM``                        :class:`tmrl.driving.memories.HistoryMemory`
``MemoryTMLidar``                   :class:`tmrl.driving.memories.LidarMemory`
``MemoryTMLidarProgress``           :class:`tmrl.driving.memories.LidarProgressMemory`
``MemoryTMFull``                    :class:`tmrl.driving.memories.ImageMemory`
``get_local_buffer_sample_lidar``   :func:`tmrl.driving.compressors.compress_lidar_sample`
``get_local_buffer_sample_lidar_progress``  :func:`~tmrl.driving.compressors.compress_lidar_progress_sample`
``get_local_buffer_sample_tm20_imgs``       :func:`~tmrl.driving.compressors.compress_full_sample`
==================================  =================================================

The driving memories accept the original keyword ``imgs_obs`` as an alias of ``hist_len``.
"""

from tmrl.driving.compressors import (
    compress_full_sample as get_local_buffer_sample_tm20_imgs,
    compress_lidar_progress_sample as get_local_buffer_sample_lidar_progress,
    compress_lidar_sample as get_local_buffer_sample_lidar,
)
from tmrl.driving.memories import (
    HistoryMemory as MemoryTM,
    ImageMemory as MemoryTMFull,
    LidarMemory as MemoryTMLidar,
    LidarProgressMemory as MemoryTMLidarProgress,
)
from tmrl.memory import GenericTorchMemory
from tmrl.util import last_true_in_list

__all__ = [
    "GenericTorchMemory",
    "MemoryTM",
    "MemoryTMFull",
    "MemoryTMLidar",
    "MemoryTMLidarProgress",
    "get_local_buffer_sample_lidar",
    "get_local_buffer_sample_lidar_progress",
    "get_local_buffer_sample_tm20_imgs",
    "last_true_in_list",
]
