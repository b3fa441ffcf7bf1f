"""The one schema of ``config.json``: every key with its type, default, allowed range and meaning.

Everything else derives from it: the loader validates against it and fills missing keys with its
defaults, ``config/config.json`` is its defaults written out (the other ``config/*.json`` are the
defaults with the changes of :data:`EXAMPLES`), and ``docs/config.md`` is generated from it. Regenerate both after a change with::

    python -m tmrl.config.schema --write

(``--markdown`` and ``--json`` print the reference and the default config instead.)

Nothing here reads a file or touches the disk at import.
"""

from __future__ import annotations

import argparse
import copy
import difflib
import json
import math
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from tmrl.errors import UserError

__all__ = [
    "ALGORITHMS",
    "EXAMPLES",
    "PASSWORD_PLACEHOLDER",
    "RTGYM_INTERFACES",
    "SCHEMA",
    "AnyDict",
    "AnyList",
    "Bool",
    "Choice",
    "ConfigError",
    "Int",
    "Number",
    "NumberList",
    "SchemaViolation",
    "Section",
    "Spec",
    "Str",
    "AGENT_CLASSES",
    "NO_CLASS_DEFAULT",
    "OPTIMIZERS",
    "UPDATE_ORDERS",
    "arguments",
    "check_consistency",
    "fed_arguments",
    "redq_subset_problem",
    "default_config_json",
    "defaults",
    "example_json",
    "generated_files",
    "markdown_reference",
]


class ConfigError(UserError):
    """A configuration mistake. ``str(err)`` is one line: where the value came from (the file, or
    ``--config``), the full key path, the value found and what is expected."""


class SchemaViolation(Exception):
    """Raised by :meth:`Spec.check`; the loader turns it into a :class:`ConfigError` by adding the
    source (file name or ``--config``) in front of the message.

    Args:
        path: the full key path of the bad value (``"ALG.LR_ACTOR"``; empty for the top level).
        message: the one-line explanation, starting with the key path.
    """

    def __init__(self, path: str, message: str):
        super().__init__(message)
        self.path = path
        self.message = message


class _NoClassDefault:
    def __repr__(self) -> str:
        return "<no class default>"


NO_CLASS_DEFAULT: Any = _NoClassDefault()
"""``Spec.class_default`` of a key whose argument has no default of its own in the class."""


def show(value: Any, limit: int = 80) -> str:
    """Render a found value the way it would be written in JSON (``"fast"``, ``true``, ``null``),
    shortened to ``limit`` characters so that an error stays on one line."""
    try:
        text = json.dumps(value, ensure_ascii=False)
    except (TypeError, ValueError):
        text = repr(value)
    text = " ".join(text.split())
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return text


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else repr(x)


class Spec:
    """One key of the schema.

    Args:
        default: the value a missing key takes (deep-copied on use).
        doc: one-line meaning, shown in ``docs/config.md``.
        nullable: ``null`` (Python ``None``) is accepted as well.
        feeds: the constructor arguments this key sets, as ``"Class.argument"`` (for example
            ``"SACAgent.lr_actor"``); :func:`arguments` collects them for one class, and a test
            checks that each class takes each argument.
        class_default: the default of that argument in the class's own signature, when the class
            has one of its own (a script that builds ``SACAgent(...)`` without the argument gets
            it; ``config.json`` gets ``default``). A test checks the signatures against it.
    """

    kind = "value"

    def __init__(
        self,
        default: Any,
        doc: str,
        *,
        nullable: bool = False,
        feeds: Sequence[str] = (),
        class_default: Any = NO_CLASS_DEFAULT,
    ):
        self.default = default
        self.doc = doc
        self.nullable = nullable
        self.feeds = tuple(feeds)
        self.class_default = class_default

    @property
    def expected(self) -> str:
        """What a valid value is, as a phrase that completes "must be ..."."""
        raise NotImplementedError

    def describe(self) -> str:
        """The expected phrase including ``or null`` for nullable keys."""
        return self.expected + (" or null" if self.nullable else "")

    def default_value(self) -> Any:
        """A deep copy of :attr:`default` (so that a caller may modify it)."""
        return copy.deepcopy(self.default)

    def check(self, value: Any, path: str, *, fill: bool = True) -> Any:
        """Validate ``value`` found at ``path`` and return it normalised (ints to floats for
        numbers, canonical spelling for choices, tuples to lists).

        Args:
            value: the value found in the configuration (already parsed from JSON).
            path: its full key path, used in the error message (``""`` for the top level).
            fill: sections fill missing keys with defaults (False to validate a partial override).

        Returns:
            The normalised value (``None`` for ``null`` when the key is nullable).

        Raises:
            SchemaViolation: naming ``path``, the value and :meth:`describe`.
        """
        if value is None and self.nullable:
            return None
        return self._check(value, path, fill=fill)

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        raise NotImplementedError

    def fail(self, path: str, value: Any) -> SchemaViolation:
        """The error for a wrong ``value`` at ``path`` ("<path> must be <expected>, got <value>"),
        returned for the caller to raise.

        Args:
            path: the full key path of the value.
            value: the value found.
        """
        return SchemaViolation(path, f"{path} must be {self.describe()}, got {show(value)}")


class Bool(Spec):
    """``true`` or ``false`` (a JSON boolean: ``0``, ``1`` and strings are refused). Takes the
    arguments of :class:`Spec`."""

    kind = "bool"

    @property
    def expected(self) -> str:
        return "true or false"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if not isinstance(value, bool):
            raise self.fail(path, value)
        return value


