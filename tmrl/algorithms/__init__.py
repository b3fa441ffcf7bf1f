"""Training algorithms: SAC (:mod:`tmrl.algorithms.sac`) and REDQ-SAC (:mod:`tmrl.algorithms.redq`).

``ALG.ALGORITHM`` in ``config.json`` names one of them; :func:`agent_class` maps that name to
the class.
"""

from __future__ import annotations

from tmrl.algorithms.redq import REDQSACAgent
from tmrl.algorithms.sac import SACAgent, SpinupSacAgent
from tmrl.config.schema import AGENT_CLASSES
from tmrl.errors import UserError

__all__ = ["ALGORITHMS", "REDQSACAgent", "SACAgent", "SpinupSacAgent", "agent_class"]

ALGORITHMS: dict[str, type] = {
    name: {cls.__name__: cls for cls in (SACAgent, REDQSACAgent)}[cls_name] for name, cls_name in AGENT_CLASSES.items()
}
"""Values of ``ALG.ALGORITHM`` and the agents they select (the names come from the settings
table, :data:`tmrl.config.schema.AGENT_CLASSES`)."""


def agent_class(name: str) -> type:
    """The training agent class for a config's ``ALG.ALGORITHM``.

    Args:
        name: ``"SAC"`` or ``"REDQSAC"``; case, ``-`` and ``_`` are ignored (``"redq-sac"`` works).

    Returns:
        The class, :class:`~tmrl.algorithms.sac.SACAgent` or :class:`~tmrl.algorithms.redq.REDQSACAgent`.

    Raises:
        UserError: unknown algorithm name.
    """
    key = str(name).upper().replace("-", "").replace("_", "")
    if key not in ALGORITHMS:
        raise UserError(f"ALG.ALGORITHM={name!r} is not supported: use one of {', '.join(ALGORITHMS)}")
    return ALGORITHMS[key]
