"""Compatibility names of the original ``tmrl.custom.custom_models`` (no logic here)."""

from tmrl.models import (
    EnsembleQFunction,
    MLPActorCritic,
    REDQMLPActorCritic,
    SquashedGaussianMLPActor,
    mlp,
)

__all__ = ["EnsembleQFunction", "MLPActorCritic", "REDQMLPActorCritic", "SquashedGaussianMLPActor", "mlp"]
