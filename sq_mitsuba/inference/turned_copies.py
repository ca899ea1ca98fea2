"""One reading from T in-plane turned copies of the images (``Predictor.predict(turns=T)``).

A roll of the camera about its optical axis is an in-plane turn of the image, so a network
read on the image turned by ``a`` reads the same spacecraft under the rotation ``Rz(a) R``.
:func:`turned_images` makes the T - 1 turned copies of a batch (the unturned one is the
caller's pass); :func:`reading_from_turns` maps every copy's output back to the unturned
image and combines them with the unturned reading into one :class:`Prediction`:

- the rotation from the product of the copies' distributions over the grid (each copy's
  cells turned back), and the hypotheses from that product;
- the shape, image position, depth and mask as means over the copies (positions and masks
  turned back first; the shape lives in the body frame and the depth along the optical axis,
  neither turns);
- with existence probabilities, every primitive's mean probability over the copies decides
  which primitives are kept, so that an image rolled by one of the turns keeps the same ones.

Convention: a point at offset q from the image centre (S / 2, S / 2) lies at ``Rz(a) q`` in
the copy turned by ``a`` (``geometry.image_turns.rotate_batch``), so ``q = Rz(a)^T p`` maps a
copy's point ``p`` back. Copies are batched copy-major: (T - 1) B images, copy k of image b
(turned by ``angles[k + 1]``) at ``k B + b``.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.image_turns import rotate_batch, turned_back_mask, z_rotation
from sq_mitsuba.geometry.rotation import matrix_to_quaternion
from sq_mitsuba.inference.prediction import Prediction
from sq_mitsuba.model.existence import gathered_primitives, kept_primitives
from sq_mitsuba.model.network import NetworkOutput
from sq_mitsuba.model.rotation_grid import (
    RotationGridPoseHead,
    rotation_hypotheses,
    turned_log_probabilities,
)

__all__ = ["check_turns_memory", "hypotheses_from_logits", "reading_from_turns", "turn_angles",
           "turned_images"]


def turn_angles(turns: int) -> Tensor:
    """(T,) float64 angles of T equal in-plane turns, the first 0 (the unturned image)."""
    return torch.arange(turns, dtype=torch.float64) * (2.0 * math.pi / turns)


#: Memory each turned copy of an image holds until the copies are read back (its input and
#: its outputs, the rotation distribution over the grid among them): measured 108 KB a copy
#: (360 turns of 4 and of 12 images, 2026-12-02).
TURN_COPY_BYTES = 128 * 1024


def check_turns_memory(images: int, turns: int) -> None:
    """One line naming ``turns`` when ``turns`` copies of ``images`` images need more memory
    than this process may use (:data:`TURN_COPY_BYTES` each copy but the unturned one)."""
    from sq_mitsuba.machine import available_memory, too_much_memory

    memory, need = available_memory(), images * (turns - 1) * TURN_COPY_BYTES
    if memory is not None and need > memory:
        copies = f"{turns} turned copies of {images} image{'s' if images != 1 else ''}"
        raise ValueError(too_much_memory(f"turns: {copies}", need, memory,
                                         "give fewer turns, or fewer images a call"))


def turned_images(images: Tensor, angles: Tensor) -> Tensor:
    """((T - 1) B, C, S, S) every image of ``images`` (B, C, S, S) turned by each of
    ``angles[1:]`` (T,), copy-major.

    Raises:
        ValueError: naming ``turns`` when the B (T - 1) copies need more memory than this
            process may use (``eval --batch-size 1024 --turns 360`` asked for about 40 GB).
    """
    batch = images.shape[0]
    check_turns_memory(batch, len(angles))
    copies = angles[1:].to(images).repeat_interleave(batch)
    return rotate_batch(images.repeat(len(angles) - 1, 1, 1, 1), copies)


def hypotheses_from_logits(head: torch.nn.Module, logits: Tensor | None, rotation: Tensor,
                           count: int) -> tuple[Tensor, Tensor]:
    """(B, K, 3, 3) rotation hypotheses, best first, and their (B, K) scores from a
    distribution head's (B, G) scores over its grid; for a regressing head (or ``logits``
    None) ``rotation`` (B, 3, 3) alone, scored 1. The best hypothesis is ``rotation``, the
    head's own (its argmax refined locally)."""
    if logits is None or not isinstance(head, RotationGridPoseHead):
        # A copy: the hypotheses must not share storage with the rotation they start from.
        return rotation[:, None].clone(), rotation.new_ones(rotation.shape[0], 1)
    grid = head.grid_rotations().to(rotation)
    rotations, scores = rotation_hypotheses(logits.clone(), grid, count)
    rotations[:, 0] = rotation
    return rotations, scores.to(rotation)


