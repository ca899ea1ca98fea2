"""Training augmentation that keeps every label exact: batched torch, per-item parameters.

Five kinds, each switched on separately in :class:`AugmentConfig` (all off in the paper's
configurations) and applied to an item with probability ``probability``:

- ``rotation``: in-plane rotation of the image and the mask about the principal point by an
  angle theta, with the pose rotated to match: ``R' = Rz R``, ``t' = Rz t``, where ``Rz`` turns
  the camera frame by theta about its optical axis (z). The body frame, and so the shape
  labels (surface and occupancy points), are untouched.
- ``brightness``: exposure jitter, the image multiplied by a factor (clipped to [0, 1]).
- ``gamma``: ``image ** gamma``.
- ``blur``: Gaussian blur of a random width (a slightly defocused or moving camera).
- ``noise``: additive Gaussian sensor noise of a random standard deviation (clipped), last, as
  a sensor adds it after the optics.

Only the rotation moves pixels of the mask; the photometric kinds change the image alone, so
the mask and the pose stay exact.

Convention: the rotation is exact only when the principal point is the image centre and ``fx =
fy`` (square pixels), as for the project's default camera and SPEED's: then turning the camera
about its optical axis maps pixel offsets from the centre by the same 2D rotation.
:func:`~sq_mitsuba.geometry.image_turns.check_rotation_exact` refuses other cameras (the
photometric kinds work with any). A positive theta turns image content clockwise on screen (x
right, y down): a point at pixel offset (dx, dy) from the centre moves to ``(cos dx - sin dy,
sin dx + cos dy)``. Parts of the image that leave the frame are lost and the corners that enter
it are black (empty space), and the mask is cropped alike, exactly as a render at the new pose
would be. Resampling is bilinear; the rotated mask is a coverage fraction in [0, 1] at object
edges.

Every random draw of an item comes from its own ``numpy.random.Generator``, so an item is
augmented the same whatever batch or process it lands in (distributed training splits batches).

Convention: the images may live on a GPU. The parameters are drawn on the host, and every
decision that depends on them (which items turn, whether any blurs, the blur's width) is taken
from the host's copy, so augmenting a batch on a GPU never waits for it; the parameters (and the
noise, drawn on the host from each item's seed) reach the device in asynchronous copies. On the
CPU the results are the same, bit for bit, as one item at a time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from sq_mitsuba.checks import check_tensor
from sq_mitsuba.config import in_range
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.image_turns import check_rotation_exact, rotate_batch, z_rotation

__all__ = ["KINDS", "AugmentConfig", "AugmentDraws", "apply_augmentation", "augment_batch",
           "check_augment_inputs", "draw_augmentation", "to_device"]

#: The kinds of augmentation, in the order they are applied.
KINDS = ("rotation", "brightness", "gamma", "blur", "noise")


@dataclass(frozen=True)
class AugmentConfig:
    """Label-preserving augmentation of training images (all off: the paper trains without)."""

    rotation: bool = False
    "In-plane rotation about the principal point, the pose rotated to match."
    max_rotation_deg: float = in_range(0, 180, default=180.0)
    "Rotation angles are uniform in [-max_rotation_deg, max_rotation_deg]."
    brightness: bool = False
    "Exposure jitter: the image multiplied by a factor."
    brightness_range: tuple[float, float] = (0.6, 1.5)
    "Exposure factors are log-uniform in this range."
    gamma: bool = False
    "Gamma jitter: image ** gamma."
    gamma_range: tuple[float, float] = (0.7, 1.4)
    "Gamma values are log-uniform in this range."
    noise: bool = False
    "Additive Gaussian sensor noise."
    noise_std: tuple[float, float] = (0.0, 0.03)
    "The noise standard deviation (image units) is uniform in this range."
    blur: bool = False
    "Gaussian blur."
    blur_sigma: tuple[float, float] = (0.3, 1.2)
    "The blur's standard deviation in pixels of the network input is uniform in this range."
    probability: float = in_range(0, 1, default=0.5)
    "Probability that a switched-on kind is applied to an item."

    def __post_init__(self) -> None:
        for name, low_limit in (("brightness_range", 0.0), ("gamma_range", 0.0),
                                ("noise_std", None), ("blur_sigma", None)):
            low, high = getattr(self, name)
            if low > high:
                raise ValueError(f"{name}: low {low} is above high {high}")
            if low_limit is not None and low <= low_limit:
                raise ValueError(f"{name}: values must be > 0, got {low}")
            if low < 0:
                raise ValueError(f"{name}: values must be >= 0, got {low}")

    @property
    def enabled(self) -> bool:
        """Whether any kind is switched on (and can fire)."""
        return self.probability > 0 and any(getattr(self, kind) for kind in KINDS)


def to_device(value: np.ndarray | Tensor, device: torch.device) -> Tensor:
    """A host array or tensor on ``device``: on a GPU through pinned memory, copied without
    waiting (a copy from pageable memory would wait for the device; a tensor already pinned,
    e.g. by the prefetch, is not pinned again); on the CPU as it is."""
    tensor = torch.as_tensor(value)
    if device.type != "cuda":
        return tensor.to(device)
    if not tensor.is_pinned():
        tensor = tensor.pin_memory()
    return tensor.to(device, non_blocking=True)


def _gaussian_blur(images: Tensor, sigmas: Tensor, largest: float | None = None) -> Tensor:
    """Per-item Gaussian blur (reflect padding) of images (B, C, H, W) with widths (B,) px;
    items with sigma 0 are returned unchanged. ``largest``: the largest width, when known on
    the host (else read from ``sigmas``)."""
    batch, channels = images.shape[:2]
    largest = float(sigmas.max()) if largest is None else largest
    radius = max(1, math.ceil(3 * largest))
    offsets = torch.arange(-radius, radius + 1, dtype=images.dtype, device=images.device)
    safe = sigmas.clamp_min(1e-6).to(images.dtype)[:, None]
    kernel = torch.exp(-0.5 * (offsets[None] / safe) ** 2)
    kernel = kernel / kernel.sum(-1, keepdim=True)  # (B, K)
    identity = (offsets == 0).to(images.dtype)[None].expand_as(kernel)
    kernel = torch.where((sigmas > 0)[:, None], kernel, identity)
    kernel = kernel.repeat_interleave(channels, dim=0)  # (B * C, K)
    flat = images.reshape(1, batch * channels, *images.shape[2:])
    flat = F.pad(flat, (radius, radius, radius, radius), mode="reflect")
    flat = F.conv2d(flat, kernel[:, None, None, :], groups=batch * channels)
    flat = F.conv2d(flat, kernel[:, None, :, None], groups=batch * channels)
    return flat.reshape(images.shape)


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return math.exp(rng.uniform(math.log(bounds[0]), math.log(bounds[1])))


@dataclass
class AugmentDraws:
    """Every item's augmentation parameters, drawn on the host (:func:`draw_augmentation`);
    applied on any device by :func:`apply_augmentation`."""

    params: dict[str, np.ndarray]
    "Each kind's parameter per item (B,), float64; neutral where the kind did not fire."
    table: Tensor
    "(kinds, B) float64: the parameters in :data:`KINDS` order, what travels to the device."
    noise: Tensor | None
    "(B, C, S, S) additive noise in the images' dtype (zero for items without), or None."

    def pinned(self) -> AugmentDraws:
        """The same draws in pinned host memory (copies to a GPU that do not wait)."""
        return AugmentDraws(self.params, self.table.pin_memory(),
                            None if self.noise is None else self.noise.pin_memory())


def draw_augmentation(config: AugmentConfig, generators: list[np.random.Generator],
                      image_shape: tuple[int, ...], dtype: torch.dtype = torch.float32
                      ) -> AugmentDraws:
    """Draw every item's parameters and noise on the host, from each item's generator.

    Args:
        config: which kinds and how strong.
        generators: one numpy Generator per item.
        image_shape: (B, C, S, S) of the images the draws will augment.
        dtype: the images' dtype (the noise is drawn in it).
    """
    batch = image_shape[0]
    if len(generators) != batch:
        raise ValueError(f"generators: expected {batch} (one per item), got {len(generators)}")
    # Every item's parameters first, in a fixed order per item, so that the draws of one kind
    # do not depend on whether another kind fired.
    p = config.probability
    params = {kind: np.zeros(batch) for kind in KINDS}
    noise_seeds = np.zeros(batch, dtype=np.int64)
    neutral = {"rotation": 0.0, "brightness": 1.0, "gamma": 1.0, "noise": 0.0, "blur": 0.0}
    for i, rng in enumerate(generators):
        fire = rng.random(len(KINDS)) < p
        angle = math.radians(rng.uniform(-config.max_rotation_deg, config.max_rotation_deg))
        factor = _log_uniform(rng, config.brightness_range)
        gamma = _log_uniform(rng, config.gamma_range)
        std = rng.uniform(*config.noise_std)
        sigma = rng.uniform(*config.blur_sigma)
        noise_seeds[i] = int(rng.integers(0, 2**62))
        values = {"rotation": angle, "brightness": factor, "gamma": gamma, "noise": std,
                  "blur": sigma}
        for k, kind in enumerate(KINDS):
            on = getattr(config, kind) and bool(fire[k])
            params[kind][i] = values[kind] if on else neutral[kind]
    stds = params["noise"]
    noise = None
    if bool((stds > 0).any()):
        # Each item's noise from its own seed: the same noise on every device.
        noise = torch.zeros(image_shape, dtype=dtype)
        for i in np.flatnonzero(stds > 0):
            gen = torch.Generator().manual_seed(int(noise_seeds[i]))
            noise[i] = float(stds[i]) * torch.randn(image_shape[1:], generator=gen, dtype=dtype)
    table = torch.from_numpy(np.stack([params[kind] for kind in KINDS]))  # (kinds, B)
    return AugmentDraws(params, table, noise)


def apply_augmentation(images: Tensor, masks: Tensor, rotations: Tensor, translations: Tensor,
                       draws: AugmentDraws, camera: Camera | None = None
                       ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Apply host-drawn parameters (:func:`draw_augmentation`) to a batch on its device;
    shapes as :func:`augment_batch`. Never waits for the device: every decision is taken from
    the host's copy of the parameters. ``camera`` is checked with
    :func:`check_rotation_exact` where an item turns."""
    check_augment_inputs(images, masks, rotations, translations)
    if draws.table.shape[-1] != images.shape[0]:
        raise ValueError(f"draws: made for {draws.table.shape[-1]} items, the batch has "
                         f"{images.shape[0]}")
    if bool((draws.params["rotation"] != 0).any()) and camera is not None:
        check_rotation_exact(camera)
    return _apply(images, masks, rotations, translations, draws)


