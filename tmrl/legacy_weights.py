"""Weights files of the original tmrl 0.7: import them into this tmrl's actors, export ours for it.

A tmrl 0.7 weights file (``.tmod``) is ``torch.save(actor.state_dict())``: a pickle. It is read
here with PyTorch's restricted loader (``torch.load(..., weights_only=True)``), which rebuilds
tensors and plain containers and refuses every other object without running it. Its tensors are
then mapped onto the actor this configuration builds, and every name and shape is checked: a
file for another model or another environment is refused in one line, nothing is written.

The built-in actors compute what the original's did, with three differences in the layout of
their parameters, which the mapping undoes:

- lidar actors (:class:`tmrl.driving.models.LidarActor`) scale speed and lidar inputs by
  :data:`~tmrl.driving.models.LIDAR_INPUT_SCALE` inside the network: the first layer's columns
  for those inputs are divided by the scale on import (multiplied on export);
- the CNN actor (:class:`tmrl.driving.models.SquashedGaussianCNNActor`) names its convolutions
  ``encoder.convs.{0,2,4,6}`` where the original's ``VanillaCNN`` has ``net.conv1..4``, its MLP
  ``net`` where the original has ``net.mlp``, and concatenates ``(image features, speed, gear,
  rpm, actions)`` where the original concatenates ``(speed, gear, rpm, image features,
  actions)``: the first MLP layer's columns are permuted;
- any other actor (the MLP actor, a user's) must have exactly the file's names and shapes.

Export writes the inverse: a plain dict of tensors saved with ``torch.save``, which the original
loads with ``torch.load`` into its actor.
"""

from __future__ import annotations

import io
import logging
import os
import pickle
from collections import OrderedDict
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tmrl.errors import UserError

__all__ = ["LegacyWeightsError", "export_state", "import_state", "read_legacy_file", "write_legacy_file"]

logger = logging.getLogger(__name__)

State = dict[str, torch.Tensor]


class LegacyWeightsError(UserError):
    """A weights file that cannot be imported or exported (the message says why and what to do)."""


def read_legacy_file(path: str | os.PathLike[str]) -> State:
    """The tensors of a tmrl 0.7 weights file, read without running any code.

    Raises:
        LegacyWeightsError: no such file, a file that holds anything but named tensors (a pickled
            object is refused before it is built), or a file PyTorch cannot read.
    """
    path = Path(path)
    if not path.is_file():
        raise LegacyWeightsError(f"no weights file at {path}")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        detail = " ".join(str(err).split("\n")[0].split())[:160]
        raise LegacyWeightsError(
            f"{path} holds more than tensors ({detail}); tmrl reads weights files with PyTorch's restricted "
            "loader and never runs the code a pickle carries: export the weights as a state_dict "
            "(torch.save(actor.state_dict(), path))"
        ) from None
    except (RuntimeError, OSError, EOFError, ValueError) as err:
        detail = " ".join(str(err).split())[:160]
        raise LegacyWeightsError(f"{path} is not a PyTorch weights file ({detail})") from None
    if not isinstance(data, Mapping) or not data:
        raise LegacyWeightsError(
            f"{path} holds a {type(data).__name__}, not a state_dict of named tensors: it is not a tmrl 0.7 "
            "weights file"
        )
    bad = next((k for k, v in data.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)), None)
    if bad is not None:
        raise LegacyWeightsError(f"{path}: entry {bad!r} is not a named tensor: it is not a tmrl 0.7 weights file")
    return {k: v.detach().clone() for k, v in data.items()}


def write_legacy_file(state: Mapping[str, torch.Tensor], path: str | os.PathLike[str]) -> Path:
    """Write ``state`` as the original writes weights (``torch.save`` of an ordered dict of
    tensors), atomically. Returns the path."""
    from tmrl.util import atomic_write_bytes

    buf = io.BytesIO()
    torch.save(OrderedDict((k, v.detach().cpu().contiguous()) for k, v in state.items()), buf)
    return atomic_write_bytes(path, buf.getvalue())


# ------------------------------------------------------------------------------------------------
# Layouts: how an actor's state_dict maps to the original's