def reading_from_turns(prediction: Prediction, output: NetworkOutput, angles: Tensor,
                       cells: Tensor, head: RotationGridPoseHead, *, side: int, width: int,
                       height: int, min_existence: float, hypotheses: int) -> Prediction:
    """``prediction`` (the unturned pass) combined with ``output`` (the network's pass on
    :func:`turned_images` of the same images by ``angles``) into one reading (module
    docstring).

    Args:
        prediction: the unturned reading of B images of ``width`` x ``height`` px, with its
            rotation log-probabilities (a distribution head's).
        output: the network's output on the (T - 1) B turned copies, copy-major.
        angles: (T,) the turns, ``angles[0] == 0`` (:func:`turn_angles`).
        cells: ``model.rotation_grid.turned_cells`` of ``head``'s grid for ``angles``.
        head: the network's distribution head.
        side: S, the network's square input side (the copies' pixels are in it).
        width, height: the given images' size (the prediction's pixels are in it).
        min_existence: the mean existence probability from which a primitive is kept.
        hypotheses: K, rotation hypotheses per image.

    Returns:
        The combined :class:`Prediction`, its ``turns`` T.
    """
    turns, batch = len(angles), prediction.rotation.shape[0]

    def per_copy(value: Tensor) -> Tensor:  # (T - 1) B x ... -> (T - 1, B, ...)
        return value.clone().reshape(turns - 1, batch, *value.shape[1:])

    log_p = prediction.rotation_log_probabilities
    logits = torch.cat([log_p.to(output.rotation_logits)[None],
                        per_copy(output.rotation_logits)])
    combined = turned_log_probabilities(logits, cells).clone()
    with torch.inference_mode():
        rotation = head.rotation_from_logits(combined.to(output.rotation_logits))
    rotation = rotation.clone().to(prediction.rotation)
    rotations, scores = hypotheses_from_logits(head, combined, rotation, hypotheses)

    dtype = prediction.rotation.dtype
    unturned, existence, rows = prediction.assembly.params, None, None
    if prediction.existence is not None:  # every primitive's mean; the copies then decide
        unturned = prediction.primitives
        existence = torch.cat([prediction.existence[None],
                               per_copy(output.existence).to(prediction.existence)]).mean(0)
        rows = kept_primitives(existence, min_existence)
    params = torch.cat([unturned[None].to(dtype),
                        per_copy(output.assembly.params).to(dtype)]).mean(dim=0)
    kept, every = (params, None) if rows is None else (gathered_primitives(params, rows), params)

    scale = prediction.pixel.new_tensor([width / side, height / side])
    back = z_rotation(angles[1:]).to(output.pixel.device, dtype)[:, None, :2, :2]  # (T-1,1,2,2)
    offsets = per_copy(output.pixel).to(dtype) - 0.5 * side
    pixels = torch.cat([prediction.pixel[None] / scale,
                        (back.transpose(-1, -2) @ offsets[..., None])[..., 0] + 0.5 * side])
    pixel = pixels.mean(dim=0)
    depth = torch.cat([prediction.depth[None], per_copy(output.depth).to(dtype)]).mean(0)
    mask = prediction.mask
    if mask is not None and output.mask_logits is not None:
        mask = turned_back_mask(mask, output.mask_logits, angles[1:], height, width)
    network_camera = prediction.camera.rescaled(side, side)
    return replace(prediction, assembly=Assembly(kept), rotation=rotation,
                   quaternion=matrix_to_quaternion(rotation), pixel=pixel * scale,
                   depth=depth, translation=network_camera.unproject(pixel, depth),
                   mask=mask, rotation_hypotheses=rotations, rotation_scores=scores,
                   rotation_log_probabilities=combined.to(rotation), existence=existence,
                   primitive_index=rows, primitives=every, turns=turns)