class Int(Spec):
    """An integer, optionally bounded (inclusive). An integral float such as ``1e6`` is accepted
    and converted, since JSON writers often produce them; booleans are refused.

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        min: the smallest value allowed (inclusive), None for no lower bound.
        max: the largest value allowed (inclusive), None for no upper bound.
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "integer"

    def __init__(
        self,
        default: Any,
        doc: str,
        *,
        min: int | None = None,
        max: int | None = None,
        nullable: bool = False,
        **table: Any,
    ):
        super().__init__(default, doc, nullable=nullable, **table)
        self.min = min
        self.max = max

    @property
    def expected(self) -> str:
        lo, hi = self.min, self.max
        if lo is not None and hi is not None:
            return f"an integer from {lo} to {hi}"
        if lo == 1:
            return "a positive integer"
        if lo == 0:
            return "a non-negative integer"
        if lo is not None:
            return f"an integer >= {lo}"
        if hi is not None:
            return f"an integer <= {hi}"
        return "an integer"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, bool):
            raise self.fail(path, value)
        if isinstance(value, float) and math.isfinite(value) and value.is_integer():
            value = int(value)
        if not isinstance(value, int):
            raise self.fail(path, value)
        if (self.min is not None and value < self.min) or (self.max is not None and value > self.max):
            raise self.fail(path, value)
        return value


class Number(Spec):
    """A finite real number (an integer is accepted and converted to float), optionally bounded.

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        min: the lower bound, None for none.
        max: the upper bound, None for none.
        min_open: the lower bound itself is refused (``min < value``).
        max_open: the upper bound itself is refused (``value < max``).
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "number"

    def __init__(
        self,
        default: Any,
        doc: str,
        *,
        min: float | None = None,
        max: float | None = None,
        min_open: bool = False,
        max_open: bool = False,
        nullable: bool = False,
        **table: Any,
    ):
        super().__init__(default, doc, nullable=nullable, **table)
        self.min = min
        self.max = max
        self.min_open = min_open
        self.max_open = max_open

    @property
    def expected(self) -> str:
        lo, hi = self.min, self.max
        if lo is not None and hi is not None:
            left = "(" if self.min_open else "["
            right = ")" if self.max_open else "]"
            return f"a number in {left}{_fmt(lo)}, {_fmt(hi)}{right}"
        if lo == 0 and hi is None:
            return "a positive number" if self.min_open else "a non-negative number"
        if lo is not None:
            return f"a number {'>' if self.min_open else '>='} {_fmt(lo)}"
        if hi is not None:
            return f"a number {'<' if self.max_open else '<='} {_fmt(hi)}"
        return "a number"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(path, value)
        value = float(value)
        if not math.isfinite(value):
            raise self.fail(path, value)
        if self.min is not None and (value < self.min or (self.min_open and value == self.min)):
            raise self.fail(path, value)
        if self.max is not None and (value > self.max or (self.max_open and value == self.max)):
            raise self.fail(path, value)
        return value


class Str(Spec):
    """A string.

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        nonempty: the empty string (or only spaces) is refused.
        forbid: characters the string may not contain (for names used in file names); when not
            empty, ``"."`` and ``".."`` are refused too.
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "string"

    def __init__(self, default: Any, doc: str, *, nonempty: bool = False, forbid: str = "",
                 nullable: bool = False, **table: Any):
        super().__init__(default, doc, nullable=nullable, **table)
        self.nonempty = nonempty
        self.forbid = forbid

    @property
    def expected(self) -> str:
        text = "a non-empty string" if self.nonempty else "a string"
        if self.forbid:
            text += " without " + " or ".join(self.forbid)
        return text

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if not isinstance(value, str):
            raise self.fail(path, value)
        if self.nonempty and not value.strip():
            raise self.fail(path, value)
        if any(c in value for c in self.forbid) or (self.forbid and value.strip() in (".", "..")):
            raise self.fail(path, value)
        return value


class Choice(Spec):
    """One string out of a fixed set, matched case-insensitively and returned in its canonical
    spelling (``"redqsac"`` becomes ``"REDQSAC"``).

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        options: the allowed values, in their canonical spelling.
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "choice"

    def __init__(self, default: str, doc: str, options: Sequence[str], *, nullable: bool = False,
                 **table: Any):
        super().__init__(default, doc, nullable=nullable, **table)
        self.options = tuple(options)

    @property
    def expected(self) -> str:
        return "one of " + ", ".join(json.dumps(o) for o in self.options)

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, str):
            wanted = value.strip().casefold()
            for option in self.options:
                if option.casefold() == wanted:
                    return option
        raise self.fail(path, value)


class NumberList(Spec):
    """A list (or tuple) of exactly ``length`` numbers, each within the bounds of ``item``.

    Args:
        default: see :class:`Spec`.
        doc: see :class:`Spec`.
        length: the number of items required.
        item: the :class:`Number` each item must satisfy.
        nullable: see :class:`Spec`.
        **table: ``feeds`` and ``class_default``, see :class:`Spec`.
    """

    kind = "list"

    def __init__(self, default: Any, doc: str, *, length: int, item: Number, nullable: bool = False,
                 **table: Any):
        super().__init__(default, doc, nullable=nullable, **table)
        self.length = length
        self.item = item

    @property
    def expected(self) -> str:
        inner = self.item.expected
        inner = inner.removeprefix("a ")
        return f"a list of {self.length} {inner.replace('number', 'numbers', 1)}"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != self.length:
            raise self.fail(path, value)
        out = []
        for x in value:
            try:
                out.append(self.item.check(x, path))
            except SchemaViolation:
                raise self.fail(path, value) from None
        return out


def _plain_data(value: Any, path: str) -> Any:
    """Copy of a JSON-like value (tuples become lists); refuses anything JSON cannot hold so that
    the value survives the trip through ``TMRL_CONFIG_OVERRIDE`` to child processes."""
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise SchemaViolation(path, f"{path} must have string keys, got key {show(k)}")
            out[k] = _plain_data(v, _join(path, k))
        return out
    if isinstance(value, (list, tuple)):
        return [_plain_data(v, f"{path}[{i}]") for i, v in enumerate(value)]
    raise SchemaViolation(path, f"{path} must hold only JSON values, got {show(value)}")


class AnyDict(Spec):
    """A free-form object (keyword arguments passed through to user code). An override replaces
    it as a whole instead of merging into it."""

    kind = "object"

    @property
    def expected(self) -> str:
        return "an object (a dict with string keys)"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if not isinstance(value, Mapping):
            raise self.fail(path, value)
        return _plain_data(value, path)


class AnyList(Spec):
    """A free-form list (positional arguments passed through to user code)."""

    kind = "list"

    @property
    def expected(self) -> str:
        return "a list"

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            raise self.fail(path, value)
        return _plain_data(value, path)


