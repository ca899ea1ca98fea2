"""Images as the network takes them: checked, as float (B, C, H, W) in [0, 1], resized to the
network's square input; and the camera of images of a given size.

Convention:
    - Images are resized to the network's S x S input by antialiased bilinear interpolation
      (``align_corners=False``; a triangle filter widened by the shrink factor): the filter
      the dataset's reader applies to every training image (PIL's ``BILINEAR``; the two
      agree within one grey level), so the network reads an image as it read its training
      images. Pixel edges scale with the image, so the intrinsics follow by
      :meth:`~sq_mitsuba.geometry.camera.Camera.rescaled`.
    - A camera for another image size with the same aspect ratio is taken to have the same
      field of view and is rescaled to the images' size.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from sq_mitsuba.geometry.camera import Camera

__all__ = ["DEFAULT_MIN_TARGET", "array_to_tensor", "camera_for", "check_min_target",
           "neighbour_correlation", "prepare_images", "resize_images", "target_scores"]

# Relative aspect-ratio difference below which a camera of another size is rescaled.
_ASPECT_TOLERANCE = 1e-3

#: The target-present score from which an image counts as showing a target (see
#: :func:`target_scores`): the default ``min_target`` of the predictor and of ``predict``.
DEFAULT_MIN_TARGET = 0.92
# Linear ramps (value at score 0, value at score 1) of the target-present evidence; measured,
# see target_scores.
_CORRELATION_RAMP = (0.04, 0.10)  # neighbour_correlation
_BRIGHT_RAMP = (0.05, 0.15)  # 99.5th percentile of the grey image
_BORDER_RAMP = (0.05, 0.01)  # share of the image border the segmented mask covers
# Largest side at which neighbour_correlation measures an image (larger: block means).
_CORRELATION_SIDE = 512


def array_to_tensor(array: np.ndarray) -> Tensor:
    """``torch.from_numpy`` of a user's array, through a native, C-ordered copy only where
    torch cannot read it as it is: another byte order, a strided or flipped view
    (``images[..., ::-1]``), or (without a warning) read-only memory."""
    if not array.dtype.isnative or not array.flags.writeable or not array.flags.c_contiguous:
        array = np.array(array, dtype=array.dtype.newbyteorder("="), order="C")
    return torch.from_numpy(array)


def prepare_images(images: Tensor | np.ndarray, channels: int = 1) -> Tensor:
    """Check images and return them as float (B, C, H, W) in [0, 1].

    Args:
        images: (B, H, W) (when ``channels`` is 1) or (B, C, H, W); uint8 (0..255) or floating
            point in [0, 1]; a torch tensor or a numpy array (read-only arrays, such as
            ``np.asarray(PIL.Image.open(path))``, other byte orders and strided views such as
            ``images[..., ::-1]`` are copied; a tensor's autograd history is not followed).
            Each image between :data:`~sq_mitsuba.inputs.MIN_IMAGE_SIDE` px a side and
            :data:`~sq_mitsuba.inputs.MAX_IMAGE_PIXELS` pixels, the bounds of an image file
            (``sq-mitsuba predict``).
        channels: the C the network expects.

    Raises:
        ValueError: naming ``images``: wrong type, shape, size or dtype, a meta tensor, NaN
            or values outside [0, 1].
    """
    from sq_mitsuba.inputs import check_image_size

    from_numpy = isinstance(images, np.ndarray)
    if from_numpy:
        if images.dtype != np.uint8 and images.dtype.kind != "f":
            raise ValueError(f"images: expected uint8 or floating point, got {images.dtype}")
        images = array_to_tensor(images)
    if not isinstance(images, Tensor):
        raise ValueError(f"images: expected a torch.Tensor or numpy array, "
                         f"got {type(images).__name__}")
    if images.is_meta:
        raise ValueError("images: a meta tensor (no values); give the images themselves")
    images = images.detach()
    given = tuple(images.shape)
    expected = "(B, H, W) or (B, 1, H, W)" if channels == 1 else f"(B, {channels}, H, W)"
    axis = _colour_axis(given) if channels == 1 else None
    if axis is not None:
        raise ValueError(f"images: expected shape {expected} (grey), got {given}: colour "
                         f"channels along axis {axis}? give their mean, e.g. "
                         f"{_grey_hint(given, axis, from_numpy, images.dtype == torch.uint8)}")
    three = images.dim() == 3 and channels == 1 and images.shape[0] == 3
    if images.dim() == 3 and channels == 1:
        images = images[:, None]
    if images.dim() != 4 or images.shape[1] != channels or images.numel() == 0:
        raise ValueError(f"images: expected shape {expected}, got {given}")
    check_image_size(images.shape[-1], images.shape[-2], "images")
    check_batch_memory(images.shape)
    if three:
        _warn_if_channels(images[:, 0], from_numpy)
    if images.dtype == torch.uint8:
        return images.float() / 255.0
    if not images.is_floating_point():
        raise ValueError(f"images: expected uint8 or floating point, got {images.dtype}")
    if not bool(torch.isfinite(images).all()):
        raise ValueError("images: contains NaN or infinite values")
    low, high = float(images.amin()), float(images.amax())
    if low < 0.0 or high > 1.0:
        raise ValueError(f"images: float values must lie in [0, 1], got [{low:.4g}, {high:.4g}]"
                         " (divide uint8-range floats by 255)")
    return images


#: Memory a call to the network's pass holds for each pixel of the images given (float copies,
#: the resize and the turned copies' intermediates): measured 13 bytes on 8 images of 8192 x
#: 8192 px (7.1 GB), 2026-12-02.
BYTES_PER_INPUT_PIXEL = 16


def check_batch_memory(shape: tuple[int, ...] | torch.Size) -> None:
    """One line naming ``images`` when a batch of ``shape`` (B, C, H, W) needs more memory than
    this process may use (:data:`BYTES_PER_INPUT_PIXEL`); 16 images of 8192 px failed inside
    torch's allocator with a message naming neither."""
    from sq_mitsuba.machine import available_memory, too_much_memory

    memory = available_memory()
    batch, channels, height, width = shape
    need = batch * channels * height * width * BYTES_PER_INPUT_PIXEL
    if memory is not None and need > memory:
        fits = memory // (channels * height * width * BYTES_PER_INPUT_PIXEL)
        advice = (f"give at most {fits} such images a call" if fits else
                  "scale the images down")
        raise ValueError(too_much_memory(
            f"images: {batch} of {width} x {height} px ({BYTES_PER_INPUT_PIXEL} bytes a "
            "pixel)", need, memory, advice))


def _colour_axis(shape: tuple[int, ...]) -> int | None:
    """The axis of an RGB(A) image's channels in a shape no grey batch can have: the last of
    (H, W, C) or (B, H, W, C), or the second of (B, C, H, W), 3 or 4 long (a grey image is at
    least 8 px a side); None otherwise."""
    from sq_mitsuba.inputs import MIN_IMAGE_SIDE

    if len(shape) in (3, 4) and shape[-1] in (3, 4) and min(shape[-3:-1]) >= MIN_IMAGE_SIDE:
        return len(shape) - 1
    if len(shape) == 4 and shape[1] in (3, 4) and min(shape[-2:]) >= MIN_IMAGE_SIDE:
        return 1
    return None


def _grey_hint(shape: tuple[int, ...], axis: int, numpy: bool, uint8: bool,
               one: bool = False) -> str:
    """How to make grey images of a colour array of ``shape`` (channels along ``axis``),
    as code for its type: numpy or torch, uint8 scaled to [0, 1], alpha left out, one
    image given its batch axis (``one``, or (H, W, C))."""
    channels = shape[axis]
    pick = "" if channels == 3 else ("[..., :3]" if axis == len(shape) - 1 else
                                     f"[{':, ' * axis}:3]")
    mean = f"mean(axis={axis})" if numpy else f"float().mean({axis})" if uint8 else \
        f"mean({axis})"
    batch = "[None]" if one or (len(shape) == 3 and axis == 2) else ""
    return f"images{pick}.{mean}{batch}{' / 255' if uint8 else ''}"


def _warn_if_channels(images: Tensor, numpy: bool) -> None:
    """Warn where three grey images (3, H, W) look like one colour image's channels (C, H, W):
    the same picture in each (correlation above 0.995 between every pair; a grey render's
    channels are equal). Three frames of a pass are not that alike: neighbouring frames of
    the held-out passes correlate up to 0.985, so a colour photo whose channels differ more
    goes unwarned (the docs say (B, H, W) is B grey images)."""
    import warnings

    step = max(1, max(images.shape[-2:]) // 128)  # a sample of pixels, a few kB
    flat = images[:, ::step, ::step].reshape(3, -1).float()
    flat = flat - flat.mean(dim=1, keepdim=True)
    norms = flat.norm(dim=1)
    if bool((norms <= 0).any()):
        return
    correlation = (flat @ flat.T) / (norms[:, None] * norms[None, :])
    if float(correlation.min()) > 0.995:
        hint = _grey_hint(tuple(images.shape), 0, numpy, images.dtype == torch.uint8, True)
        warnings.warn(f"images: 3 images alike as the channels of one colour image (shape "
                      f"{tuple(images.shape)} read as (B, H, W): 3 grey images); for one colour "
                      f"image give its mean over the channels, e.g. {hint}",
                      stacklevel=5)  # prepare_images, the predictor, its caller's call


def resize_images(images: Tensor, size: int) -> Tensor:
    """(B, C, H, W) -> (B, C, size, size), resampled as the module docstring says."""
    if tuple(images.shape[-2:]) == (size, size):
        return images
    # Not "area": a box filter differs from the training images' triangle filter by up to
    # 16-63 grey levels at edges (256 px -> 96-224), a shift the network never saw.
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False,
                         antialias=True)


def check_camera(camera: Camera) -> Camera:
    """``camera`` itself; refused, in one line naming ``camera``, for intrinsics no camera
    has, as a camera file's are (:func:`sq_mitsuba.inputs.check_camera_intrinsics`): a
    principal point more than a quarter of the image from its centre, or a field of view
    outside [``MIN_FIELD_OF_VIEW_DEG``, ``MAX_FIELD_OF_VIEW_DEG``] (:mod:`sq_mitsuba.inputs`'s
    rules, in the words of a Camera object). Poses read through such a camera came back
    infinite or millions of metres off, not as an error."""
    from sq_mitsuba.inputs import (
        MAX_FIELD_OF_VIEW_DEG,
        MIN_FIELD_OF_VIEW_DEG,
        field_of_view_deg,
        principal_point_off_centre,
    )

    if not isinstance(camera, Camera):
        raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
    width, height = camera.width, camera.height
    if principal_point_off_centre(width, height, camera.cx, camera.cy):
        raise ValueError(f"camera: the principal point ({camera.cx:g}, {camera.cy:g}) is far "
                         f"from the centre ({width / 2:g}, {height / 2:g}) of its {width} x "
                         f"{height} px images (intrinsics for another image size?)")
    for axis, size, focal, centre in (("x", width, camera.fx, camera.cx),
                                      ("y", height, camera.fy, camera.cy)):
        fov = field_of_view_deg(size, focal, centre)
        if not MIN_FIELD_OF_VIEW_DEG <= fov < MAX_FIELD_OF_VIEW_DEG:
            raise ValueError(f"camera: f{axis} = {focal:g} gives a {fov:.3g} deg field of view "
                             f"across {axis} over {size} px; expected {MIN_FIELD_OF_VIEW_DEG:g} "
                             f"to {MAX_FIELD_OF_VIEW_DEG:g} deg")
    return camera


def camera_for(camera: Camera, width: int, height: int) -> Camera:
    """``camera`` for ``width`` x ``height`` images: itself, or rescaled (same aspect ratio).

    Raises:
        ValueError: naming ``camera`` when its aspect ratio differs from the images'.
    """
    if not isinstance(camera, Camera):
        raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
    if (camera.width, camera.height) == (width, height):
        return camera
    if abs(camera.width * height / (camera.height * width) - 1.0) > _ASPECT_TOLERANCE:
        raise ValueError(f"camera: is for {camera.width} x {camera.height} images, the images are "
                         f"{width} x {height} (another aspect ratio); pass their camera")
    return camera.rescaled(width, height)


def _ramp(value: Tensor, zero: float, one: float) -> Tensor:
    """``value`` mapped linearly from ``zero`` (0) to ``one`` (1), clipped to [0, 1]."""
    return ((value - zero) / (one - zero)).clamp(0.0, 1.0)


def neighbour_correlation(images: Tensor) -> Tensor:
    """(B,) the correlation of neighbouring pixels of images (B, C, H, W) (grey, horizontal
    and vertical pairs together), or 1 for an image of one grey level (no noise to measure).

    A picture of anything has strongly correlated neighbours (a space scene: 0.2 to 0.97,
    lower for a grainy render or a barely lit target); per-pixel noise has none (|r| < 0.04).
    An image larger than 512 px is measured on its means over k x k blocks (k the smallest
    integer that brings it to 512 px or less; no taller or wider than the image), which keep
    both so.
    """
    grey = images.detach().float().mean(dim=1, keepdim=True)
    height, width = grey.shape[-2:]
    factor = -(-max(height, width) // _CORRELATION_SIDE)
    if factor > 1:  # block means: white noise stays white, a picture stays a picture
        block = (min(factor, height), min(factor, width))  # a strip keeps one row of blocks
        grey = F.avg_pool2d(grey, block, stride=block, ceil_mode=False)
    grey = grey[:, 0]
    first = torch.cat([grey[..., :, :-1].flatten(1), grey[..., :-1, :].flatten(1)], dim=1)
    second = torch.cat([grey[..., :, 1:].flatten(1), grey[..., 1:, :].flatten(1)], dim=1)
    first = first - first.mean(dim=1, keepdim=True)
    second = second - second.mean(dim=1, keepdim=True)
    scale = (first.square().mean(dim=1) * second.square().mean(dim=1)).sqrt()
    covariance = (first * second).mean(dim=1)
    flat = scale <= 1e-12
    return torch.where(flat, torch.ones_like(scale), covariance / scale.clamp_min(1e-12))


def target_scores(network_input: Tensor, mask_logits: Tensor | None,
                  images: Tensor | None = None) -> Tensor:
    """(B,) the target-present score in [0, 1]: how sure the predictor is that each image
    shows a target (a spacecraft) at all.

    Args:
        network_input: (B, C, S, S) the images as the network takes them.
        mask_logits: (B, 1, h, w) the network's mask head's logits, or None without one.
        images: (B, C, H, W) the images at their own size (default: ``network_input``), for
            the noise test.

    The score is the weaker of two pieces of evidence:

    - the target's: with a mask head, its probability at its most confident pixel; without
      one, the threshold segmentation of the network's input
      (:func:`~sq_mitsuba.data.segmentation.segment_target`), scored by the weaker of its
      brightness (the 99.5th percentile: 0 up to 0.05, 1 from 0.15) and of how little of
      the image border its mask covers (1 up to 1 %, 0 from 5 %: a target lies within the
      image, the Earth's limb and noise cross the border); 0 where nothing is segmented;
    - that the image is a picture and not noise: its :func:`neighbour_correlation` at its
      own size, 0 up to 0.04, 1 from 0.10 (the mask head never saw noise, and fires on it).

    Convention: an image shows a target when its score is at least ``min_target``
    (:data:`DEFAULT_MIN_TARGET`, 0.92); below it, nothing is fitted to it. 0.92 is the
    midpoint in log-odds between the highest score of an image without a target (0.889, the
    Earth alone) and the lowest of a spacecraft (0.944, before the Earth) measured below.

    Measured (the project's renderer, :class:`~sq_mitsuba.render.space.SpaceScene`: 20
    spacecraft of catalogue seed 11, which the shipped model never saw, in the default space
    scene; "alone" is the same frame with the target moved behind the camera): the lowest and
    highest score, and the share at or above 0.92, of the shipped model (96 px input, mask
    head) on images rendered as it was trained (96 px, 16 samples per pixel) and at 256 px,
    16 spp (then downsampled: finer), and of the segmentation (a network without a mask head)
    on the 256 px images at 64 px:

    =======================================  ===  ================  ================  =========
    images                                     n  head, 96 px       head, 256 px      segment.
    =======================================  ===  ================  ================  =========
    spacecraft, the Earth out of view         60  0.990-1 (100%)    0.987-1 (100%)    1 (100%)
    spacecraft before the Earth               60  0.974-1 (100%)    0.944-1 (100%)    0-1 (28%)
    spacecraft in eclipse (earthshine only)   40  0.035-1 (68%)     0.046-1 (75%)     0-1 (8%)
    spacecraft 2.5-4 x farther than trained   72                    0.520-1 (96%)     0-1 (42%)
    the Earth alone                           60  0.002-0.889 (0%)  0.001-0.842 (0%)  0 (0%)
    stars alone                               20  0.004-0.180 (0%)  0.007-0.261 (0%)  0 (0%)
    =======================================  ===  ================  ================  =========

    Black and one-grey images (6, up to 1,024 px) score at most 0.260. Noise (256 images:
    uniform, 5 levels; Gaussian, means 0 to 0.5, sd 0.02 to 0.5; sparse bright pixels; each
    at 48 to 512 px) scores 0: alone, the mask head's most confident pixel exceeds 0.9 on 71
    of them (up to 0.997), but their neighbour correlation is at most 0.037, against 0.18 for
    the grainiest spacecraft image (64 px, 4 spp) and 0.45 at 96 px, 16 spp.

    So every spacecraft rendered as in training is a target and nothing else is; a much
    farther spacecraft may fall below (3 of 72), and so do a third of the eclipsed ones
    (barely lit). Limits: the mask head also fires on a grainy Earth (rendered at 64 px with
    4 spp, 16 of 60 Earth-alone frames score 0.92 or more); without a mask head the
    segmentation cannot tell a target before the Earth from the Earth (both cross the
    border): such images score 0.
    """
    count = network_input.shape[0]
    picture = _ramp(neighbour_correlation(network_input if images is None else images),
                    *_CORRELATION_RAMP).cpu()
    if mask_logits is not None:
        evidence = mask_logits.detach().float().flatten(1).amax(dim=1).sigmoid().cpu()
    else:
        from sq_mitsuba.data.segmentation import segment_target

        evidence = torch.zeros(count)
        grey = network_input.detach().float().mean(dim=1).cpu()
        for k in range(count):
            image = grey[k].double().numpy()
            try:
                mask = segment_target(image).mask
            except ValueError:  # nothing bright: no target
                continue
            border = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]]).mean()
            bright = float(np.percentile(image, 99.5))
            evidence[k] = min(float(_ramp(torch.tensor(bright), *_BRIGHT_RAMP)),
                              float(_ramp(torch.tensor(border), *_BORDER_RAMP)))
    return torch.minimum(evidence, picture)


def check_min_target(min_target: float, name: str = "min_target") -> float:
    """``min_target`` (or another threshold, ``name``) as a float, or a one-line
    ``ValueError`` naming it unless in [0, 1]."""
    if isinstance(min_target, bool) or not isinstance(min_target, int | float) \
            or not 0.0 <= min_target <= 1.0:
        raise ValueError(f"{name}: expected a number in [0, 1], got {min_target!r}")
    return float(min_target)
