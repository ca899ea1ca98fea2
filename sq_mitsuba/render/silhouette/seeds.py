"""The silhouette renderers' sample seeds: one rule for every renderer and its callers.

A render's samples are seeded by ``base + CALL_SEED_STRIDE * (2 * call + backward) +
ITEM_SEED_STRIDE * item`` (32 bits): successive calls, their backward passes and the items of
a batch draw different samples, and a distributed training step reseeds each process at
``ITEM_SEED_STRIDE * (its first item in the global batch)``, so that item j of a batch draws
the same samples whatever the number of processes (training's bit-equality across DDP ranks
rests on the two sides using these constants).
"""

from __future__ import annotations

CALL_SEED_STRIDE = 0x9E3779B1
"""Seed step between successive calls (the golden-ratio step: decorrelates neighbours)."""

ITEM_SEED_STRIDE = 7919
"""Seed step between the items of one call (a prime)."""


def render_seed(base: int, call: int, item: int = 0, backward: bool = False,
                salt: int = 0) -> int:
    """The 32-bit seed of one render: item ``item`` of call ``call`` (its backward pass with
    ``backward``), from the renderer's ``base`` seed; ``salt`` sets a renderer's samples apart
    from another's at the same seed (the tiled renderer's)."""
    return (base + CALL_SEED_STRIDE * (2 * call + int(backward)) + ITEM_SEED_STRIDE * item
            + salt) & 0xFFFFFFFF