class Section(Spec):
    """A nested object with a fixed set of keys. Unknown keys are refused (with a suggestion
    when one is close); missing keys take their defaults.

    Args:
        fields: key name -> :class:`Spec` of that key, in the order of ``config.json``.
        doc: one-line meaning of the section, shown in ``docs/config.md``.
    """

    kind = "section"

    def __init__(self, fields: dict[str, Spec], doc: str):
        super().__init__(None, doc)
        self.fields = fields

    @property
    def expected(self) -> str:
        return "an object (a dict of keys)"

    def default_value(self) -> dict[str, Any]:
        """A new dict with every key of the section at its default."""
        return {name: spec.default_value() for name, spec in self.fields.items()}

    def _check(self, value: Any, path: str, *, fill: bool) -> Any:
        if not isinstance(value, Mapping):
            if not path:
                raise SchemaViolation(path, f"the top level must be an object (a dict of keys), got {show(value)}")
            raise self.fail(path, value)
        for key in value:
            if not isinstance(key, str) or key not in self.fields:
                raise self.unknown(path, key)
        out: dict[str, Any] = {}
        for name, spec in self.fields.items():
            if name in value:
                out[name] = spec.check(value[name], _join(path, name), fill=fill)
            elif fill:
                out[name] = spec.default_value()
        return out

    def unknown(self, path: str, key: Any) -> SchemaViolation:
        """The error for a ``key`` this section does not have, suggesting the closest known key
        (returned for the caller to raise).

        Args:
            path: the key path of the section (``""`` for the top level).
            key: the unknown key found.
        """
        where = _join(path, str(key))
        close = difflib.get_close_matches(str(key), list(self.fields), n=1, cutoff=0.6)
        if not close:
            close = [k for k in self.fields if k.casefold() == str(key).casefold()]
        if close:
            hint = f"did you mean {_join(path, close[0])}?"
        else:
            hint = "remove it (docs/config.md lists every key)"
        return SchemaViolation(where, f"{where} is not a known key; {hint}")


# --- the schema ----------------------------------------------------------------------------------

RTGYM_INTERFACES = (
    "TM20FULL",
    "TM20LIDAR",
    "TM20LIDARPROGRESS",
    "SIMFULL",
    "SIMLIDAR",
    "SIMLIDARPROGRESS",
    "GYM",
    "DRONE",
)
"""Values of ``ENV.RTGYM_INTERFACE``: TrackMania 2020 (full images, lidar, lidar with track
progress), the built-in simulated track (same three observations), any Gymnasium environment
(``ENV.GYM_ID``), and the real-time simulated drone of :mod:`tmrl.realtime`."""

ALGORITHMS = ("SAC", "REDQSAC", "DROQ", "TQC", "CROSSQ")
"""Values of ``ALG.ALGORITHM``."""

PASSWORD_PLACEHOLDER = "YourRandomPasswordHere"
"""The password of the shipped file; ``python -m tmrl --install`` replaces it by a random one."""

OPTIMIZERS = ("adam", "adamw", "sgd")
"""Values of ``ALG.OPTIMIZER_ACTOR`` and ``ALG.OPTIMIZER_CRITIC`` (:func:`tmrl.algorithms.sac.make_optimizer`)."""

UPDATE_ORDERS = ("simultaneous", "sequential")
"""Values of ``ALG.UPDATE_ORDER`` (``SACAgent(update_order=...)``)."""

AGENT_CLASSES = {"SAC": "SACAgent", "REDQSAC": "REDQSACAgent", "DROQ": "DroQAgent", "TQC": "TQCAgent",
                 "CROSSQ": "CrossQAgent"}
"""The agent class each value of ``ALG.ALGORITHM`` selects (:data:`tmrl.algorithms.ALGORITHMS`)."""

_MIB = 1024 * 1024


def _agents(arg: str, class_default: Any) -> dict[str, Any]:
    """``feeds`` and ``class_default`` of an ``ALG`` key that every agent takes."""
    return {"feeds": tuple(f"{cls}.{arg}" for cls in AGENT_CLASSES.values()), "class_default": class_default}


