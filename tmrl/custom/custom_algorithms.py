"""Compatibility names of the original ``tmrl.custom.custom_algorithms`` (no logic here)."""

from tmrl.algorithms.redq import REDQSACAgent
from tmrl.algorithms.sac import SACAgent, SpinupSacAgent

__all__ = ["REDQSACAgent", "SACAgent", "SpinupSacAgent"]
