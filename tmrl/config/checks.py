"""Checks of the configuration that involve several keys (each key alone is checked by its
:class:`~tmrl.config.spec.Spec` in the table of :mod:`tmrl.config.schema`).

The loader runs :func:`check_consistency` on every complete config it returns; a violation names
the key to change. Nothing here reads a file.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from tmrl.config.spec import SchemaViolation, fmt_number, show

__all__ = ["check_consistency", "redq_subset_problem"]


def redq_subset_problem(n: int, m: int) -> str | None:
    """Why REDQ's ``m`` (critics drawn per target) does not fit its ``n`` critics, or None when
    ``1 <= m <= n``. The one place this rule is written: the config check and ``REDQSACAgent``
    both call it."""
    if int(m) < 1:
        return f"ALG.REDQ_M must be at least 1, got {int(m)}"
    if int(m) > int(n):
        return f"ALG.REDQ_M must be at most ALG.REDQ_N ({int(n)}), got {int(m)}"
    return None


def check_consistency(cfg: Mapping[str, Any]) -> None:
    """Checks that involve several keys of a complete, validated config: REDQ's ``REDQ_M`` within
    ``REDQ_N``, the simultaneous update order of REDQ, DroQ, TQC, DrQ, BRO and SimbaV2, TQC's dropped quantiles fewer
    than its quantiles, the two pacing ratios not blocking each other,
    ``act_in_obs`` for the simulator and TrackMania, grayscale images for ``SIMFULL``, a
    ``GYM_ID`` for ``GYM``.

    Args:
        cfg: a complete config, each key already checked by :data:`tmrl.config.schema.SCHEMA`.

    Raises:
        SchemaViolation: naming the key to change.
    """
    alg = cfg["ALG"]
    problem = redq_subset_problem(alg["REDQ_N"], alg["REDQ_M"]) if alg["ALGORITHM"] == "REDQSAC" else None
    if problem:
        raise SchemaViolation("ALG.REDQ_M", problem)
    if alg["ALGORITHM"] in ("REDQSAC", "DROQ", "TQC", "DRQ", "BRO", "SIMBAV2") and alg["UPDATE_ORDER"] != "simultaneous":
        raise SchemaViolation(
            "ALG.UPDATE_ORDER",
            f'ALG.UPDATE_ORDER must be "simultaneous" when ALG.ALGORITHM is {show(alg["ALGORITHM"])} (the '
            f"sequential order is SAC's), got {show(alg['UPDATE_ORDER'])}",
        )
    if alg["ALGORITHM"] == "TQC" and alg["TQC_DROP_PER_CRITIC"] >= alg["TQC_QUANTILES"]:
        raise SchemaViolation(
            "ALG.TQC_DROP_PER_CRITIC",
            f"ALG.TQC_DROP_PER_CRITIC must be below ALG.TQC_QUANTILES ({alg['TQC_QUANTILES']}), got "
            f"{alg['TQC_DROP_PER_CRITIC']}: TQC would drop every quantile",
        )
    pace, ratio = cfg["MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP"], cfg["MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP"]
    if pace and pace * ratio < 1.0:
        raise SchemaViolation(
            "MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP",
            f"MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP ({fmt_number(pace)}) times MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP "
            f"({fmt_number(ratio)}) must be at least 1, or workers and trainer would wait for each other; raise one of "
            "them or set MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP to 0",
        )
    env = cfg["ENV"]
    name = env["RTGYM_INTERFACE"]
    if name.startswith(("SIM", "TM20")) and not env["RTGYM_CONFIG"]["act_in_obs"]:
        raise SchemaViolation(
            "ENV.RTGYM_CONFIG.act_in_obs",
            f"ENV.RTGYM_CONFIG.act_in_obs must be true when ENV.RTGYM_INTERFACE is {show(name)} (its replay "
            "memory rebuilds the action buffer of the observations), got false",
        )
    if name == "SIMFULL" and not env["IMG_GRAYSCALE"]:
        raise SchemaViolation(
            "ENV.IMG_GRAYSCALE",
            'ENV.IMG_GRAYSCALE must be true when ENV.RTGYM_INTERFACE is "SIMFULL" (the simulator renders '
            "grayscale images), got false",
        )
    if name == "GYM" and not env["GYM_ID"].strip():
        raise SchemaViolation(
            "ENV.GYM_ID",
            'ENV.GYM_ID must name a Gymnasium environment (e.g. "Pendulum-v1") when ENV.RTGYM_INTERFACE is '
            f'"GYM", got {show(env["GYM_ID"])}',
        )