_ALG = Section(
    {
        "ALGORITHM": Choice("SAC", "training algorithm (SAC: SACAgent, REDQSAC: REDQSACAgent, DROQ: DroQAgent, "
                            "TQC: TQCAgent, CROSSQ: CrossQAgent)", ALGORITHMS),
        "LEARN_ENTROPY_COEF": Bool(False, "learn the entropy coefficient (SAC v2) instead of keeping ALPHA fixed",
                                   **_agents("learn_entropy_coef", True)),
        "LR_ACTOR": Number(1e-05, "learning rate of the actor", min=0, min_open=True, **_agents("lr_actor", 1e-3)),
        "LR_CRITIC": Number(5e-05, "learning rate of the critic(s)", min=0, min_open=True,
                            **_agents("lr_critic", 1e-3)),
        "LR_ENTROPY": Number(0.0003, "learning rate of the entropy coefficient (when learned)", min=0,
                             min_open=True, **_agents("lr_entropy", 1e-3)),
        "GAMMA": Number(0.995, "discount factor", min=0, max=1, **_agents("gamma", 0.99)),
        "POLYAK": Number(0.995, "weight of the old target critic in each soft update (1: never updated)",
                         min=0, max=1, **_agents("polyak", 0.995)),
        "TARGET_ENTROPY": Number(-0.5, "target entropy when LEARN_ENTROPY_COEF is true (null: minus the action size)",
                                 nullable=True, **_agents("target_entropy", None)),
        "ALPHA": Number(0.01, "entropy coefficient (fixed, or initial value when learned)", min=0,
                         **_agents("alpha", 0.2)),
        "ALPHA_MAX": Number(None, "ceiling of a learned entropy coefficient once it has come down to it (it falls "
                                  "freely from ALPHA until then; null: no ceiling)", min=0, min_open=True,
                            nullable=True, **_agents("alpha_max", None)),
        "REDQ_N": Int(10, "number of critics in the REDQ ensemble", min=1, feeds=("REDQSACAgent.n",), class_default=10),
        "REDQ_M": Int(2, "number of critics drawn at random for each REDQ target", min=1, feeds=("REDQSACAgent.m",),
                      class_default=2),
        "REDQ_Q_UPDATES_PER_POLICY_UPDATE": Int(20, "REDQ critic updates for each actor update", min=1,
                                                feeds=("REDQSACAgent.q_updates_per_policy_update",), class_default=1),
        "DROQ_DROPOUT_RATE": Number(0.01, "dropout rate of the DroQ critics", min=0, max=1, max_open=True,
                                    feeds=("DroQAgent.dropout_rate",), class_default=0.01),
        "DROQ_Q_UPDATES_PER_POLICY_UPDATE": Int(20, "DroQ critic updates for each actor update", min=1,
                                                feeds=("DroQAgent.q_updates_per_policy_update",), class_default=20),
        "TQC_N": Int(5, "number of TQC critics", min=1, feeds=("TQCAgent.n",), class_default=5),
        "TQC_QUANTILES": Int(25, "quantiles output by each TQC critic", min=1, feeds=("TQCAgent.n_quantiles",),
                             class_default=25),
        "TQC_DROP_PER_CRITIC": Int(2, "largest target quantiles dropped per TQC critic (below TQC_QUANTILES)", min=0,
                                   feeds=("TQCAgent.drop_per_critic",), class_default=2),
        "CROSSQ_POLICY_DELAY": Int(3, "CrossQ critic updates for each actor update", min=1,
                                   feeds=("CrossQAgent.policy_delay",), class_default=3),
        "CROSSQ_CRITIC_WIDTH": Int(1024, "width of the two hidden layers of each CrossQ critic (the paper: 2048, "
                                         "for a GPU)", min=1, feeds=("CrossQAgent.critic_width",), class_default=1024),
        "CROSSQ_BN_MOMENTUM": Number(0.01, "momentum of the CrossQ critics' batch normalisation (weight of each "
                                           "batch in the running statistics)", min=0, max=1, min_open=True,
                                    feeds=("CrossQAgent.bn_momentum",), class_default=0.01),
        "CROSSQ_RENORM_WARMUP_STEPS": Int(100000, "CrossQ critic updates of plain batch normalisation before batch "
                                                  "renormalisation", min=0,
                                          feeds=("CrossQAgent.renorm_warmup_steps",), class_default=100000),
        "OPTIMIZER_ACTOR": Choice("adam", "optimizer of the actor", OPTIMIZERS, **_agents("optimizer_actor", "adam")),
        "OPTIMIZER_CRITIC": Choice("adam", "optimizer of the critic(s)", OPTIMIZERS,
                                   **_agents("optimizer_critic", "adam")),
        "BETAS_ACTOR": NumberList([0.997, 0.997], "Adam/AdamW betas of the actor", length=2,
                                  item=Number(0, "", min=0, max=1, max_open=True), **_agents("betas_actor", None)),
        "BETAS_CRITIC": NumberList([0.997, 0.997], "Adam/AdamW betas of the critic(s)", length=2,
                                   item=Number(0, "", min=0, max=1, max_open=True), **_agents("betas_critic", None)),
        "L2_ACTOR": Number(0.0, "weight decay of the actor optimizer", min=0, **_agents("l2_actor", None)),
        "L2_CRITIC": Number(0.0, "weight decay of the critic optimizer", min=0, **_agents("l2_critic", None)),
        "UPDATE_ORDER": Choice("simultaneous", "SAC only: \"simultaneous\" evaluates the actor loss on the critics "
                               "before their step (one backward pass), \"sequential\" after it (the original tmrl "
                               "SAC)", UPDATE_ORDERS, feeds=("SACAgent.update_order",),
                               class_default="simultaneous"),
    },
    "the training algorithm and its hyperparameters",
)

_RTGYM = Section(
    {
        "time_step_duration": Number(0.05, "target duration of one real-time step, in seconds", min=0,
                                     min_open=True),
        "start_obs_capture": Number(0.04, "time after the start of a step when the observation is captured (s)",
                                    min=0),
        "time_step_timeout_factor": Number(1.0, "how late a step may end, in steps, before the clock resets",
                                           min=0),
        "act_buf_len": Int(2, "number of past actions appended to each observation", min=1),
        "benchmark": Bool(False, "time the environment's steps (needed by --benchmark)"),
        "wait_on_done": Bool(True, "pause the environment when an episode ends"),
        "ep_max_length": Int(1000, "episodes are truncated after this many steps (null: never)", min=1,
                             nullable=True),
        "interface_kwargs": AnyDict({}, "keyword arguments of the interface (TrackMania: save_replays)"),
        "interface_args": AnyList([], "positional arguments of the interface"),
        "act_in_obs": Bool(True, "append the action buffer to observations"),
        "reset_act_buf": Bool(True, "fill the action buffer with the default action at reset"),
        "benchmark_polyak": Number(0.1, "smoothing factor of the benchmark averages", min=0, max=1,
                                   min_open=True),
        "benchmark_type": Choice("polyak", "how benchmarks are kept (running averages or full traces)",
                                 ("polyak", "trace")),
        "last_act_on_reset": Bool(False, "at reset, send the last action instead of the default one"),
    },
    "the real-time clock (rtgym parameters)",
)

_REWARD = Section(
    {
        "END_OF_TRACK": Number(100.0, "reward for crossing the finish line"),
        "CONSTANT_PENALTY": Number(0.0, "reward added at every step (zero or negative)"),
        "CHECK_FORWARD": Int(500, "trajectory points searched ahead of the car (allows cuts)", min=1),
        "CHECK_BACKWARD": Int(10, "trajectory points searched behind the car", min=0),
        "FAILURE_COUNTDOWN": Int(10, "steps without progress before the episode ends", min=1),
        "MIN_STEPS": Int(70, "steps at the start of an episode during which it cannot fail", min=0),
        "MAX_STRAY": Number(100.0, "distance from the trajectory (m) that ends the episode", min=0,
                            min_open=True),
    },
    "the trajectory reward (TrackMania and the simulated track)",
)

