"""Training algorithms: SAC (:mod:`tmrl.algorithms.sac`), REDQ-SAC (:mod:`tmrl.algorithms.redq`),
DroQ (:mod:`tmrl.algorithms.droq`), TQC (:mod:`tmrl.algorithms.tqc`), CrossQ
(:mod:`tmrl.algorithms.crossq`), DrQ (:mod:`tmrl.algorithms.drq`, image observations only), BRO (:mod:`tmrl.algorithms.bro`) and
SimbaV2 (:mod:`tmrl.algorithms.simbav2`).

``ALG.ALGORITHM`` in ``config.json`` names one of them; :func:`agent_class` maps that name to
the class.
"""

from __future__ import annotations

from tmrl.algorithms.bro import BROAgent
from tmrl.algorithms.crossq import CrossQAgent
from tmrl.algorithms.droq import DroQAgent
from tmrl.algorithms.drq import DrQAgent
from tmrl.algorithms.redq import REDQSACAgent
from tmrl.algorithms.sac import SACAgent, SpinupSacAgent
from tmrl.algorithms.simbav2 import SimbaV2Agent
from tmrl.algorithms.tqc import TQCAgent
from tmrl.config.schema import AGENT_CLASSES
from tmrl.errors import UserError

__all__ = [
    "ALGORITHMS", "BROAgent", "CrossQAgent", "DrQAgent", "DroQAgent", "REDQSACAgent", "SACAgent", "SimbaV2Agent", "SpinupSacAgent", "TQCAgent", "agent_class",
]

_CLASSES = {cls.__name__: cls for cls in (SACAgent, REDQSACAgent, DroQAgent, TQCAgent, CrossQAgent, DrQAgent, BROAgent, SimbaV2Agent)}
ALGORITHMS: dict[str, type] = {name: _CLASSES[cls_name] for name, cls_name in AGENT_CLASSES.items()}
"""Values of ``ALG.ALGORITHM`` and the agents they select (the names come from the settings
table, :data:`tmrl.config.schema.AGENT_CLASSES`)."""


def agent_class(name: str) -> type:
    """The training agent class for a config's ``ALG.ALGORITHM``.

    Args:
        name: ``"SAC"``, ``"REDQSAC"``, ``"DROQ"``, ``"TQC"``, ``"CROSSQ"``, ``"DRQ"``, ``"BRO"`` or ``"SIMBAV2"``; case, ``-`` and ``_`` are ignored
            (``"redq-sac"`` works).

    Returns:
        The class: :class:`~tmrl.algorithms.sac.SACAgent`, :class:`~tmrl.algorithms.redq.REDQSACAgent`,
        :class:`~tmrl.algorithms.droq.DroQAgent`, :class:`~tmrl.algorithms.tqc.TQCAgent`,
        :class:`~tmrl.algorithms.crossq.CrossQAgent`, :class:`~tmrl.algorithms.drq.DrQAgent`,
        :class:`~tmrl.algorithms.bro.BROAgent` or :class:`~tmrl.algorithms.simbav2.SimbaV2Agent`.

    Raises:
        UserError: unknown algorithm name.
    """
    key = str(name).upper().replace("-", "").replace("_", "")
    if key not in ALGORITHMS:
        raise UserError(f"ALG.ALGORITHM={name!r} is not supported: use one of {', '.join(ALGORITHMS)}")
    return ALGORITHMS[key]
