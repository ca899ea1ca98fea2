"""A batch of silhouettes and their vertex gradients in one Mitsuba launch: items in tiles.

:class:`~sq_mitsuba.render.silhouette.renderer.SilhouetteRenderer` renders item by item: one
vertex upload, BVH rebuild, render and backward pass per item, which leaves a GPU waiting on
the host. :class:`TiledSilhouettes` puts every item of a batch into one mesh of one scene and
renders them all at once, forward and backward, into one film of tiles.

Convention (the tiles): a perspective projection keeps lines lines, so an item can be moved
into its own tile of a larger film by a linear map of its camera-frame vertices that fixes the
camera centre. With the big film's principal point ``(cx_b, cy_b)`` and item i's image placed
with its pixel (0, 0) at film pixel ``(ox_i, oy_i)``, the map is the shear

    x' = x + z (cx + ox_i - cx_b) / fx,   y' = s y + z (cy + oy_i - cy_b) / fx,   z' = z

(``s = fy / fx``: Mitsuba takes one focal length, as in the per-item renderer), under which
item i's film pixels are exactly its own image's pixels shifted by whole pixels. The vertex
gradients come back through the transpose of the shear. Images are ``2 margin`` pixels
apart (cells of ``(W + 2 margin) x (H + 2 margin)``), and an item may reach ``2 margin``
pixels out of its image: margins may overlap, as no image pixel lies there, so no other item's
ray or silhouette sample sees it. An item that reaches further (or has a vertex within
:data:`NEAR` of the camera plane, where the projection is unbounded) is not tiled: it is hidden
behind the camera and the caller renders it alone (:attr:`TiledResult.tiled` says which).

Convention (the samples): the film renders ``spp`` samples per pixel, as an item's own
render does. The backward pass draws ``ceil(sppp W H / cell)`` silhouette samples per film
pixel, at least ``sppp W H`` per tile, and shares them equally among the tiled items: the
integrator ``silhouette_projective_tiled`` (:mod:`.integrator`) weights an edge by the angle
it subtends in its item's own frame, as a one-item scene does, normalised per item. So each
item's loss and gradients are unbiased estimates of its own render's, with the same expected
number of samples; the random numbers differ (they come from the seed and the call), so the
results are equal in distribution, not bit for bit.

Everything stays on the vertices' device (Dr.Jit and torch share the buffers on CUDA); the one
host read per call is whether every item could be tiled.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import check_int
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.render.backend import interrupts_deferred, mitsuba
from sq_mitsuba.render.silhouette.integrator import TILED_PLUGIN
from sq_mitsuba.render.silhouette.integrator import register as register_integrator
from sq_mitsuba.render.silhouette.seeds import render_seed

__all__ = ["DEFAULT_MARGIN", "TileLayout", "TiledResult", "TiledSilhouettes", "default_margin"]

MESH_ID = "tiled_mesh"
VERTEX_KEY = f"{MESH_ID}.vertex_positions"
#: Margin on each side of a tile, as a fraction of the image's larger side (8 px at 64 x 64):
#: an item may reach twice this out of its image and still be tiled.
DEFAULT_MARGIN = 0.125


def default_margin(camera: Camera) -> int:
    """Pixels of margin on each side of a tile for ``camera`` (:data:`DEFAULT_MARGIN`)."""
    return max(2, round(DEFAULT_MARGIN * max(camera.width, camera.height)))
#: Items with a vertex this close to the camera plane (or behind it) are not tiled.
NEAR = 1e-3
#: Items per launch at most: far tiles are strongly sheared and a film of many tiles traces
#: slower per sample, while each launch costs ~10 ms of fixed work. On an H200 (64 px, level 2,
#: spp 8, forward + backward) 256 items took 327 ms in one launch, 207 / 149 / 154 / 178 ms in
#: chunks of 128 / 64 / 32 / 16; at 128 px the best chunk was 32 (189 ms).
DEFAULT_MAX_ITEMS = 32
_CHUNK_STRIDE = 0x632BE5AB
_TILED_SALT = 0x5BD1E995  # keeps the tiled seeds apart from the per-item ones


@dataclass(frozen=True)
class TileLayout:
    """Where ``count`` items of ``width`` x ``height`` pixels lie in one film.

    Items fill a grid of ``columns`` x ``rows`` cells row by row; item i's image starts at
    film pixel :meth:`origins` ``[i]``, ``margin`` pixels inside its cell.
    """

    count: int
    width: int
    height: int
    margin: int

    @property
    def columns(self) -> int:
        return math.ceil(math.sqrt(self.count))

    @property
    def rows(self) -> int:
        return math.ceil(self.count / self.columns)

    @property
    def cell(self) -> tuple[int, int]:
        """(height, width) of a cell."""
        return self.height + 2 * self.margin, self.width + 2 * self.margin

    @property
    def film(self) -> tuple[int, int]:
        """(height, width) of the whole film."""
        cell_h, cell_w = self.cell
        return self.rows * cell_h, self.columns * cell_w

    def origins(self) -> Tensor:
        """(count, 2) float64 film pixel (x, y) of each item's image pixel (0, 0)."""
        index = torch.arange(self.count, dtype=torch.float64)
        cell_h, cell_w = self.cell
        column, row = index % self.columns, torch.div(index, self.columns, rounding_mode="floor")
        return torch.stack([column * cell_w, row * cell_h], 1) + self.margin

    def camera(self, camera: Camera) -> Camera:
        """The film's camera: ``camera``'s fx on both axes, principal point at the centre."""
        film_h, film_w = self.film
        return Camera(camera.fx, camera.fx, film_w / 2, film_h / 2, film_w, film_h)

    def tiles(self, film: Tensor) -> Tensor:
        """Item images (count, H, W) cut from a film image (film_h, film_w)."""
        cell_h, cell_w = self.cell
        m = self.margin
        cells = film.reshape(self.rows, cell_h, self.columns, cell_w).permute(0, 2, 1, 3)
        cells = cells.reshape(self.rows * self.columns, cell_h, cell_w)
        return cells[:self.count, m:m + self.height, m:m + self.width]

    def film_from_tiles(self, tiles: Tensor) -> Tensor:
        """A film image (film_h, film_w), zero outside the images, from (count, H, W)."""
        cell_h, cell_w = self.cell
        m = self.margin
        cells = tiles.new_zeros(self.rows * self.columns, cell_h, cell_w)
        cells[:self.count, m:m + self.height, m:m + self.width] = tiles
        cells = cells.reshape(self.rows, self.columns, cell_h, cell_w).permute(0, 2, 1, 3)
        return cells.reshape(self.rows * cell_h, self.columns * cell_w)


