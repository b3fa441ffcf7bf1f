"""Compatibility names of the original ``tmrl.custom.tm.tm_gym_interfaces`` (no logic here)."""

from tmrl.tm.interfaces import (
    TM20FullInterface as TM2020Interface,
    TM20LidarInterface as TM2020InterfaceLidar,
    TM20LidarProgressInterface as TM2020InterfaceLidarProgress,
)

__all__ = ["TM2020Interface", "TM2020InterfaceLidar", "TM2020InterfaceLidarProgress"]