def _input_columns(observation_space: Any) -> list[int]:
    """Number of flattened inputs of each element of a (Tuple) observation space."""
    from tmrl.models import space_dim

    elements = list(getattr(observation_space, "spaces", [observation_space]))
    return [space_dim(s) for s in elements]


def _lidar_column_scale(actor: Any) -> torch.Tensor:
    """Per-input scale of the first layer of a lidar actor (1 where inputs are not scaled)."""
    widths = _input_columns(actor.observation_space)
    scales = list(actor.obs_scales) + [1.0] * (len(widths) - len(actor.obs_scales))
    return torch.cat([torch.full((w,), float(s)) for w, s in zip(widths, scales)])


def _lidar_to_ours(theirs: State, actor: Any) -> State:
    ours = dict(theirs)
    if "net.0.weight" in ours:
        scale = _lidar_column_scale(actor)
        if ours["net.0.weight"].shape[1] == len(scale):
            ours["net.0.weight"] = ours["net.0.weight"] / scale
    return ours


def _lidar_to_theirs(ours: State, actor: Any) -> State:
    theirs = dict(ours)
    theirs["net.0.weight"] = theirs["net.0.weight"] * _lidar_column_scale(actor)
    return theirs


def _cnn_permutation(actor: Any) -> np.ndarray:
    """Index array p such that ``ours[:, i] = theirs[:, p[i]]`` for the CNN actor's first MLP layer."""
    widths = _input_columns(actor.observation_space)
    image = actor.image_index
    feats = actor.encoder.out_dim
    starts = np.concatenate([[0], np.cumsum([feats if i == image else w for i, w in enumerate(widths)])])
    # The original's order is the observation's (speed, gear, rpm, images, actions...), with the image
    # features where the images are; ours puts the image features first, then the other elements.
    order = [image] + [i for i in range(len(widths)) if i != image]
    return np.concatenate([np.arange(starts[i], starts[i + 1]) for i in order])


def _cnn_names(actor: Any) -> list[tuple[str, str]]:
    """``(ours, theirs)`` parameter names of the CNN actor's convolutions and MLP."""
    pairs = []
    convs = [i for i, m in enumerate(actor.encoder.convs) if isinstance(m, torch.nn.Conv2d)]
    for n, i in enumerate(convs, start=1):
        pairs += [(f"encoder.convs.{i}.{p}", f"net.conv{n}.{p}") for p in ("weight", "bias")]
    linears = [i for i, m in enumerate(actor.net) if isinstance(m, torch.nn.Linear)]
    for i in linears:
        pairs += [(f"net.{i}.{p}", f"net.mlp.{i}.{p}") for p in ("weight", "bias")]
    for head in ("mu_layer", "log_std_layer"):
        pairs += [(f"{head}.{p}", f"{head}.{p}") for p in ("weight", "bias")]
    return pairs


def _cnn_to_ours(theirs: State, actor: Any) -> State:
    ours: State = {}
    for mine, other in _cnn_names(actor):
        if other not in theirs:
            raise LegacyWeightsError(f"the file has no {other!r}: it is not the weights of tmrl 0.7's CNN actor")
        ours[mine] = theirs[other]
    extra = sorted(set(theirs) - {other for _, other in _cnn_names(actor)})
    if extra:
        raise LegacyWeightsError(f"the file has {extra[0]!r}, which tmrl 0.7's CNN actor does not: another model")
    first = "net.0.weight"
    perm = _cnn_permutation(actor)
    if ours[first].shape[1] == len(perm):
        ours[first] = ours[first][:, torch.from_numpy(perm)]
    return ours


def _cnn_to_theirs(ours: State, actor: Any) -> State:
    theirs: State = {}
    perm = _cnn_permutation(actor)
    for mine, other in _cnn_names(actor):
        theirs[other] = ours[mine]
    inverse = np.argsort(perm)
    theirs["net.mlp.0.weight"] = theirs["net.mlp.0.weight"][:, torch.from_numpy(inverse)]
    return theirs


def _same(state: State, actor: Any) -> State:
    return dict(state)


