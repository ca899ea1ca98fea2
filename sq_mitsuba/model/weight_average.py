"""One network from several: the average of the weights of fine-tunes of one start.

Networks fine-tuned from the same start (here: the archetype model, grown by ``init_from``) stay
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

The start itself can join the average (:func:`fine_tune_start`, ``start_share``): weights part
way back from the fine-tunes to the network they began from, which keep more of what the start
read well (Wortsman et al. 2022, "Robust fine-tuning of zero-shot models", WiSE-FT, where
the mix read shifted data better than either end). Here the start is the archetype model, good
on its own archetypes, the fine-tunes read unseen families better, and a quarter of the way
keeps the first and about half of the second: a trade, not a gain on both; the shipped model
is made so (eval/MODEL_CARD.md, "Back towards the start").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from sq_mitsuba.geometry.assembly import NUM_PARAMS
from sq_mitsuba.model.checkpoint import checkpoint_network_config, load_weights
from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

__all__ = ["average_checkpoints", "average_weights", "existence_keys", "fine_tune_start"]

#: Network fields that do not change the network a checkpoint holds: the ImageNet file the
#: encoder started from (replaced by the checkpoint's own weights when it loads).
_IRRELEVANT = ("pretrained",)


def average_weights(states: Sequence[Mapping[str, Tensor]], names: Sequence[str],
                    coefficients: Sequence[float] | None = None) -> dict[str, Tensor]:
    """The uniform average of K state dicts of one network (module note: Convention).

    Args:
        states: K >= 1 state dicts with the same keys and shapes, each tensor floating-point
            in all of them or in none (floating dtypes may differ).
        names: K names for the errors (e.g. the files).
        coefficients: K weights summing to 1 for a weighted mean instead (one rounding, in
            float64, to the first state's dtypes).

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
    if coefficients is not None and (len(coefficients) != len(states)
                                     or abs(sum(coefficients) - 1.0) > 1e-9):
        raise ValueError(f"expected {len(states)} coefficients summing to 1, got "
                         f"{list(coefficients)}")
    weight = None if coefficients is None else torch.tensor(coefficients, dtype=torch.float64)
    averaged = {}
    for key, value in first.items():
        if value.is_floating_point():
            total = torch.stack([state[key].detach().cpu().double() for state in states])
            mixed = total.mean(0) if weight is None else torch.tensordot(weight, total, dims=1)
            averaged[key] = mixed.to(value.dtype)
        else:
            averaged[key] = value.detach().cpu().clone()
    return averaged


def fine_tune_start(start: Mapping[str, Tensor], network: NetworkConfig, seed: int,
                    where: str) -> dict[str, Tensor]:
    """The weights a fine-tune began from: the network of ``network`` built after
    ``torch.manual_seed(seed)``, then ``start``'s weights loaded into it as training's
    ``init_from`` loads them (layers the file lacks keep that seeded initialisation; a file
    of fewer primitives grows, :func:`~sq_mitsuba.model.checkpoint.load_weights`).

    Args:
        start: the state dict of the file the fine-tunes name in ``init_from``.
        network: their network configuration.
        seed: their config's ``seed`` (it draws the layers the file lacks).
        where: names the start in errors.

    Returns:
        The state dict (CPU, float32 weights), key for key a fine-tune's.

    Raises:
        ValueError: ``<where>: weights do not fit config.network (...)``.
    """
    bare = dataclasses.replace(network, pretrained=None)
    with torch.random.fork_rng():
        encoder = [k for k in SuperquadricNet(bare).state_dict() if k.startswith("encoder.")]
    if all(key in start for key in encoder):
        # The start replaces every ImageNet weight: their file, perhaps on another machine
        # (the one that trained the fine-tunes), is not read (loading it draws no random
        # numbers, so the other layers are drawn alike).
        network = bare
    torch.manual_seed(seed)
    model = SuperquadricNet(network)
    load_weights(model, start, where, partial=True)
    return {key: value.detach().clone() for key, value in model.state_dict().items()}


def existence_keys(state: Mapping[str, Tensor]) -> list[str]:
    """The tensors that hold the existence logits of a network with ``network.existence``:
    the last layer of the primitives' generators (weight (M, hidden, 17) and bias (M, 17),
    the logit last of the 17 outputs); [] for a network without them."""
    layers = sorted({int(key.split(".")[2]) for key in state
                     if key.startswith("sq_generator.layers.")})
    if not layers:
        return []
    last = [f"sq_generator.layers.{layers[-1]}.{part}" for part in ("weight", "bias")]
    keys = [key for key in last if key in state]
    return keys if keys and all(state[key].shape[-1] == NUM_PARAMS + 1 for key in keys) else []


def average_checkpoints(payloads: Sequence[Mapping[str, Any]], names: Sequence[str],
                        start: tuple[Mapping[str, Any], str] | None = None,
                        start_share: float = 0.0,
                        keep_existence: bool = False) -> dict[str, Any]:
    """A checkpoint dictionary whose weights average ``payloads``' (read by
    :func:`~sq_mitsuba.model.checkpoint.read_checkpoint`), with the first one's config and
    camera; no baseline (each payload's describes its own weights) and no training state.

    Args:
        payloads, names: the checkpoints (one or more) and their names for the errors.
        start: (the checkpoint the payloads were fine-tuned from, its name), or None.
        start_share: with ``start``, the weights are ``start_share`` x the start (grown to
            the payloads' network by :func:`fine_tune_start` with their seed) plus
            ``1 - start_share`` x the payloads' average.
        keep_existence: with ``start``, the existence column of the generators' last layer
            (its weights and bias: :func:`existence_keys`) is the payloads' average alone,
            not mixed back: a start grown from a network without existence holds every
            primitive at probability 0.9 (``INITIAL_EXISTENCE``), so its share would keep
            every primitive the fine-tunes learned to switch off (eval/MODEL_CARD.md, PARS-E).

    Raises:
        ValueError: ``<name>: ...`` for a payload whose network configuration (a field
            named), camera, seed (with ``start``) or weights differ from the first's, or a
            start whose weights do not fit the network.
    """
    if start is not None and not 0.0 <= start_share < 1.0:
        raise ValueError(f"start_share: expected a share in [0, 1), got {start_share}")
    if keep_existence and start is None:
        raise ValueError("keep_existence: only with a start (without one the logits are the "
                         "average already)")
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
    if start is None:
        weights = average_weights([payload["model"] for payload in payloads], names)
    else:
        seeds = [payload["config"].get("seed") for payload in payloads]
        for seed, name in zip(seeds[1:], names[1:], strict=True):
            if seed != seeds[0]:
                raise ValueError(f"{name}: config.seed is {seed!r}, {names[0]} has {seeds[0]!r}: "
                                 "fine-tunes of one start share the seed that drew its new "
                                 "layers")
        if not isinstance(seeds[0], int):
            raise ValueError(f"{names[0]}: config.seed is {seeds[0]!r}, expected the run's "
                             "integer seed (it drew the start's new layers)")
        network_config = checkpoint_network_config(first, names[0])
        if keep_existence and not (network_config.existence
                                   and network_config.shape_decoder == "slots"):
            raise ValueError(f"{names[0]}: keep_existence needs a network whose slots carry "
                             "existence logits (network.existence, shape_decoder 'slots')")
        begun = fine_tune_start(start[0]["model"], network_config, seeds[0], start[1])
        # The start last: the first fine-tune gives the dtypes and the integer counters.
        shares = [(1.0 - start_share) / len(payloads)] * len(payloads) + [start_share]
        weights = average_weights([payload["model"] for payload in payloads] + [begun],
                                  [*names, start[1]], shares)
        if keep_existence:  # the existence column of the last layer: the runs' alone
            keys = existence_keys(weights)
            runs = average_weights([{key: payload["model"][key] for key in keys}
                                    for payload in payloads], names)
            for key in keys:
                weights[key][..., NUM_PARAMS] = runs[key][..., NUM_PARAMS]
    return {"format": first["format"], "version": first["version"], "config": first["config"],
            "model": weights, "camera": first["camera"]}