@dataclass
class TiledResult:
    """What :meth:`TiledSilhouettes.target_loss` returns (tensors on the vertices' device)."""

    losses: Tensor
    "(B,) float32 per-item losses; 0 where not :attr:`tiled`."
    coverage: Tensor
    "(B, H, W) float32 coverage; 0 where not tiled."
    grad: Tensor
    "(B, V, 3) float32 d(sum of losses)/d(vertices); 0 where not tiled or without a gradient."
    tiled: Tensor
    "(B,) bool: the items rendered here (the rest are the caller's)."


def shears(camera: Camera, layout: TileLayout) -> Tensor:
    """(count, 2) float64 shear coefficients (a_x, a_y) of the items: see the module."""
    film = layout.camera(camera)
    origins = layout.origins()
    principal = torch.tensor([camera.cx - film.cx, camera.cy - film.cy], dtype=torch.float64)
    return (origins + principal) / camera.fx


def fits(vertices: Tensor, camera: Camera, margin: int) -> Tensor:
    """(B,) bool: whether each item's projected vertices keep off every other item's image.

    Images are ``2 margin`` pixels apart, so an item may reach ``2 margin`` pixels out of its
    image on each side (items may overlap each other's margins: no image pixel sees that).
    Half a pixel is kept free (rounding, the film's border samples); every vertex must lie at
    depth > :data:`NEAR`. vertices: (B, V, 3) camera frame.
    """
    z = vertices[..., 2]
    ahead = (z > NEAR).all(1)
    safe_z = torch.where(z > NEAR, z, torch.ones_like(z))
    u = camera.fx * vertices[..., 0] / safe_z + camera.cx
    v = camera.fy * vertices[..., 1] / safe_z + camera.cy
    slack = 2 * margin - 0.5
    inside = ((u.amin(1) > -slack) & (u.amax(1) < camera.width + slack)
              & (v.amin(1) > -slack) & (v.amax(1) < camera.height + slack))
    return ahead & inside