def _layout(actor: Any) -> tuple[Callable[[State, Any], State], Callable[[State, Any], State], str]:
    """``(to_ours, to_theirs, description)`` for ``actor``."""
    from tmrl.driving.models import LidarActor, SquashedGaussianCNNActor

    if isinstance(actor, SquashedGaussianCNNActor):
        return _cnn_to_ours, _cnn_to_theirs, "tmrl 0.7's CNN actor (SquashedGaussianVanillaCNNActor)"
    if isinstance(actor, LidarActor):
        return _lidar_to_ours, _lidar_to_theirs, "tmrl 0.7's MLP actor (SquashedGaussianMLPActor)"
    return _same, _same, f"{type(actor).__name__}"


def _check_against(state: State, actor: Any, what: str) -> None:
    """Every name and shape of ``actor``'s state_dict in ``state``, nothing else, all finite."""
    expected = {k: tuple(v.shape) for k, v in actor.state_dict().items()}
    missing = sorted(set(expected) - set(state))
    extra = sorted(set(state) - set(expected))
    if missing or extra:
        name = missing[0] if missing else extra[0]
        side = "lacks" if missing else "has an unexpected"
        raise LegacyWeightsError(
            f"the weights do not fit the configured actor ({what}): the file {side} {name!r}; import them with "
            "the config.json they were trained with (ENV.RTGYM_INTERFACE, image size, history lengths)"
        )
    for key, shape in expected.items():
        if tuple(state[key].shape) != shape:
            raise LegacyWeightsError(
                f"the weights do not fit the configured actor ({what}): {key!r} has shape "
                f"{tuple(state[key].shape)} in the file, the actor needs {shape}; import them with the "
                "config.json they were trained with"
            )
        if state[key].is_floating_point() and not bool(torch.isfinite(state[key]).all()):
            raise LegacyWeightsError(f"{key!r} holds NaN or infinite values: these weights are broken")


def import_state(theirs: Mapping[str, torch.Tensor], actor: Any) -> State:
    """The state_dict for ``actor`` equivalent to the tmrl 0.7 state_dict ``theirs``.

    Raises:
        LegacyWeightsError: the tensors do not fit ``actor`` (names, shapes) or are not finite.
    """
    to_ours, _, what = _layout(actor)
    state = to_ours(dict(theirs), actor)
    _check_against(state, actor, what)
    return {k: v.to(actor.state_dict()[k].dtype) for k, v in state.items()}


def export_state(actor: Any) -> State:
    """tmrl 0.7's state_dict equivalent to ``actor``'s current parameters."""
    _, to_theirs, _ = _layout(actor)
    ours = {k: v.detach().cpu() for k, v in actor.state_dict().items()}
    return to_theirs(ours, actor)


def import_file(src: str | os.PathLike[str], out: str | os.PathLike[str], actor: Any) -> Path:
    """Import the tmrl 0.7 weights file ``src`` into ``actor`` and save it to ``out`` in this
    tmrl's format (``actor.save``). Nothing is written when the file does not fit.

    Raises:
        LegacyWeightsError: see :func:`read_legacy_file` and :func:`import_state`.
    """
    state = import_state(read_legacy_file(src), actor)
    actor.load_state_dict(state)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    actor.save(str(out))
    return out


def export_file(src: str | os.PathLike[str], out: str | os.PathLike[str], actor: Any) -> Path:
    """Load this tmrl's weights file ``src`` into ``actor`` and write them as a tmrl 0.7 weights
    file at ``out``.

    Raises:
        LegacyWeightsError: no such file, or weights that do not fit ``actor``.
    """
    src = Path(src)
    if not src.is_file():
        raise LegacyWeightsError(f"no weights file at {src}")
    try:
        actor = actor.load(str(src), device="cpu")
    except UserError:
        raise
    except Exception as err:  # noqa: BLE001 (any failure to read them: one line)
        detail = " ".join(str(err).split())[:160]
        raise LegacyWeightsError(f"cannot load {src} into the configured actor ({detail})") from None
    return write_legacy_file(export_state(actor), out)
