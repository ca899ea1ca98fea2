"""Checkpoint files: write atomically, read safely, rebuild the network and camera they hold.

A checkpoint is a ``torch.save`` of one dictionary::

    {
        "format": "sq_mitsuba.checkpoint",
        "version": 1,
        "config": {...},   # to_dict of the training config; its "network" entry is the
                           # NetworkConfig as a dict
        "model": {...},    # SuperquadricNet.state_dict()
        "camera": {...},   # Camera.to_speed_dict() of the dataset camera
        "baseline": {...}, # optional: the trivial baseline ("raw" (1, M, 16), "rotation"
                           # (1, 3, 3), "translation" (1, 3)), see checkpoint_baseline
        ...                # anything else the training adds (optimiser state, step, metrics)
    }

Every value must load with ``torch.load(weights_only=True)``: dicts, lists, tuples, strings,
numbers, booleans, None and tensors (:func:`write_checkpoint` refuses anything else before it
writes). Files are read with ``weights_only=True`` only, so a checkpoint cannot run code.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from sq_mitsuba.config import ConfigError, from_dict, to_dict
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.inputs import check_finite_tensors, load_torch_file
from sq_mitsuba.io import atomic_path
from sq_mitsuba.model.network import (
    NetworkConfig,
    SuperquadricNet,
    sphere_directions,
    upgrade_state_dict,
)

__all__ = [
    "FORMAT",
    "GROWN_OFFSET",
    "SHIPPED_MODEL",
    "VERSION",
    "checkpoint_baseline",
    "checkpoint_network_config",
    "checkpoint_payload",
    "grown_generators",
    "load_weights",
    "model_from_checkpoint",
    "read_checkpoint",
    "write_checkpoint",
]

FORMAT = "sq_mitsuba.checkpoint"
VERSION = 1
#: The model shipped as package data, loaded by ``load_model()`` without a path.
SHIPPED_MODEL = Path(__file__).resolve().parent / "weights" / "model.pt"
_REQUIRED = ("config", "model", "camera")
# Exact types: numpy scalars subclass float but weights_only loading refuses them.
_SCALARS = (str, int, float, bool, type(None))
#: The generators' grouped layers, whose first dimension is the primitive: what a partial load
#: may grow (:func:`grown_generators`).
_GROUPED = tuple(f"sq_generator.layers.{k}.{name}" for k in range(3)
                 for name in ("weight", "bias"))
#: Raw translation added to a grown primitive's position outputs (along a direction of its
#: own), so it does not coincide with the primitive it copies: at most 0.05 model units.
GROWN_OFFSET = 0.1


def _check_loadable(value: Any, where: str) -> None:
    """Refuse values that ``torch.load(weights_only=True)`` would not read back."""
    if type(value) in _SCALARS or isinstance(value, Tensor):
        return
    if type(value) in (dict, OrderedDict):
        for key, item in value.items():
            if not isinstance(key, str | int):
                raise ValueError(f"{where}: keys must be strings or integers, got {key!r}")
            _check_loadable(item, f"{where}.{key}")
        return
    if isinstance(value, list | tuple) and type(value) in (list, tuple):
        for index, item in enumerate(value):
            _check_loadable(item, f"{where}[{index}]")
        return
    raise ValueError(f"{where}: {type(value).__name__} cannot be read back with weights_only=True "
                     "(use dicts, lists, strings, numbers, None and tensors)")


def checkpoint_network_config(payload: Mapping[str, Any], where: str) -> NetworkConfig:
    """The :class:`NetworkConfig` a checkpoint dictionary holds (a field a file written before
    it existed takes its default).

    Raises:
        ValueError: ``<where>: ...`` when ``config.network`` is missing or invalid.
    """
    config = payload.get("config")
    if not isinstance(config, Mapping) or not isinstance(config.get("network"), Mapping):
        raise ValueError(f"{where}: 'config' must be a dict with a 'network' dict")
    try:
        return from_dict(NetworkConfig, config["network"], "config.network")
    except ConfigError as error:
        raise ValueError(f"{where}: {error}") from None


def checkpoint_payload(model: SuperquadricNet, camera: Camera,
                       config: Mapping[str, Any] | None = None, **extra: Any) -> dict[str, Any]:
    """A checkpoint dictionary for ``model`` (weights copied to the CPU) and ``camera``.

    Args:
        model: the network.
        camera: the dataset camera (the predictor's default camera).
        config: ``to_dict`` of the training config; its ``network`` entry is replaced by
            ``model.config`` (default: ``{"network": to_dict(model.config)}``).
        extra: further entries (e.g. ``step=1000``).
    """
    network = to_dict(model.config)
    state = {key: value.detach().cpu().clone() for key, value in model.state_dict().items()}
    return {
        "format": FORMAT,
        "version": VERSION,
        "config": {**dict(config or {}), "network": network},
        "model": state,
        "camera": camera.to_speed_dict(),
        **extra,
    }


def write_checkpoint(path: str | os.PathLike[str], payload: dict[str, Any]) -> Path:
    """Save ``payload`` to ``path`` atomically (temporary file, then rename).

    ``format`` and ``version`` are filled in when missing. Everything is checked before the
    file is touched.

    Raises:
        ValueError: naming ``payload`` (or the bad entry): another format or version, a missing
            ``config`` / ``model`` / ``camera``, a network config that does not parse, or a value
            ``weights_only`` loading would refuse.
    """
    path = Path(path)
    if not isinstance(payload, dict):
        raise ValueError(f"payload: expected a dict, got {type(payload).__name__}")
    payload = {"format": FORMAT, "version": VERSION, **payload}
    if payload["format"] != FORMAT or payload["version"] != VERSION:
        raise ValueError(f"payload: format {payload['format']!r} version {payload['version']!r};"
                         f" expected {FORMAT!r} version {VERSION}")
    for key in _REQUIRED:
        if key not in payload:
            raise ValueError(f"payload: missing {key!r} (required: {', '.join(_REQUIRED)})")
    if not isinstance(payload["model"], Mapping) or not all(
            isinstance(v, Tensor) for v in payload["model"].values()):
        raise ValueError("payload.model: expected a state dict of tensors")
    if not isinstance(payload["camera"], Mapping):
        raise ValueError("payload.camera: expected Camera.to_speed_dict()")
    try:
        Camera.from_speed_dict(dict(payload["camera"]))
    except ValueError as error:
        raise ValueError(f"payload.camera: {error}") from None
    checkpoint_network_config(payload, "payload")
    _check_loadable({k: v for k, v in payload.items() if k != "model"}, "payload")
    payload["model"] = dict(payload["model"])  # an OrderedDict loads too, but keep it plain
    payload = _canonical(payload)
    # Through a file object: torch names the archive's records after a path it is given (the
    # temporary file's random name), so the same payload would not give the same bytes.
    with atomic_path(path) as tmp, open(tmp, "wb") as stream:
        torch.save(payload, stream)
        stream.flush()
        os.fsync(stream.fileno())  # on disk before the rename: the file a --resume needs
    return path


def _canonical(value: Any) -> Any:
    """``value`` with every dict, list and tuple rebuilt and every string interned, so that
    the file's bytes follow its content alone. Pickle writes an object met twice as a
    reference to the first: a resumed run's optimizer keys ("lr", "betas", ...) come from the
    file it read, copies unlike the interned names of a fresh run's, and its last.pt differed
    from an uninterrupted run's in those bytes, every value equal."""
    if type(value) is str:
        return sys.intern(value)
    if type(value) is dict:  # plain containers only: subclasses (namedtuples) as they are
        return {_canonical(key): _canonical(item) for key, item in value.items()}
    if type(value) in (list, tuple):
        return type(value)(_canonical(item) for item in value)
    return value


def read_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Load a checkpoint written by :func:`write_checkpoint` (``weights_only=True``, on CPU).

    Raises:
        FileNotFoundError: ``checkpoint: no such file <path>``.
        ValueError: ``<path>: ...`` for a corrupt, random or hostile file, another format or a
            newer version, or weights holding NaN or infinities (a run that diverged).
    """
    path = Path(path)
    payload = load_torch_file(path, "checkpoint")
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        found = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise ValueError(f"{path}: not an sq_mitsuba checkpoint (format {found!r}, "
                         f"expected {FORMAT!r})")
    version = payload.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or not 1 <= version <= VERSION:
        raise ValueError(f"{path}: checkpoint version {version!r} is not one this sq_mitsuba "
                         f"reads (1 to {VERSION})")
    missing = [key for key in _REQUIRED if key not in payload]
    if missing:
        raise ValueError(f"{path}: checkpoint lacks {', '.join(map(repr, missing))}")
    if isinstance(payload["model"], Mapping):
        check_finite_tensors(payload["model"], str(path))
    return payload


def grown_generators(state: Mapping[str, Tensor], model: SuperquadricNet) -> dict[str, Tensor]:
    """``state`` with the generators' grouped layers grown to fit ``model`` (a network with
    ``existence``): M_f primitives in the file, M >= M_f in the network.

    Groups 0..M_f-1 are the file's. Convention: group m >= M_f copies group m mod M_f of the
    file (all three layers), its raw translation bias moved by :data:`GROWN_OFFSET` along a
    direction of its own (Fibonacci lattice): it starts next to the primitive it copies, so
    the grown network reads an image nearly as the file's did, and the two can part. A file
    without existence logits leaves the last layer's existence column as the network
    initialised it (every primitive present with probability 0.9). Anything else (another
    width, a network without ``existence``, fewer groups than the file) is left for the shape
    check to refuse.
    """
    state = dict(state)
    own = model.state_dict()
    if not model.config.existence or any(
            not isinstance(state.get(key), Tensor) or key not in own for key in _GROUPED):
        return state
    file_groups = {state[key].shape[0] for key in _GROUPED}
    groups = model.config.num_primitives
    if len(file_groups) != 1 or not 1 <= (file_count := file_groups.pop()) <= groups:
        return state
    grown: dict[str, Tensor] = {}
    for key in _GROUPED:
        value, target = state[key], own[key]
        extra = target.shape[-1] - value.shape[-1]  # 1: the file has no existence column
        last = key.startswith("sq_generator.layers.2.")
        if value.shape[1:-1] != target.shape[1:-1] or extra not in ((0, 1) if last else (0,)):
            return state
        result = target.detach().clone()
        result[:file_count, ..., :value.shape[-1]] = value.to(result.dtype)
        result[file_count:] = result[torch.arange(file_count, groups) % file_count]
        grown[key] = result
    if groups > file_count:  # the copies' raw translations (columns 5:8 of the last bias)
        offsets = GROWN_OFFSET * sphere_directions(groups - file_count)
        grown["sq_generator.layers.2.bias"][file_count:, 5:8] += offsets.to(
            grown["sq_generator.layers.2.bias"].dtype)
    return {**state, **grown}


def load_weights(model: SuperquadricNet, state: Any, where: str = "checkpoint", *,
                 partial: bool = False) -> None:
    """A checkpoint's state dict into ``model``, after checking that it fits.

    Checkpoints of the fixed-head layout are upgraded first. With ``partial`` the state may
    lack some of the network's entries (a head added since: it keeps its initialisation), and
    a network with ``existence`` may have more primitives than the file, or an existence
    column the file lacks (:func:`grown_generators`), and a file's shape decoder of another
    kind (``network.shape_decoder``) is left out; otherwise every entry must be there, of the
    network's shape.

    Raises:
        ValueError: ``<where>: weights do not fit config.network (...)`` naming the first
            missing, unexpected or differently shaped entry.
    """
    if not isinstance(state, Mapping):
        raise ValueError(f"{where}: 'model' must be a state dict")
    state = upgrade_state_dict(state)  # checkpoints of the fixed-head layout load too
    own = model.state_dict()
    if partial:
        state = grown_generators(state, model)
        # A file whose shape decoder is of another kind (slots against regions): the
        # network's decoder keeps its initialisation, everything else loads.
        state = {key: value for key, value in state.items()
                 if key in own or not key.startswith("sq_generator.")}
    missing = [] if partial else sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        raise ValueError(f"{where}: weights do not fit config.network ({len(missing)} missing, "
                         f"{len(unexpected)} unexpected; first: "
                         f"{(missing or unexpected)[0]})")
    for key in state:
        value = own[key]
        if not isinstance(state[key], Tensor) or state[key].shape != value.shape:
            got = tuple(state[key].shape) if isinstance(state[key], Tensor) else type(state[key])
            hint = ("; a network grows more primitives from a file only with "
                    "network.existence = true" if partial and key in _GROUPED
                    and not model.config.existence else "")
            raise ValueError(f"{where}: weights do not fit config.network ({key}: file {got}, "
                             f"network {tuple(value.shape)}){hint}")
    model.load_state_dict(state, strict=not partial)


def model_from_checkpoint(payload: Mapping[str, Any],
                          where: str = "checkpoint") -> tuple[SuperquadricNet, Camera]:
    """The network (eval mode, on the CPU) and dataset camera of a checkpoint dictionary.

    The ImageNet file named by ``config.network.pretrained`` is not read: the checkpoint's
    weights replace it.

    Raises:
        ValueError: ``<where>: ...`` when the config, weights or camera do not fit.
    """
    config = dataclasses.replace(checkpoint_network_config(payload, where), pretrained=None)
    model = SuperquadricNet(config)
    load_weights(model, payload["model"], where)
    try:
        camera = Camera.from_speed_dict(dict(payload["camera"]), f"{where}: camera")
    except TypeError as error:  # not a mapping (the ValueErrors name the field already)
        raise ValueError(f"{where}: camera: {error}") from None
    return model.eval(), camera


def checkpoint_baseline(payload: Mapping[str, Any],
                        where: str = "checkpoint") -> tuple[Tensor, Tensor, Tensor] | None:
    """The trivial baseline stored in a checkpoint, or None when it holds none.

    Returns:
        raw (1, M, 16), rotation (1, 3, 3), translation (1, 3), all float64.

    Raises:
        ValueError: ``<where>: baseline ...`` when the entry is malformed.
    """
    entry = payload.get("baseline")
    if entry is None:
        return None
    shapes = {"raw": (1, checkpoint_network_config(payload, where).num_primitives, 16),
              "rotation": (1, 3, 3), "translation": (1, 3)}
    if not isinstance(entry, Mapping) or set(entry) != set(shapes):
        raise ValueError(f"{where}: baseline must hold exactly {sorted(shapes)}")
    values = []
    for key, shape in shapes.items():
        value = entry[key]
        if not isinstance(value, Tensor) or tuple(value.shape) != shape:
            raise ValueError(f"{where}: baseline {key}: expected a tensor of shape {shape}")
        values.append(value.double())
    check_finite_tensors({f"baseline.{key}": value for key, value in entry.items()}, where)
    return values[0], values[1], values[2]