_ENV = Section(
    {
        "RTGYM_INTERFACE": Choice("TM20FULL", "environment: TrackMania 2020 (TM20*) or the simulated track (SIM*) "
                                              "with images (FULL), lidar (LIDAR) or lidar and progress "
                                              "(LIDARPROGRESS); a Gymnasium env (GYM, see GYM_ID); the real-time "
                                              "drone (DRONE)",
                                  RTGYM_INTERFACES),
        "WINDOW_WIDTH": Int(256, "the game window is resized to this width (pixels)", min=1),
        "WINDOW_HEIGHT": Int(128, "the game window is resized to this height (pixels)", min=1),
        "IMG_WIDTH": Int(64, "width of the images fed to the model", min=1),
        "IMG_HEIGHT": Int(64, "height of the images fed to the model", min=1),
        "IMG_GRAYSCALE": Bool(True, "convert images to grayscale"),
        "SLEEP_TIME_AT_RESET": Number(1.5, "seconds waited after a respawn (the green light)", min=0),
        "IMG_HIST_LEN": Int(4, "number of past images or lidar scans in each observation", min=1),
        "LINUX_X_OFFSET": Int(64, "horizontal offset of the game window's content on Linux (pixels)"),
        "LINUX_Y_OFFSET": Int(70, "vertical offset of the game window's content on Linux (pixels)"),
        "IMG_SCALE_CHECK_ENV": Number(1.0, "zoom of the images shown by --check-environment", min=0,
                                      min_open=True),
        "GYM_ID": Str("Pendulum-v1", "Gymnasium id used when RTGYM_INTERFACE is GYM"),
        "GYM_KWARGS": AnyDict({}, "keyword arguments of gymnasium.make when RTGYM_INTERFACE is GYM"),
        "SIM_FAST_MODE": Bool(True, "SIM* interfaces: step the simulator as fast as the CPU allows (false: in real "
                                    "time through tmrl.realtime, like the game)"),
        "RTGYM_CONFIG": _RTGYM,
        "REWARD_CONFIG": _REWARD,
    },
    "the environment",
)