def _apply(images: Tensor, masks: Tensor, rotations: Tensor, translations: Tensor,
           draws: AugmentDraws) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`apply_augmentation` on inputs already checked."""
    params = draws.params
    dtype, device = images.dtype, images.device
    images, masks = images.clone(), masks.clone()
    rotations, translations = rotations.clone(), translations.clone()

    # Every parameter in one copy to the device (float64 here, each cast as before).
    column = dict(zip(KINDS, to_device(draws.table, device), strict=True))
    angles = column["rotation"]
    turned = np.flatnonzero(params["rotation"] != 0)  # decided on the host: no wait
    if len(turned):
        idx = to_device(turned, device)
        images[idx] = rotate_batch(images[idx], angles[idx]).to(dtype)
        masks[idx] = rotate_batch(masks[idx], angles[idx]).to(masks.dtype).clamp(0, 1)
        rz = z_rotation(angles[idx])
        rotations[idx] = (rz @ rotations[idx].to(torch.float64)).to(rotations.dtype)
        translations[idx] = (rz @ translations[idx].to(torch.float64)[..., None])[..., 0].to(
            translations.dtype)

    factor = column["brightness"].to(dtype)
    images = (images * factor[:, None, None, None]).clamp(0, 1)
    gamma = column["gamma"].to(dtype)
    if bool((params["gamma"] != 1).any()):
        images = images.clamp_min(0) ** gamma[:, None, None, None]
    sigmas = column["blur"].to(dtype)
    if bool((params["blur"] > 0).any()):
        # The radius from the host's values, rounded to the images' dtype as on the device.
        largest = float(torch.as_tensor(params["blur"], dtype=dtype).max())
        images = _gaussian_blur(images, sigmas, largest)
    if draws.noise is not None:
        images = (images + to_device(draws.noise, device)).clamp(0, 1)
    return images, masks, rotations, translations


def augment_batch(images: Tensor, masks: Tensor, rotations: Tensor, translations: Tensor,
                  config: AugmentConfig, generators: list[np.random.Generator],
                  camera: Camera | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Augment a batch; labels stay exact (see the module docstring): the draws of
    :func:`draw_augmentation`, then :func:`apply_augmentation`.

    Args:
        images: (B, C, S, S) in [0, 1].
        masks: (B, 1, S, S) in [0, 1].
        rotations: (B, 3, 3) body-to-camera rotations; translations: (B, 3).
        config: which kinds and how strong.
        generators: one numpy Generator per item; each item draws its parameters from its own.
        camera: intrinsics at S x S, checked with :func:`check_rotation_exact` when the
            rotation is on (None: assume the default camera, centred and square).

    Returns:
        (images, masks, rotations, translations), new tensors of the same shapes and dtypes.
    """
    check_augment_inputs(images, masks, rotations, translations)
    if len(generators) != images.shape[0]:
        raise ValueError(f"generators: expected {images.shape[0]} (one per item), got "
                         f"{len(generators)}")
    if not config.enabled:
        return images, masks, rotations, translations
    if config.rotation and camera is not None:
        check_rotation_exact(camera)
    draws = draw_augmentation(config, generators, tuple(images.shape), images.dtype)
    return _apply(images, masks, rotations, translations, draws)  # checked above


def check_augment_inputs(images: Tensor, masks: Tensor, rotations: Tensor,
                         translations: Tensor) -> None:
    """One-line errors for a batch of the wrong shapes (see :func:`augment_batch`)."""
    check_tensor("images", images, (None, None, None), min_dims=4)
    batch = images.shape[0]
    if images.dim() != 4 or images.shape[-1] != images.shape[-2]:
        raise ValueError(f"images: expected (B, C, S, S), got {tuple(images.shape)}")
    if masks.shape != (batch, 1, *images.shape[-2:]):
        raise ValueError(f"masks: expected {(batch, 1, *images.shape[-2:])}, got "
                         f"{tuple(masks.shape)}")
    check_tensor("rotations", rotations, (3, 3), min_dims=3)
    check_tensor("translations", translations, (3,), min_dims=2)
    if rotations.shape[0] != batch or translations.shape[0] != batch:
        raise ValueError(f"rotations, translations: expected {batch} items, got "
                         f"{rotations.shape[0]} and {translations.shape[0]}")
