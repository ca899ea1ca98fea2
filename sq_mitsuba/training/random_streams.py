"""Training's randomness: seeds of the independent random streams, and the global RNG states a
checkpoint saves.

Convention: every random draw of training is a pure function of (seed, stream, step, position
in the batch): the data order of epoch e from (seed, ``order``, e), an item's point samples and
augmentation from (seed, ``item``, step, j), the reprojection subset from (seed, ``subset``,
step, rank), the renderer's samples from (seed, ``render``, step), and the torch state of a
fresh run from (seed, ``torch``, rank). So a resumed run repeats an uninterrupted one's steps.
"""

from __future__ import annotations

import random
from typing import Any

import numpy as np
import torch

__all__ = ["STREAMS", "rng_state", "seed_globals", "seed_of", "set_rng_state"]

#: The random streams of training (see the module docstring).
STREAMS = {"order": 1, "item": 2, "subset": 3, "render": 4, "torch": 5}


def seed_of(*parts: int) -> int:
    """A 63-bit seed from integers (numpy's SeedSequence: well mixed, order sensitive)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, np.uint64)[0]
               >> 1)


def seed_globals(seed: int, rank: int) -> None:
    """A fresh run's global random states, from (``seed``, ``torch``, ``rank``): torch's, and
    numpy's legacy one and python's with it. Every checkpoint saves all three (unseeded, two
    runs of one seed saved different bytes; code training calls would draw differently)."""
    value = seed_of(seed, STREAMS["torch"], rank)
    torch.manual_seed(value)
    np.random.seed(value % 2**32)  # noqa: NPY002 (the legacy global state, on purpose)
    random.seed(value)


def rng_state() -> dict[str, Any]:
    """The global random states of this process (torch, numpy's legacy one, python's, CUDA's
    when initialised), as a checkpoint stores them."""
    # The legacy global numpy state: training draws from its own Generators, but code it
    # calls may use the global one, so it is saved and restored too.
    np_state = np.random.get_state()  # noqa: NPY002
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"name": np_state[0], "keys": torch.from_numpy(np_state[1].astype(np.int64)),
                  "pos": int(np_state[2]), "has_gauss": int(np_state[3]),
                  "cached_gaussian": float(np_state[4])},
        "python": random.getstate(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` returned."""
    torch.set_rng_state(state["torch"])
    numpy = state["numpy"]
    legacy = (numpy["name"], numpy["keys"].numpy().astype(np.uint32), numpy["pos"],
              numpy["has_gauss"], numpy["cached_gaussian"])
    np.random.set_state(legacy)  # noqa: NPY002
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():
        # One state per GPU of the run that saved it; a machine with fewer GPUs takes the first.
        for index, cuda_state in enumerate(state["cuda"][:torch.cuda.device_count()]):
            torch.cuda.set_rng_state(cuda_state, index)