SCHEMA = Section(
    {
        "RUN_NAME": Str("SAC_4_imgs_pretrained", "name of the run; names the weights and checkpoint files",
                        nonempty=True, forbid="/\\"),
        "RESET_TRAINING": Bool(False, "start training from scratch instead of resuming the checkpoint"),
        "BUFFERS_MAXLEN": Int(500000, "maximum number of samples held in a network buffer (not the replay memory)",
                              min=1, feeds=("Buffer.maxlen",)),
        "RW_MAX_SAMPLES_PER_EPISODE": Int(1000, "a worker truncates episodes longer than this", min=1,
                                          feeds=("RolloutWorker.max_samples_per_episode",)),
        "CUDA_TRAINING": Bool(False, "train on the GPU when one is available"),
        "CUDA_INFERENCE": Bool(False, "run the workers' policy on the GPU when one is available"),
        "VIRTUAL_GAMEPAD": Bool(True, "drive TrackMania with a virtual gamepad (false: keyboard)"),
        "LOCALHOST_WORKER": Bool(True, "the worker reaches the server on 127.0.0.1 (false: PUBLIC_IP_SERVER)"),
        "LOCALHOST_TRAINER": Bool(True, "the trainer reaches the server on 127.0.0.1 (false: PUBLIC_IP_SERVER)"),
        "PUBLIC_IP_SERVER": Str("0.0.0.0", "address of the server when it is on another machine", nonempty=True),
        "PASSWORD": Str(PASSWORD_PLACEHOLDER, "shared secret of the server, trainer and workers (same everywhere)",
                        nonempty=True, feeds=("Server.password", "Trainer.password", "RolloutWorker.password")),
        "TLS": Bool(False, "encrypt and authenticate connections with TLS (needed on public networks)"),
        "TLS_HOSTNAME": Str("default", "host name in the TLS certificate", nonempty=True),
        "TLS_CREDENTIALS_DIRECTORY": Str("", "folder of the TLS key and certificate (empty: credentials/ in the "
                                             "data folder)"),
        "ALLOW_PLAIN_TCP": Bool(False, "allow unencrypted connections to a server on another machine "
                                       "(trusted networks only)"),
        "ALLOW_PICKLE": Bool(False, "accept pickled messages from the network (trusted networks only: "
                                    "pickle can run code)"),
        "MAX_FRAME_BYTES": Int(64 * _MIB, "largest message accepted from the network, in bytes", min=1024),
        "NB_WORKERS": Int(64, "maximum number of workers connected to the server at once (negative: no limit)",
                          feeds=("Server.max_workers",)),
        "SERVER_MEMORY_BYTES": Int(1536 * _MIB, "most memory the server spends on samples waiting for the trainer "
                                                "and on messages being received, in bytes; a connection that "
                                                "would exceed it is closed", min=64 * _MIB),
        "SERVER_PARTIAL_TIMEOUT": Number(60.0, "seconds the server waits for the next part of a half-received "
                                               "message before it drops it and closes the connection", min=1),
        "TRANSPORT": Choice("tlspyo", 'how samples and weights cross the network: "tlspyo" (tmrl\'s relay) or '
                                      '"nats" (NATS JetStream, pip install "tmrl[nats]"; see the Scale-out page)',
                            ("tlspyo", "nats")),
        "NATS": Section(
            {
                "URLS": Str("", "comma-separated URLs of an existing NATS cluster (nats://host:4222,...); empty: "
                                "the server (--server) starts and supervises a local nats-server on PORT"),
                "STREAM": Str("tmrl-samples", "JetStream stream of the sample batches", nonempty=True,
                              forbid=".*>/\\"),
                "BUCKET": Str("tmrl-weights", "object-store and key-value bucket of the weights", nonempty=True,
                              forbid=".*>/\\"),
                "MAX_BYTES": Int(1024 * _MIB, "bound of the samples stream in bytes: beyond it the oldest batches "
                                              "are discarded (the trainer counts them)", min=_MIB),
                "MAX_MSGS": Int(100000, "bound of the samples stream in batches: beyond it the oldest are "
                                        "discarded (the trainer counts them)", min=1),
                "MAX_PAYLOAD": Int(8 * _MIB, "largest message the local nats-server accepts, in bytes (a sample "
                                             "batch must fit)", min=_MIB, max=64 * _MIB),
                "REPLICAS": Int(1, "copies of the stream and buckets in a NATS cluster (3 on a three-node "
                                   "cluster survives the loss of one node; 1 for a single server)", min=1, max=5),
                "TLS": Choice("auto", 'TLS to the NATS server: "auto" (on when TLS is true or the server is on '
                                      'another machine), "on" or "off"', ("auto", "on", "off")),
                "WORKER_CREDENTIALS": Str("", "a worker's NATS credentials file (worker.json from --install); "
                                              "empty: nats/worker.json in the credentials folder when it exists, "
                                              "else derived from PASSWORD"),
                "TRAINER_CREDENTIALS": Str("", "the trainer's NATS credentials file (trainer.json from --install); "
                                               "empty: nats/trainer.json in the credentials folder when it exists, "
                                               "else derived from PASSWORD"),
                "STORE_DIRECTORY": Str("", "folder of the local nats-server's JetStream store (empty: nats/ in "
                                           "the data folder)"),
            },
            "the NATS JetStream transport (TRANSPORT \"nats\"; see docs/scale-out.md)",
        ),
        "WANDB_PROJECT": Str("tmrl", "wandb project of --trainer --wandb"),
        "WANDB_ENTITY": Str("tmrl", "wandb entity (user or team) of --trainer --wandb"),
        "WANDB_KEY": Str("YourWandbApiKey", "wandb API key of --trainer --wandb"),
        "PORT": Int(55555, "public port of the server", min=1, max=65535,
                    feeds=("Server.port", "Trainer.server_port", "RolloutWorker.server_port")),
        "LOCAL_PORT_SERVER": Int(55556, "kept so that tmrl 0.7 config files load; unused (the server needs one port: PORT)",
                                 min=1, max=65535),
        "LOCAL_PORT_TRAINER": Int(55557, "kept so that tmrl 0.7 config files load; unused (the trainer opens no port)",
                                  min=1, max=65535),
        "LOCAL_PORT_WORKER": Int(55558, "kept so that tmrl 0.7 config files load; unused (workers open no port, "
                                        "several can share a machine)", min=1, max=65535),
        "BUFFER_SIZE": Int(536870912, "kept so that tmrl 0.7 config files load; unused (the transport sizes its "
                           "own socket buffers; MAX_FRAME_BYTES bounds a message)",
                           min=1),
        "HEADER_SIZE": Int(12, "size of the transport's message header, in bytes", min=1,
                           feeds=("Server.header_size", "Trainer.header_size", "RolloutWorker.header_size")),
        "SEED": Int(None, "seeds Python's, NumPy's and PyTorch's generators when a role starts "
                           "(initial weights, exploration); a distributed run still varies with sample arrival order; null: "
                           "no seeding", nullable=True, min=0),
        "DEBUG_MODE": Bool(False, "kept so that tmrl 0.7 config files load; unused (CRC_DEBUG checks samples "
                                            "end to end)"),
        "MAX_EPOCHS": Int(10000, "number of training epochs (a checkpoint is saved after each)", min=1,
                          feeds=("TorchTrainingOffline.epochs",), class_default=10),
        "ROUNDS_PER_EPOCH": Int(100, "rounds per epoch (metrics are reported after each)", min=1,
                                feeds=("TorchTrainingOffline.rounds",), class_default=50),
        "TRAINING_STEPS_PER_ROUND": Int(200, "training steps per round", min=1, feeds=("TorchTrainingOffline.steps",), class_default=2000),
        "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": Number(4.0, "training pauses when updates per collected "
                                                               "sample exceed this", min=0, min_open=True,
                                                        feeds=("TorchTrainingOffline.max_training_steps_per_env_step",), class_default=1.0),
        "MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP": Number(
            0.0, "workers pause when samples collected per training step exceed this (0: never); for "
            "environments faster than real time, like the simulator in fast mode; real-time environments "
            "pause only between episodes", min=0, feeds=("TorchTrainingOffline.max_env_steps_per_training_step",), class_default=0.0),
        "ENVIRONMENT_STEPS_BEFORE_TRAINING": Int(1000, "samples collected before training starts", min=0,
                                                 feeds=("TorchTrainingOffline.start_training",), class_default=0),
        "UPDATE_MODEL_INTERVAL": Int(200, "training steps between two broadcasts of the weights", min=1,
                                     feeds=("TorchTrainingOffline.update_model_interval",), class_default=100),
        "UPDATE_BUFFER_INTERVAL": Int(200, "training steps between two retrievals of new samples", min=1,
                                      feeds=("TorchTrainingOffline.update_buffer_interval",), class_default=100),
        "SAVE_MODEL_EVERY": Int(0, "workers keep a copy of every N-th received model (0: none)", min=0,
                                feeds=("RolloutWorker.model_history",)),
        "MEMORY_SIZE": Int(1000000, "capacity of the replay memory, in samples", min=1,
                           feeds=("GenericTorchMemory.memory_size",), class_default=1000000),
        "BATCH_SIZE": Int(256, "training batch size", min=1, feeds=("GenericTorchMemory.batch_size",), class_default=256),
        "ALG": _ALG,
        "ENV": _ENV,
        "__VERSION__": Str("0.6.0", "format version of this file (do not edit)", nonempty=True),
    },
    "config.json",
)
"""The schema of ``config.json``: every key with its type, default, range and meaning (the table
of the Configuration page is generated from it)."""


def defaults() -> dict[str, Any]:
    """A fresh dict holding every key at its default (with the placeholder password)."""
    return SCHEMA.default_value()


def _fed(section: Section, cfg: Mapping[str, Any], cls: str, out: dict[str, Any]) -> None:
    for name, spec in section.fields.items():
        if isinstance(spec, Section):
            _fed(spec, cfg[name], cls, out)
            continue
        for target in spec.feeds:
            owner, _, arg = target.partition(".")
            if owner == cls:
                out[arg] = copy.deepcopy(cfg[name])