def _item_losses(loss: Callable[[Tensor, Tensor], Tensor], coverage: Tensor,
                 targets: Tensor) -> Tensor:
    """(B,) per-item ``loss(coverage_i, target_i)``: one vectorised call where ``torch.func``
    can map the loss over items, else a loop."""
    try:
        losses = torch.func.vmap(loss)(coverage, targets)
    except Exception:  # a loss vmap cannot trace (data-dependent control flow, .item(), ...)
        losses = torch.stack([loss(c, t).reshape(()) for c, t in zip(coverage, targets,
                                                                     strict=True)])
    if losses.dim() > 1 and losses[0].numel() == 1:  # one element each, as the per-item
        losses = losses.reshape(-1)                     # path takes it: (B, 1) -> (B,)
    if losses.shape != (coverage.shape[0],):
        raise ValueError("loss: must return a scalar tensor per item")
    return losses


class TiledSilhouettes:
    """Coverage, losses and vertex gradients of B meshes in one Mitsuba launch each way.

    Args:
        camera: intrinsics and resolution of each item's image.
        spp: samples per pixel of the forward images.
        sppp: silhouette samples per pixel of an item's backward pass (per tile: see the
            module's convention on samples).
        sensor: maps a camera to its Mitsuba sensor dictionary (the per-item renderer's
            :func:`~sq_mitsuba.render.silhouette.renderer.sensor_dict`, handed in so that
            this module does not import the renderer that imports it).
        margin: pixels between an item's image and its cell's edge; default
            :func:`default_margin` (8 at 64 x 64).
        max_items: items per launch at most; a larger batch is rendered in chunks of this
            many (one scene serves them all). See :data:`DEFAULT_MAX_ITEMS`.

    One scene is built per (item count, topology) and kept while they stay the same; a call
    updates the one vertex buffer of every item (one BVH build).
    """

    def __init__(self, camera: Camera, spp: int, sppp: int,
                 sensor: Callable[[Camera], dict[str, Any]], margin: int | None = None,
                 max_items: int = DEFAULT_MAX_ITEMS) -> None:
        if margin is None:
            margin = default_margin(camera)
        margin, max_items = check_int("margin", margin), check_int("max_items", max_items)
        self.max_items = max_items
        self.camera, self.spp, self.sppp, self.margin = camera, spp, sppp, margin
        self._sensor = sensor
        self._mi = mitsuba()
        self._scene: Any = None
        self._params: Any = None
        self._integrator: Any = None
        self._key: tuple[int, int, bytes] | None = None
        self._faces_dr: Any = None
        self.layout: TileLayout | None = None
        self.scenes_built = 0

    # ------------------------------------------------------------------ scene

    def _ensure_scene(self, count: int, num_vertices: int, faces: np.ndarray) -> None:
        """Build the scene of ``count`` items of this topology unless it is live."""
        key = (count, num_vertices, faces.tobytes())
        if self._key == key:
            return
        with interrupts_deferred():  # Ctrl-C waits for Mitsuba (see interrupts_deferred)
            self._build(count, num_vertices, faces)
        self._key = key

    def _build(self, count: int, num_vertices: int, faces: np.ndarray) -> None:
        mi = self._mi
        register_integrator()
        # Drop the old scene first: Dr.Jit traces virtual calls over every live instance.
        self._scene = self._params = self._integrator = self._faces_dr = None
        layout = TileLayout(count, self.camera.width, self.camera.height, self.margin)
        offsets = (np.arange(count, dtype=np.uint32) * np.uint32(num_vertices))[:, None, None]
        all_faces = (faces[None].astype(np.uint32) + offsets).reshape(-1)
        total = count * num_vertices
        mesh = mi.Mesh(MESH_ID, vertex_count=total, face_count=count * faces.shape[0],
                       has_vertex_normals=False, has_vertex_texcoords=False)
        mesh_params = mi.traverse(mesh)
        placeholder = np.zeros((total, 3), np.float32)  # replaced before any render
        placeholder[:, 2] = -1.0
        placeholder[:, 0] = np.linspace(-1.0, 1.0, total, dtype=np.float32)
        mesh_params["vertex_positions"] = mi.Float(placeholder.ravel())
        mesh_params["faces"] = mi.UInt32(all_faces)
        mesh_params.update()
        self._scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": TILED_PLUGIN, "max_depth": 1, "sppc": 0, "sppi": 0,
                           "sppp": self.sppp},
            "sensor": self._sensor(layout.camera(self.camera)),
            "environment": {"type": "constant", "radiance": 1.0},
            MESH_ID: mesh,
        })
        self._params = mi.traverse(self._scene)
        self._params.keep([VERTEX_KEY])
        self._integrator = self._scene.integrator()
        self._faces_dr = mi.UInt32(all_faces)
        self.layout = layout
        self.scenes_built += 1

    def backward_sppp(self) -> int:
        """Silhouette samples per film pixel: at least ``sppp`` per image pixel per tile."""
        layout = self.layout
        cell_h, cell_w = layout.cell
        return math.ceil(self.sppp * layout.width * layout.height / (cell_h * cell_w))

    # ------------------------------------------------------------------ render

    def target_loss(self, vertices: Tensor, faces: np.ndarray, targets: Tensor,
                    loss: Callable[[Tensor, Tensor], Tensor], seeds: tuple[int, int],
                    requires_grad: bool) -> TiledResult:
        """Per-item ``loss(coverage_i, target_i)``, coverage and (with ``requires_grad``)
        vertex gradients of the items that fit their tiles, in one launch each way.

        Args:
            vertices: (B, V, 3) camera-frame vertices, detached, float, any device.
            faces: (F, 3) uint32 faces shared by the items (checked by the caller).
            targets: (B, H, W) target images.
            loss: (coverage (H, W), target (H, W)) -> scalar; mapped over items with
                ``torch.func.vmap`` where it can be.
            seeds: Mitsuba seeds of the forward and backward passes.
            requires_grad: also run the backward pass.
        """
        count = vertices.shape[0]
        chunk = min(count, self.max_items)
        if chunk == count:
            return self._launch(vertices, faces, targets, loss, seeds, requires_grad, count)
        results = []
        for index, start in enumerate(range(0, count, chunk)):
            part = slice(start, start + chunk)
            used = min(chunk, count - start)
            pieces = [vertices[part], targets[part]]
            if used < chunk:  # the last chunk: padded with hidden copies, so one scene serves
                pieces = [torch.cat([p, p[:1].expand(chunk - used, *p.shape[1:])])
                          for p in pieces]
            chunk_seeds = tuple((seed + _CHUNK_STRIDE * index) & 0xFFFFFFFF for seed in seeds)
            result = self._launch(pieces[0], faces, pieces[1], loss, chunk_seeds,
                                  requires_grad, used)
            results.append([field[:used] for field in (result.losses, result.coverage,
                                                       result.grad, result.tiled)])
        return TiledResult(*(torch.cat(fields) for fields in zip(*results, strict=True)))

    def _launch(self, vertices: Tensor, faces: np.ndarray, targets: Tensor,
                loss: Callable[[Tensor, Tensor], Tensor], seeds: tuple[int, int],
                requires_grad: bool, used: int) -> TiledResult:
        """:meth:`target_loss` of one scene's worth of items, the first ``used`` real (the
        rest padding, hidden and given no samples)."""
        mi = self._mi
        import drjit as dr

        count, num_vertices = vertices.shape[0], vertices.shape[1]
        self._ensure_scene(count, num_vertices, faces)
        layout = self.layout
        device = vertices.device
        vertices = vertices.to(torch.float32)
        tiled = fits(vertices, self.camera, self.margin)
        if used < count:
            tiled[used:] = False
        stretch = self.camera.fy / self.camera.fx
        own = vertices * vertices.new_tensor([1.0, stretch, 1.0])  # what a one-item scene holds
        shear = shears(self.camera, layout).to(device=device, dtype=torch.float32)
        sheared = own.clone()
        sheared[..., :2] += own[..., 2:3] * shear[:, None, :]
        # Items that do not fit: a tiny copy behind the camera, never seen, given no samples.
        centred = own - own.mean(1, keepdim=True)
        scale = centred.abs().amax((1, 2), keepdim=True).clamp_min(1e-12)
        hidden = centred / scale * 1e-3 + vertices.new_tensor([0.0, 0.0, -1.0])
        sheared = torch.where(tiled[:, None, None], sheared, hidden).contiguous()
        _sync_torch(device)
        with interrupts_deferred():
            values = mi.Float(sheared.reshape(-1))
            if requires_grad:
                dr.enable_grad(values)
            self._params[VERTEX_KEY] = values
            self._params.update()
            with dr.suspend_grad():
                film = self._integrator.render(self._scene, sensor=0, seed=seeds[0],
                                               spp=self.spp, develop=True)
                dr.eval(film)
                dr.sync_thread()
                film = film.torch()[..., 0]
        coverage = (1.0 - layout.tiles(film.to(device))).clamp(0.0, 1.0)
        coverage = torch.where(tiled[:, None, None], coverage, torch.zeros_like(coverage))
        targets = targets.to(device=device, dtype=torch.float32)
        grad_vertices = torch.zeros_like(vertices)
        with torch.enable_grad() if requires_grad else torch.no_grad():
            leaf = coverage.detach().requires_grad_(requires_grad)
            losses = _item_losses(loss, leaf, targets)
            losses = torch.where(tiled, losses, torch.zeros_like(losses))
            if requires_grad:
                (grad_coverage,) = torch.autograd.grad(losses.sum(), leaf, allow_unused=True)
        if requires_grad and grad_coverage is not None:
            grad_vertices = self._backward(values, own, tiled, grad_coverage, seeds[1])
            # Back through the shear: d/dx = d/dx', d/dy = s d/dy', d/dz = a . d/d(x', y') + d/dz'.
            grad_vertices[..., 2] += (grad_vertices[..., :2] * shear[:, None, :]).sum(-1)
            grad_vertices[..., 1] *= stretch
            grad_vertices = torch.where(tiled[:, None, None], grad_vertices,
                                        torch.zeros_like(grad_vertices))
        return TiledResult(losses.detach(), coverage.detach(), grad_vertices, tiled)

    def _backward(self, values: Any, own: Tensor, tiled: Tensor, grad_coverage: Tensor,
                  seed: int) -> Tensor:
        """d(loss)/d(sheared vertices) (B, V, 3) given d(loss)/d(coverage) (B, H, W)."""
        mi = self._mi
        import drjit as dr

        layout = self.layout
        # coverage = 1 - image, so the image receives the negated gradient.
        grad_film = layout.film_from_tiles(-grad_coverage.detach().to(torch.float32))
        active = tiled.to(torch.int32).contiguous()
        _sync_torch(own.device)
        with interrupts_deferred():
            self._integrator.layout = _Layout(
                faces=self._faces_dr, positions=mi.Float(own.reshape(-1).contiguous()),
                faces_per_item=len(self._faces_dr) // (3 * layout.count), items=layout.count,
                active=mi.UInt32(active) != 0)
            try:
                grad_in = mi.TensorXf(grad_film[..., None].contiguous())
                self._integrator.render_backward(self._scene, self._params, grad_in, sensor=0,
                                                 seed=seed, spp=self.backward_sppp())
                grad = dr.grad(values)
                dr.eval(grad)
                dr.sync_thread()
                grad = grad.torch().clone()
            finally:
                self._integrator.layout = None
                dr.clear_grad(values)
        # A rare silhouette sample with a degenerate Jacobian can give NaN; it carries no
        # information, so it counts as zero (as in the per-item renderer).
        grad = torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)
        return grad.to(own.device).reshape(own.shape)


def _sync_torch(device: torch.device) -> None:
    """Wait for torch's queued work on ``device`` before Dr.Jit reads its tensors (Dr.Jit
    launches on its own CUDA stream)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@dataclass
class _Layout:
    """What ``silhouette_projective_tiled`` needs to share the silhouette samples (see
    :mod:`.integrator`)."""

    faces: Any
    positions: Any
    faces_per_item: int
    items: int
    active: Any


def tiled_seeds(seed: int, call: int) -> tuple[int, int]:
    """Forward and backward Mitsuba seeds of a tiled call: from the base seed and the call."""
    forward, backward = (render_seed(seed, call, backward=b, salt=_TILED_SALT)
                         for b in (False, True))
    return forward, backward
