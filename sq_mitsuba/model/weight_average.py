"""One network from several: the average of the weights of fine-tunes of one start.

Networks fine-tuned from the same start (here: the shipped model, grown by ``init_from``) stay
in one basin of the loss, where the mean of their weights is itself a good network and often
reads data unlike the training data better than any of them (Wortsman et al. 2022, "Model
soups"; Wortsman et al. 2022, "lo-fi": fine-tunes on separate shards, averaged). On this
project's held-out families the average of two runs trained on different spacecraft libraries
reads unseen spacecraft nearer than either run (eval/MODEL_CARD.md, "Averaged weights").

Convention: a uniform average of every floating-point tensor (weights and BatchNorm's running
statistics), computed in float64 and stored in the first checkpoint's dtype (files in half
and single precision average alike); integer tensors
(BatchNorm's step counters) are the first checkpoint's. Networks that did not share a start
have no common basin and average to nonsense; that cannot be read from the files, so only
what can is checked: one network configuration, one camera, the same tensors.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from sq_mitsuba.model.checkpoint import checkpoint_network_config

__all__ = ["average_checkpoints", "average_weights"]

#: Network fields that do not change the network a checkpoint holds: the ImageNet file the
#: encoder started from (replaced by the checkpoint's own weights when it loads).
_IRRELEVANT = ("pretrained",)


def average_weights(states: Sequence[Mapping[str, Tensor]], names: Sequence[str]
                    ) -> dict[str, Tensor]:
    """The uniform average of K state dicts of one network (module note: Convention).

    Args:
        states: K >= 1 state dicts with the same keys and shapes, each tensor floating-point
            in all of them or in none (floating dtypes may differ).
        names: K names for the errors (e.g. the files).

    Raises:
        ValueError: ``<name>: ...`` naming the first key whose presence, shape or dtype
            differs from the first state's.
    """
    if not states or len(states) != len(names):
        raise ValueError(f"expected one name per state dict and at least one, got "
                         f"{len(states)} states and {len(names)} names")
    first = states[0]
    for state, name in zip(states[1:], names[1:], strict=True):
        extra = sorted(set(state) - set(first))
        missing = sorted(set(first) - set(state))
        if extra or missing:
            key = (missing or extra)[0]
            raise ValueError(f"{name}: {'lacks' if missing else 'has an extra'} weight {key!r} "
                             f"({names[0]} {'has' if missing else 'has not'} it): not the "
                             "same network")
        for key, value in first.items():
            other = state[key]
            # Floating dtypes may differ (an exported file's half precision beside a
            # training checkpoint's float32): the mean is taken in float64.
            if other.shape != value.shape or other.is_floating_point() != \
                    value.is_floating_point():
                raise ValueError(f"{name}: weight {key!r} is {other.dtype} "
                                 f"{tuple(other.shape)}, {names[0]} has {value.dtype} "
                                 f"{tuple(value.shape)}: not the same network")
    averaged = {}
    for key, value in first.items():
        if value.is_floating_point():
            total = torch.stack([state[key].detach().cpu().double() for state in states])
            averaged[key] = total.mean(0).to(value.dtype)
        else:
            averaged[key] = value.detach().cpu().clone()
    return averaged


def average_checkpoints(payloads: Sequence[Mapping[str, Any]], names: Sequence[str]
                        ) -> dict[str, Any]:
    """A checkpoint dictionary whose weights average ``payloads``' (read by
    :func:`~sq_mitsuba.model.checkpoint.read_checkpoint`), with the first one's config and
    camera; no baseline (each payload's describes its own weights) and no training state.

    Raises:
        ValueError: ``<name>: ...`` for a payload whose network configuration (a field
            named), camera or weights differ from the first's.
    """
    first = payloads[0]
    # Every field filled: a file written before a field existed holds its default.
    network = dataclasses.asdict(checkpoint_network_config(first, names[0]))
    for payload, name in zip(payloads[1:], names[1:], strict=True):
        other = dataclasses.asdict(checkpoint_network_config(payload, name))
        for field, value in network.items():
            if field not in _IRRELEVANT and other[field] != value:
                raise ValueError(f"{name}: network.{field} is {other[field]!r}, "
                                 f"{names[0]} has {value!r}: only fine-tunes of one network "
                                 "can be averaged")
        if dict(payload["camera"]) != dict(first["camera"]):
            raise ValueError(f"{name}: its camera differs from {names[0]}'s: the networks "
                             "read images of different cameras")
    weights = average_weights([payload["model"] for payload in payloads], names)
    return {"format": first["format"], "version": first["version"], "config": first["config"],
            "model": weights, "camera": first["camera"]}