def arguments(cfg: Mapping[str, Any], cls: str) -> dict[str, Any]:
    """The constructor arguments of class ``cls`` (``"SACAgent"``, ``"TorchTrainingOffline"``,
    ...) that a loaded config sets, by the ``feeds`` of the table: ``{"lr_actor": 1e-05, ...}``.

    Args:
        cfg: a complete, validated config (:func:`tmrl.config.loader.load_config`).
        cls: the class name as written in ``feeds``.
    """
    out: dict[str, Any] = {}
    _fed(SCHEMA, cfg, cls, out)
    return out


def fed_arguments() -> dict[str, dict[str, tuple[str, Any]]]:
    """For each class named in ``feeds``: ``{argument: (key path, class default)}`` (the class
    default is :data:`NO_CLASS_DEFAULT` where the table declares none). The tests check every
    class's signature against it."""
    table: dict[str, dict[str, tuple[str, Any]]] = {}

    def walk(section: Section, path: str) -> None:
        for name, spec in section.fields.items():
            key = _join(path, name)
            if isinstance(spec, Section):
                walk(spec, key)
                continue
            for target in spec.feeds:
                owner, _, arg = target.partition(".")
                table.setdefault(owner, {})[arg] = (key, spec.class_default)

    walk(SCHEMA, "")
    return table


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
    ``REDQ_N``, the simultaneous update order of REDQ, DroQ and TQC, TQC's dropped quantiles fewer
    than its quantiles, the two pacing ratios not blocking each other,
    ``act_in_obs`` for the simulator and TrackMania, grayscale images for ``SIMFULL``, a
    ``GYM_ID`` for ``GYM``.

    Args:
        cfg: a complete config, each key already checked by :data:`SCHEMA`.

    Raises:
        SchemaViolation: naming the key to change.
    """
    alg = cfg["ALG"]
    problem = redq_subset_problem(alg["REDQ_N"], alg["REDQ_M"]) if alg["ALGORITHM"] == "REDQSAC" else None
    if problem:
        raise SchemaViolation("ALG.REDQ_M", problem)
    if alg["ALGORITHM"] in ("REDQSAC", "DROQ", "TQC") and alg["UPDATE_ORDER"] != "simultaneous":
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
            f"MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP ({_fmt(pace)}) times MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP "
            f"({_fmt(ratio)}) must be at least 1, or workers and trainer would wait for each other; raise one of "
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


# --- generated artefacts -------------------------------------------------------------------------


def default_config_json() -> str:
    """The text of the shipped ``config/config.json``: the defaults, indented, ending in a newline."""
    return json.dumps(defaults(), indent=2) + "\n"


_GENERIC_TRAINING: dict[str, Any] = {
    "RW_MAX_SAMPLES_PER_EPISODE": 200,
    "MAX_EPOCHS": 20,
    "ROUNDS_PER_EPOCH": 10,
    "TRAINING_STEPS_PER_ROUND": 100,
    "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 1.0,
    "ENVIRONMENT_STEPS_BEFORE_TRAINING": 1000,
    "UPDATE_MODEL_INTERVAL": 100,
    "UPDATE_BUFFER_INTERVAL": 100,
    "MEMORY_SIZE": 100000,
    "BATCH_SIZE": 256,
}
_GENERIC_ALG: dict[str, Any] = {
    "LEARN_ENTROPY_COEF": True,
    "LR_ACTOR": 0.001,
    "LR_CRITIC": 0.001,
    "LR_ENTROPY": 0.001,
    "GAMMA": 0.99,
    "ALPHA": 0.2,
    "TARGET_ENTROPY": None,
    "BETAS_ACTOR": [0.9, 0.999],
    "BETAS_CRITIC": [0.9, 0.999],
}

# The simulator's files: the demo's settings (tmrl.sim.demo.DEMO_SETTINGS), under which a server,
# a trainer and a worker on one machine learn to drive the default track within minutes on a CPU.
_SIM_TRAINING: dict[str, Any] = {
    **_GENERIC_TRAINING,
    "RW_MAX_SAMPLES_PER_EPISODE": 1000,
    "MAX_EPOCHS": 10000,
    "ROUNDS_PER_EPOCH": 10,
    "TRAINING_STEPS_PER_ROUND": 200,
    "UPDATE_MODEL_INTERVAL": 20,
    "UPDATE_BUFFER_INTERVAL": 20,
    "MEMORY_SIZE": 200000,
    # The fast simulator runs far faster than the trainer: keep three samples per update at most.
    "MAX_ENVIRONMENT_STEPS_PER_TRAINING_STEP": 3.0,
    # In real time (SIM_FAST_MODE false) the clock sets the pace and the trainer, otherwise idle, does
    # up to 4 updates per sample: SAC laps in fewer environment steps so (bench/track_learning.py).
    # In fast mode the line above binds first and this one changes nothing. (In real time, set ALG's
    # ALPHA 0.01 and LEARN_ENTROPY_COEF false too, as the demo does: docs/simulator.md.)
    "MAX_TRAINING_STEPS_PER_ENVIRONMENT_STEP": 4.0,
}
_SIM_RTGYM: dict[str, Any] = {
    "time_step_duration": 0.05,
    "start_obs_capture": 0.04,
    "time_step_timeout_factor": 1.0,
    "act_buf_len": 2,
    "benchmark": False,
    "wait_on_done": True,
    "ep_max_length": 1000,
    "interface_kwargs": {"track": "classic"},
}


def _sim_example(interface: str, **env: Any) -> dict[str, Any]:
    return {
        "RUN_NAME": f"{interface.lower()}_sac",
        **_SIM_TRAINING,
        "ALG": _GENERIC_ALG,
        "ENV": {"RTGYM_INTERFACE": interface, "SIM_FAST_MODE": True, "IMG_HIST_LEN": 4, **env,
                "RTGYM_CONFIG": _SIM_RTGYM},
    }


EXAMPLES: dict[str, dict[str, Any]] = {
    "config_tm20lidar.json": {
        "RUN_NAME": "SAC_4_LIDAR_pretrained",
        "ENV": {"RTGYM_INTERFACE": "TM20LIDAR", "WINDOW_WIDTH": 958, "WINDOW_HEIGHT": 488},
    },
    "config_gym_pendulum.json": {
        "RUN_NAME": "pendulum_sac",
        **_GENERIC_TRAINING,
        "ALG": _GENERIC_ALG,
        "ENV": {"RTGYM_INTERFACE": "GYM", "GYM_ID": "Pendulum-v1", "GYM_KWARGS": {}},
    },
    "config_drone.json": {
        "RUN_NAME": "drone_sac",
        **_GENERIC_TRAINING,
        "ALG": _GENERIC_ALG,
        "ENV": {
            "RTGYM_INTERFACE": "DRONE",
            "RTGYM_CONFIG": {"time_step_duration": 0.05, "start_obs_capture": 0.05, "act_buf_len": 2,
                             "wait_on_done": False, "ep_max_length": 100, "interface_kwargs": {}},
        },
    },
    "config_simlidar.json": _sim_example("SIMLIDAR"),
    "config_simlidarprogress.json": _sim_example("SIMLIDARPROGRESS"),
    "config_simfull.json": _sim_example("SIMFULL", IMG_WIDTH=64, IMG_HEIGHT=64, IMG_GRAYSCALE=True),
}
"""Example files shipped beside the default ``config/config.json``: the defaults with these keys
changed (starting points: copy one over your ``config.json``)."""


def example_json(name: str) -> str:
    """The text of the shipped example ``config/<name>``: a complete, valid config.

    Args:
        name: a file name among the keys of :data:`EXAMPLES` (``"config_simlidar.json"``).

    Raises:
        KeyError: ``name`` is not one of :data:`EXAMPLES`.
    """
    cfg = SCHEMA.check(defaults(), "")
    delta = SCHEMA.check(EXAMPLES[name], "", fill=False)

    def merge(base: dict[str, Any], upd: dict[str, Any], spec: Section) -> dict[str, Any]:
        out = dict(base)
        for k, v in upd.items():
            sub = spec.fields[k]
            out[k] = merge(out[k], v, sub) if isinstance(sub, Section) else v
        return out

    full = merge(cfg, delta, SCHEMA)
    check_consistency(full)
    return json.dumps(full, indent=2) + "\n"


def generated_files() -> dict[str, str]:
    """Repository-relative path -> text of every file generated from the schema."""
    files = {"docs/config.md": markdown_reference(), "config/config.json": default_config_json()}
    for name in EXAMPLES:
        files[f"config/{name}"] = example_json(name)
    return files


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def _feeds_cell(spec: Spec) -> str:
    """``SACAgent(lr_actor=0.001)``-style list of the arguments a key sets, with the class's own
    default where it has one."""
    parts = []
    for target in spec.feeds:
        owner, _, arg = target.partition(".")
        if spec.class_default is NO_CLASS_DEFAULT:
            parts.append(f"`{owner}({arg})`")
        else:
            parts.append(f"`{owner}({arg}={show(spec.class_default, 30)})`")
    return ", ".join(parts)


def _rows(section: Section, path: str, rows: list[str]) -> None:
    for name, spec in section.fields.items():
        key = _join(path, name)
        if isinstance(spec, Section):
            rows.append(f"| `{key}` | object | | {_md_escape(spec.doc)} (keys below) | |")
            _rows(spec, key, rows)
        else:
            default = "" if spec.default is None and not spec.nullable else f"`{show(spec.default, 60)}`"
            rows.append(f"| `{key}` | {_md_escape(spec.describe())} | {_md_escape(default)} | {_md_escape(spec.doc)} "
                        f"| {_md_escape(_feeds_cell(spec))} |")


def markdown_reference() -> str:
    """The text of ``docs/config.md``: one table row per key, generated from :data:`SCHEMA`."""
    rows: list[str] = []
    _rows(SCHEMA, "", rows)
    head = [
        "# config.json reference",
        "",
        "<!-- Generated from tmrl/config/schema.py by `python -m tmrl.config.schema --write`; do not edit. -->",
        "",
        "`config.json` lives in `config/` of the data folder (`$TMRL_DATA`, or `~/TmrlData` when it is",
        "not set); `python -m tmrl --install` creates it with a fresh random `PASSWORD`. A file written for",
        "the original tmrl 0.7 loads unchanged.",
        "",
        "- A missing key takes the default below.",
        "- An unknown key, a value of the wrong type or out of range stops the command with exit code 2",
        "  and one line naming the key path, the value found and what is expected.",
        "- `python -m tmrl ... -d '{\"ALG\": {\"LR_ACTOR\": 0.0001}}'` (JSON or a Python literal) overrides",
        "  keys for one run. Sections merge key by key; free-form objects (`GYM_KWARGS`,",
        "  `interface_kwargs`) are replaced as a whole. `python -m tmrl --print-config` shows the result.",
        "- Choices (`ALGORITHM`, `RTGYM_INTERFACE`, optimizers) are matched without regard to case.",
        "",
        "- The last column names the constructor argument each key sets when `python -m tmrl` builds",
        "  the objects, and that argument's own default in the class (what a script gets when it builds",
        "  the class itself without that argument; the defaults of tmrl 0.7.1's classes and of its",
        "  `config.json` differ in places, and both are kept).",
        "",
        "| key | expected | default | meaning | sets (class default) |",
        "|---|---|---|---|---|",
    ]
    return "\n".join(head + rows) + "\n"


def _repo_root() -> Path:
    return Path(__file__).resolve().parents[2]


def main(argv: list[str] | None = None) -> int:
    """``python -m tmrl.config.schema``: print or write the generated reference and default file."""
    parser = argparse.ArgumentParser(prog="python -m tmrl.config.schema", description=main.__doc__)
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--markdown", action="store_true", help="print docs/config.md")
    group.add_argument("--json", action="store_true", help="print the default config.json")
    group.add_argument("--write", action="store_true",
                       help="write docs/config.md and the config/*.json files of the source checkout")
    args = parser.parse_args(argv)
    if args.markdown:
        sys.stdout.write(markdown_reference())
    elif args.json:
        sys.stdout.write(default_config_json())
    else:
        root = _repo_root()
        for rel, text in generated_files().items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_text(text, encoding="utf-8")
            print(f"wrote {root / rel}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
