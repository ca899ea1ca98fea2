"""Differentiable silhouettes rendered by Mitsuba's projective integrator, bridged into torch.

A :class:`SilhouetteRenderer` holds one Mitsuba scene: a perspective sensor fixed at the origin
(OpenCV frame, see :func:`sensor_dict`), a constant white environment, and one mesh slot whose
vertex positions are swapped per batch item. With ``max_depth = 1`` a camera ray sees only the
environment, so every pixel reads the fraction of its area *not* covered by the mesh:
``coverage = 1 - image``. Gradients with respect to the vertices come from Mitsuba's projective
sampling of the primarily visible silhouette (``sppp`` samples per pixel); interior (``sppc``)
and indirect (``sppi``) terms are zero for a mask and are switched off (``sppi > 0`` alone
costs seconds per backward pass: it builds an indirect-silhouette guide every time). The
integrator is ``silhouette_projective`` (:mod:`sq_mitsuba.render.silhouette.integrator`):
``prb_projective`` with its path-tracing loop replaced by one visibility test, which renders
the same images and gradients bit for bit at about half the cost.

Convention: the batch is a loop over items inside one ``torch.autograd.Function``: Mitsuba's
``batch`` sensor fails in the backward pass and ``dr.freeze`` refuses projective integrators.
Each item costs one vertex update (a BVH rebuild) in the forward pass and one in the backward
pass; the backward pass runs the items in reverse so that the last item, still in the scene,
needs none.

Convention: Ctrl-C waits for the Mitsuba call in progress (a scene build, a vertex update,
one item's render or backward pass) and then raises ``KeyboardInterrupt`` as usual
(:func:`~sq_mitsuba.render.backend.interrupts_deferred`): raised inside Dr.Jit, it would come
out as some other error, or abort the process.

Convention: :meth:`SilhouetteRenderer.render_target_loss` (how training's reprojection loss
renders) can spread its items over worker processes (``workers``), each rendering on one Dr.Jit
thread. An item draws its samples from ``(seed, call, item)`` alone, so the pooled result
equals a one-process, one-thread render bit for bit, whatever the number of workers. The
renderer renders and back-propagates; the losses it is given are the caller's.

Convention: with ``batched`` (the default on CUDA variants), :meth:`render_target_loss` renders
every item of the batch in one Mitsuba launch each way instead, each item in its own tile of one
film (:mod:`sq_mitsuba.render.silhouette.tiled`): the same estimator with other random numbers,
so equal to the per-item result in distribution, not bit for bit. An item that reaches too far
out of its image for a tile is rendered alone, as above. The CPU default stays per item (exact,
and faster there).
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import check_int, check_rotations, check_tensor
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.render.backend import MAX_SAMPLES_PER_RENDER, interrupts_deferred, mitsuba
from sq_mitsuba.render.silhouette.integrator import register as register_integrator
from sq_mitsuba.render.silhouette.seeds import render_seed
from sq_mitsuba.render.silhouette.tiled import TiledSilhouettes, tiled_seeds
from sq_mitsuba.render.silhouette.workers import SilhouetteWorkers, WorkerError

#: Integrators a renderer can use: the lean mask integrator (default) and Mitsuba's general
#: ``prb_projective``, which renders the same images and gradients at about twice the cost.
INTEGRATORS = ("silhouette_projective", "prb_projective")
MESH_ID = "silhouette_mesh"
VERTEX_KEY = f"{MESH_ID}.vertex_positions"
DEFAULT_SPP = 16
#: Silhouette samples per image of the backward pass by default: Mitsuba's projective
#: integrators draw ``sppp x width x height`` of them along the silhouette edges, so the
#: gradient noise depends on this total. 16,384 is sppp 4 at 64 x 64; measured relative
#: gradient noise (bench render): 15.9 % at 64 x 64 (sppp 4), 13.8 % at 128 x 128 (sppp 1).
DEFAULT_SILHOUETTE_SAMPLES = 4 * 64 * 64


def default_sppp(camera: Camera) -> int:
    """Silhouette samples per pixel that spend :data:`DEFAULT_SILHOUETTE_SAMPLES` per image."""
    return max(1, round(DEFAULT_SILHOUETTE_SAMPLES / (camera.width * camera.height)))



def sensor_dict(camera: Camera) -> dict[str, Any]:
    """Mitsuba ``perspective`` sensor for ``camera``, fixed at the origin, OpenCV frame.

    Convention: the sensor looks down +z with image-up along -y, so image x runs along +x and
    image y along +y (verified against an independent ray-sphere reference). Mitsuba takes one
    field of view, so the sensor uses ``fx`` for both axes; :class:`SilhouetteRenderer`
    stretches vertex y by ``fy / fx`` to honour a different ``fy``. The principal point is an
    offset in units of the image size, with Mitsuba's sign.
    """
    mi = mitsuba()
    return {
        "type": "perspective",
        "fov": math.degrees(2 * math.atan(camera.width / (2 * camera.fx))),
        "fov_axis": "x",
        "principal_point_offset_x": -(camera.cx - camera.width / 2) / camera.width,
        "principal_point_offset_y": -(camera.cy - camera.height / 2) / camera.height,
        "near_clip": 1e-3,
        "far_clip": 1e5,
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1],
                                                   up=[0, -1, 0]),
        "film": {
            "type": "hdrfilm",
            "width": camera.width,
            "height": camera.height,
            "pixel_format": "luminance",
            "component_format": "float32",
            # Box filter: a pixel value is exactly the covered fraction of its area.
            "rfilter": {"type": "box"},
            # Lets silhouettes entering or leaving the frame contribute gradients.
            "sample_border": True,
        },
        "sampler": {"type": "independent", "sample_count": 1},
    }


@dataclass
class _Topology:
    """The mesh topology the scene was built for, and how to recognise it cheaply.

    Convention: a render with the very faces tensor of the last one, unmodified since
    (``torch`` bumps a tensor's ``_version`` on every in-place change), is a hit at no cost;
    another tensor is compared element by element with ``key`` (a memory compare, several
    times cheaper than hashing the faces, which every call did before).
    """

    ident: int
    "Increases with every scene built: a backward pass checks that its forward's scene is live."
    num_vertices: int
    faces: np.ndarray
    "(F, 3) uint32, as given to Mitsuba."
    key: Tensor
    "(F, 3) int64 CPU copy of the faces, for the element-wise comparison."
    last: weakref.ref[Tensor] | None = None
    "The faces tensor last seen with this topology."
    last_version: int = -1
    "Its ``_version`` then."

    def matches(self, faces: Tensor, num_vertices: int) -> bool:
        """Whether ``faces`` with ``num_vertices`` vertices is this topology (remembers it)."""
        if num_vertices != self.num_vertices:
            return False
        if self.last is not None and self.last() is faces and faces._version == self.last_version:
            return True
        if (faces.shape != self.key.shape or faces.is_floating_point()
                or faces.is_complex() or faces.dtype == torch.bool):
            return False
        if not torch.equal(faces.detach().to("cpu", torch.int64), self.key):
            return False
        self.remember(faces)
        return True

    def remember(self, faces: Tensor) -> None:
        try:
            version = faces._version
        except RuntimeError:  # inference-mode tensors have no version counter
            self.last = None
            return
        self.last, self.last_version = weakref.ref(faces), version


def _check_faces(faces: Tensor, num_vertices: int) -> np.ndarray:
    """Faces as a contiguous uint32 array (F, 3), or ``ValueError`` naming ``faces``."""
    if not isinstance(faces, Tensor):
        raise ValueError(f"faces: expected a torch.Tensor, got {type(faces).__name__}")
    if faces.dim() != 2 or faces.shape[1] != 3 or faces.shape[0] < 1:
        raise ValueError(f"faces: expected shape (F, 3) with F >= 1, got {tuple(faces.shape)}")
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise ValueError(f"faces: expected an integer dtype, got {faces.dtype}")
    low, high = int(faces.min()), int(faces.max())
    if low < 0 or high >= num_vertices:
        raise ValueError(f"faces: indices must lie in [0, {num_vertices}), got [{low}, {high}]")
    return np.ascontiguousarray(faces.detach().cpu().numpy().astype(np.uint32))


class SilhouetteRenderer:
    """Differentiable silhouettes (coverage in [0, 1]) of triangle meshes seen by ``camera``.

    Args:
        camera: intrinsics and resolution of the images.
        spp: samples per pixel of the forward (primal) image; coverage is exact up to Monte
            Carlo noise of about ``sqrt(c (1 - c) / spp)`` in pixels on an edge.
        sppp: silhouette samples per pixel of the backward pass (gradient noise against a
            sppp-256 reference, ``bench render``'s measure: about 26 / 17 / 13 % at 64 x 64
            for 1 / 4 / 16, 14 / 10 / 8 % at 128 x 128; the forward's spp sets the floor);
            default :func:`default_sppp` (4 at 64 x 64, 1 at 128 x 128: a fixed budget of
            silhouette samples per image).
        seed: base seed; every call draws fresh samples, reproducibly from this seed.
        workers: processes that :meth:`render_target_loss` spreads its items over (see
            :mod:`sq_mitsuba.render.silhouette.workers`); 0 renders in this process. Started
            on first use; CPU variants only.
        integrator: ``"silhouette_projective"`` (:mod:`sq_mitsuba.render.silhouette.integrator`,
            the lean one) or ``"prb_projective"`` (Mitsuba's general one, the reference).
        batched: :meth:`render_target_loss` renders the whole batch in one launch each way
            (:mod:`sq_mitsuba.render.silhouette.tiled`; lean integrator only, no workers); None
            (default): on CUDA variants, where per-item launches leave the GPU waiting on the
            host. The CPU default, per item, is exact across worker counts and faster there.

    One Mitsuba scene is built on the first call and reused while the mesh topology (vertex
    count and faces) stays the same; a new topology rebuilds it. Recognising the topology costs
    nothing when the same faces tensor comes back unmodified, and one element-wise comparison
    otherwise (see :class:`_Topology`). Kernels are compiled once and come from Dr.Jit's cache
    afterwards.
    """

    def __init__(self, camera: Camera, spp: int = DEFAULT_SPP, sppp: int | None = None,
                 seed: int = 0, workers: int = 0,
                 integrator: str = "silhouette_projective", batched: bool | None = None) -> None:
        if not isinstance(camera, Camera):
            raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
        if sppp is None:
            sppp = default_sppp(camera)
        spp, sppp = check_int("spp", spp), check_int("sppp", sppp)
        workers = check_int("workers", workers, 0, 256)
        samples = camera.width * camera.height * max(spp, sppp)
        if samples > MAX_SAMPLES_PER_RENDER:  # Mitsuba's limit: said here, not as its error
            raise ValueError(f"spp: {spp} (sppp {sppp}) at {camera.width} x {camera.height} px "
                             f"is {samples:,} samples per render, more than Mitsuba's 2^32; "
                             "lower the samples or the resolution")
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator: expected one of {INTEGRATORS}, got {integrator!r}")
        if batched is not None and not isinstance(batched, bool):
            raise ValueError(f"batched: expected True, False or None, got {batched!r}")
        if batched and integrator != "silhouette_projective":
            raise ValueError(f"batched: needs the integrator 'silhouette_projective', got "
                             f"{integrator!r}")
        if batched and workers:  # the batched path renders in this process: said, not ignored
            raise ValueError(f"workers: {workers} with batched=True, which renders every item "
                             "in this process; use workers=0")
        self.integrator = integrator
        self.camera = camera
        self.spp = spp
        self.sppp = sppp
        self.seed = int(seed) & 0xFFFFFFFF
        self._mi = mitsuba()
        if batched is None:
            batched = (self._mi.variant().startswith("cuda")
                       and integrator == "silhouette_projective")
        self.batched = batched
        self._tiled: TiledSilhouettes | None = None
        self._tiled_topology: _Topology | None = None
        self._scene: Any = None
        self._params: Any = None
        self._integrator: Any = None
        self._topology: _Topology | None = None
        self._scenes_built = 0
        # (render, call, item) whose vertices the scene holds; ``_renders`` counts every render
        # and, unlike the call number that seeds the samples, survives reseed(): a backward
        # pass reuses the loaded vertices only if they are its own forward pass's.
        self._loaded: tuple[int, int, int] | None = None
        self._loaded_vertices: Any = None
        self._calls = 0
        self._renders = 0
        self.workers = workers
        self._pool: Any = None
        # Convention: Mitsuba renders with fx on both axes; y is stretched to give fy.
        self._y_stretch = camera.fy / camera.fx

    def reseed(self, seed: int) -> None:
        """Restart the sample sequence from ``seed``: the next render draws the samples a fresh
        renderer with this seed would (so a training step's samples depend on the step alone)."""
        self.seed = int(seed) & 0xFFFFFFFF
        self._calls = 0

    def __repr__(self) -> str:
        c = self.camera
        return (f"SilhouetteRenderer({c.width}x{c.height}, fx={c.fx:.2f}, spp={self.spp}, "
                f"sppp={self.sppp}, workers={self.workers}, batched={self.batched}, "
                f"variant={self._mi.variant()})")

    def close(self) -> None:
        """Stop the worker processes, if any were started (a later call starts new ones)."""
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    @property
    def scenes_built(self) -> int:
        """Mitsuba scenes built so far: one per change of topology (see :class:`_Topology`)."""
        return self._scenes_built

    @property
    def resolution(self) -> tuple[int, int]:
        """(height, width) of the images."""
        return self.camera.height, self.camera.width

    # ------------------------------------------------------------------ public

    def render(self, vertices: Tensor, faces: Tensor) -> Tensor:
        """Coverage images (B, H, W) in [0, 1] of meshes with camera-frame ``vertices``.

        Args:
            vertices: (B, V, 3) float, OpenCV camera frame (x right, y down, z forward);
                differentiable.
            faces: (F, 3) integer indices into V, shared by all items; watertight meshes with
                shared vertices give the cleanest silhouette gradients.

        Returns:
            (B, H, W) tensor of ``vertices``' dtype and device; pixel (i, j) is the fraction of
            its area covered by the mesh. Geometry behind the camera is invisible.
        """
        faces_np = self._prepare(vertices, faces)
        if torch.is_grad_enabled() and vertices.requires_grad:
            return _RenderSilhouettes.apply(vertices, self, faces_np)
        return self._forward(vertices.detach(), self._next_call(), requires_grad=False)

    # ------------------------------------------------------------------ scene

    @staticmethod
    def _check_vertices(vertices: Tensor) -> None:
        check_tensor("vertices", vertices, (None, 3), min_dims=3)
        if vertices.dim() != 3 or vertices.shape[0] < 1 or vertices.shape[1] < 3:
            raise ValueError(f"vertices: expected shape (B, V, 3) with B >= 1 and V >= 3, got "
                             f"{tuple(vertices.shape)}")

    def _check_targets(self, vertices: Tensor, targets: Tensor, loss: Any) -> None:
        """One-line errors for :meth:`render_target_loss`'s targets (B, H, W) and loss."""
        check_tensor("targets", targets, (None, None), min_dims=3)
        expected = (vertices.shape[0], *self.resolution)
        if tuple(targets.shape) != expected:
            raise ValueError(f"targets: expected shape {expected}, got {tuple(targets.shape)}")
        if not callable(loss):
            raise ValueError("loss: expected a callable (coverage (H, W), target (H, W)) -> "
                             "scalar")

    def _prepare(self, vertices: Tensor, faces: Tensor) -> np.ndarray:
        """Check the inputs of a render, make the scene fit their topology; faces as numpy."""
        self._check_vertices(vertices)
        num_vertices = vertices.shape[1]
        if (self._topology is not None and isinstance(faces, Tensor)
                and self._topology.matches(faces, num_vertices)):
            return self._topology.faces
        faces_np = _check_faces(faces, num_vertices)
        self._build_scene(num_vertices, faces_np)
        self._topology.remember(faces)
        return faces_np

    def _restore_topology(self, ident: int, num_vertices: int, faces: np.ndarray) -> None:
        """Rebuild the scene of topology ``ident`` (faces as numpy) unless it is still live."""
        if self._topology is None or self._topology.ident != ident:
            self._build_scene(num_vertices, faces)

    def _build_scene(self, num_vertices: int, faces: np.ndarray) -> None:
        with interrupts_deferred():  # Ctrl-C waits for Mitsuba (see interrupts_deferred)
            self._build_scene_now(num_vertices, faces)

    def _build_scene_now(self, num_vertices: int, faces: np.ndarray) -> None:
        mi = self._mi
        if self.integrator == "silhouette_projective":
            register_integrator()
        # Drop the old scene first: Dr.Jit traces virtual calls over every live instance.
        self._scene = self._params = self._integrator = self._loaded_vertices = None
        self._loaded = None
        mesh = mi.Mesh(MESH_ID, vertex_count=num_vertices, face_count=faces.shape[0],
                       has_vertex_normals=False, has_vertex_texcoords=False)
        mesh_params = mi.traverse(mesh)
        # Placeholder: a unit sphere-ish point cloud far in front; replaced before any render.
        placeholder = np.zeros((num_vertices, 3), np.float32)
        placeholder[:, 2] = 10.0
        placeholder[:, 0] = np.linspace(-1.0, 1.0, num_vertices, dtype=np.float32)
        mesh_params["vertex_positions"] = mi.Float(placeholder.ravel())
        mesh_params["faces"] = mi.UInt32(faces.ravel())
        mesh_params.update()
        self._scene = mi.load_dict({
            "type": "scene",
            "integrator": {
                "type": self.integrator,
                "max_depth": 1,
                "sppc": 0,
                "sppi": 0,
                "sppp": self.sppp,
            },
            "sensor": sensor_dict(self.camera),
            "environment": {"type": "constant", "radiance": 1.0},
            MESH_ID: mesh,
        })
        self._params = mi.traverse(self._scene)
        self._params.keep([VERTEX_KEY])
        self._integrator = self._scene.integrator()
        self._scenes_built += 1
        self._topology = _Topology(self._scenes_built, num_vertices, faces,
                                   torch.from_numpy(faces.astype(np.int64)))

    def _next_call(self) -> int:
        self._calls += 1
        self._renders += 1
        return self._calls

    def _seed(self, call: int, item: int, backward: bool, seed: int | None = None) -> int:
        """The samples' seed of one item of a call (``seed``: the base seed, default the
        renderer's; a backward pass passes its forward pass's, which reseed() may have left)."""
        return render_seed(self.seed if seed is None else seed, call, item, backward)

    def _load(self, vertices: Tensor, token: tuple[int, int], requires_grad: bool) -> Any:
        """Put one item's vertices (V, 3) into the scene (rebuilds the BVH)."""
        mi = self._mi
        import drjit as dr

        array = vertices.detach().to("cpu", torch.float32)
        if self._y_stretch != 1.0:
            array = array * array.new_tensor([1.0, self._y_stretch, 1.0])
        with interrupts_deferred():
            values = mi.Float(np.ascontiguousarray(array.numpy()).ravel())
            if requires_grad:
                dr.enable_grad(values)
            self._params[VERTEX_KEY] = values
            self._params.update()
        self._loaded, self._loaded_vertices = (self._renders, *token), values
        return values

    # ------------------------------------------------------------------ passes

    def _forward(self, vertices: Tensor, call: int, requires_grad: bool) -> Tensor:
        images = []
        for item in range(vertices.shape[0]):
            self._load(vertices[item], (call, item), requires_grad)
            images.append(self._render_item(call, item))
        return torch.stack(images).to(dtype=vertices.dtype, device=vertices.device)

    def _backward(self, vertices: Tensor, grad_coverage: Tensor, call: int,
                  render: int | None = None, seed: int | None = None) -> Tensor:
        """Vertex gradients of call ``call`` (``render``: its render count, ``seed``: the base
        seed at its forward pass; default the renderer's now)."""
        import drjit as dr

        grad_vertices = torch.zeros(vertices.shape, dtype=torch.float32)
        # coverage = 1 - image, so the image receives the negated gradient.
        grad_images = (-grad_coverage.detach()).to("cpu", torch.float32).contiguous()
        for item in reversed(range(vertices.shape[0])):
            if not bool(grad_images[item].any()):
                continue
            own = (self._renders if render is None else render, call, item)
            if self._loaded == own and dr.grad_enabled(self._loaded_vertices):
                values = self._loaded_vertices
            else:
                values = self._load(vertices[item], (call, item), requires_grad=True)
            grad_vertices[item] = self._vertex_gradient(values, grad_images[item], call, item,
                                                        seed)
        return grad_vertices.to(dtype=vertices.dtype, device=vertices.device)

    def _vertex_gradient(self, values: Any, grad_image: Tensor, call: int, item: int,
                         seed: int | None = None) -> Tensor:
        """d(loss)/d(vertices) (V, 3) of the loaded item, given d(loss)/d(image) (H, W)."""
        mi = self._mi
        import drjit as dr

        with interrupts_deferred():
            grad_in = mi.TensorXf(np.ascontiguousarray(grad_image.numpy()[..., None]))
            self._integrator.render_backward(self._scene, self._params, grad_in, sensor=0,
                                             seed=self._seed(call, item, True, seed), spp=0)
            grad = np.array(dr.grad(values), dtype=np.float32).reshape(-1, 3)
            dr.clear_grad(values)
        # A rare silhouette sample with a degenerate Jacobian can give NaN; it carries no
        # information, so it counts as zero.
        grad_vertices = torch.from_numpy(np.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0))
        if self._y_stretch != 1.0:
            grad_vertices[..., 1] *= self._y_stretch
        return grad_vertices

    def _render_item(self, call: int, item: int) -> Tensor:
        """Coverage (H, W) float32 of the item whose vertices are loaded."""
        import drjit as dr

        with interrupts_deferred(), dr.suspend_grad():
            image = self._integrator.render(self._scene, sensor=0,
                                            seed=self._seed(call, item, False), spp=self.spp,
                                            develop=True)
            image = np.array(image, dtype=np.float32)
        coverage = 1.0 - torch.from_numpy(image[..., 0])
        return coverage.clamp_(0.0, 1.0)

    def render_loss(self, vertices: Tensor, faces: Tensor,
                    loss_fn: Callable[[Tensor, int], Tensor]) -> tuple[Tensor, Tensor]:
        """Sum over items of ``loss_fn(coverage[i], i)``, differentiable w.r.t. ``vertices``.

        Equivalent to ``sum(loss_fn(c, i) for i, c in enumerate(render(vertices, faces)))``,
        but each item's vertices are loaded once (one BVH rebuild instead of two): the
        backward pass of an item runs right after its forward pass, with the gradient of its
        loss, so a loss must be a sum of per-item terms (a reprojection loss is). Runs in this
        process; :meth:`render_target_loss` is the same for a loss against per-item target
        images, and can use ``workers``.

        Args:
            vertices: (B, V, 3) camera-frame vertices (see :meth:`render`).
            faces: (F, 3) shared faces.
            loss_fn: maps one coverage image (H, W) (float32, CPU) and its item index to a
                scalar; only its gradient w.r.t. the image is used.

        Returns:
            (loss, coverage): the summed loss (scalar, vertices' dtype) and the coverage
            images (B, H, W), detached.
        """
        if not callable(loss_fn):
            raise ValueError("loss_fn: expected a callable (coverage (H, W), item) -> scalar")
        self._prepare(vertices, faces)
        requires_grad = torch.is_grad_enabled() and vertices.requires_grad

        def run(detached: Tensor, call: int) -> tuple[float, Tensor, Tensor]:
            losses, coverage, grad = self._loss_items(detached, call, range(detached.shape[0]),
                                                      loss_fn, requires_grad=requires_grad)
            return float(sum(losses.tolist())), coverage, grad  # in item order

        return self._fused(vertices, run, requires_grad)

    def render_target_loss(self, vertices: Tensor, faces: Tensor, targets: Tensor,
                           loss: Callable[[Tensor, Tensor], Tensor]) -> tuple[Tensor, Tensor]:
        """``sum_i loss(coverage_i, targets_i)``, differentiable w.r.t. ``vertices``.

        :meth:`render_loss` for a loss that compares each item's coverage with its own target
        image: the renderer renders the coverage, hands it to ``loss`` and back-propagates the
        coverage gradient the loss returns (one BVH rebuild per item), sharing the items among
        the ``workers`` processes when it has any. The loss itself is the caller's (the
        training losses live in :mod:`sq_mitsuba.model.losses`); with workers it must be a
        module-level function, which the processes import by name. Without a gradient to
        compute, only the forward images are rendered.

        Args:
            vertices: (B, V, 3) camera-frame vertices (see :meth:`render`).
            faces: (F, 3) shared faces.
            targets: (B, H, W) target images; (H, W) = :attr:`resolution`.
            loss: maps one coverage image (H, W) and its target (H, W), both float32 CPU, to a
                scalar; only its gradient w.r.t. the coverage is used.

        Returns:
            (loss, coverage): the summed loss (scalar, vertices' dtype) and the coverage
            images (B, H, W), detached.

        With :attr:`batched`, all items render in one launch each way (see the module); the
        loss is then mapped over the items with ``torch.func.vmap`` where it can be (a loop
        otherwise), and everything stays on the vertices' device.
        """
        if self.batched:
            return self._tiled_target_loss(vertices, faces, targets, loss)
        self._prepare(vertices, faces)
        self._check_targets(vertices, targets, loss)
        targets = targets.detach().to("cpu", torch.float32).contiguous()
        requires_grad = torch.is_grad_enabled() and vertices.requires_grad

        def run(detached: Tensor, call: int) -> tuple[float, Tensor, Tensor]:
            if self.workers and detached.shape[0] > 1 and self._mi.variant().startswith("llvm"):
                if self._pool is None:
                    self._pool = SilhouetteWorkers(self.camera, self.spp, self.sppp,
                                                   self.integrator, self.workers)
                try:
                    losses, coverage, grad = self._pool.target_loss(
                        self.seed, call, detached, self._topology.faces, targets, loss,
                        requires_grad)
                except WorkerError:
                    self.close()  # the next call starts a fresh pool
                    raise
            else:
                losses, coverage, grad = self.target_loss_items(
                    detached, targets, call, range(detached.shape[0]), loss, requires_grad)
            return float(sum(losses.tolist())), coverage, grad  # in item order

        return self._fused(vertices, run, requires_grad)

    def _tiled_target_loss(self, vertices: Tensor, faces: Tensor, targets: Tensor,
                           loss: Callable[[Tensor, Tensor], Tensor]) -> tuple[Tensor, Tensor]:
        """:meth:`render_target_loss` with every item in one launch each way (``batched``)."""
        self._check_vertices(vertices)
        num_vertices = vertices.shape[1]
        topology = self._tiled_topology
        if topology is not None and isinstance(faces, Tensor) and topology.matches(
                faces, num_vertices):
            faces_np = topology.faces
        else:
            faces_np = _check_faces(faces, num_vertices)
            self._tiled_topology = _Topology(0, num_vertices, faces_np,
                                             torch.from_numpy(faces_np.astype(np.int64)))
            self._tiled_topology.remember(faces)
        self._check_targets(vertices, targets, loss)
        if self._tiled is None:
            self._tiled = TiledSilhouettes(self.camera, self.spp, self.sppp, sensor_dict)
        requires_grad = torch.is_grad_enabled() and vertices.requires_grad
        targets = targets.detach()

        def run(detached: Tensor, call: int) -> tuple[Tensor, Tensor, Tensor]:
            result = self._tiled.target_loss(detached, faces_np, targets, loss,
                                             tiled_seeds(self.seed, call), requires_grad)
            losses, coverage, grad = result.losses, result.coverage, result.grad
            if not bool(result.tiled.all()):  # the one host read of a batched call
                # Items reaching too far out of their images: rendered alone, as per item.
                rest = (~result.tiled).nonzero().flatten().cpu()
                self._prepare(detached, faces)
                alone = self.target_loss_items(
                    detached[rest.to(detached.device)].to("cpu", torch.float32),
                    targets[rest.to(targets.device)].to("cpu", torch.float32).contiguous(),
                    call, rest.tolist(), loss, requires_grad)
                index = rest.to(losses.device)
                losses[index] = alone[0].to(losses)
                coverage[index] = alone[1].to(coverage)
                grad[index] = alone[2].to(grad)
            return losses.double().sum(), coverage, grad

        return self._fused(vertices, run, requires_grad)

    def _fused(self, vertices: Tensor, run: Callable[[Tensor, int], tuple[Any, Tensor, Tensor]],
               requires_grad: bool) -> tuple[Tensor, Tensor]:
        """The fused losses' (loss, coverage) from ``run``: through :class:`_RenderedLoss`
        where a gradient is wanted, else its forward pass alone (no backward rendered)."""
        if requires_grad:
            return _RenderedLoss.apply(vertices, self, run)
        total, coverage, _ = run(vertices.detach(), self._next_call())
        total = total if isinstance(total, Tensor) else vertices.new_tensor(total)
        return (total.to(dtype=vertices.dtype, device=vertices.device),
                coverage.to(dtype=vertices.dtype, device=vertices.device))

    def target_loss_items(self, vertices: Tensor, targets: Tensor, call: int,
                          items: Sequence[int], loss: Callable[[Tensor, Tensor], Tensor],
                          requires_grad: bool) -> tuple[Tensor, Tensor, Tensor]:
        """The per-item work of :meth:`render_target_loss` (also what a worker process runs).

        Args:
            vertices: (k, V, 3) camera-frame vertices of ``items`` (the scene must already fit
                their topology, see :meth:`_prepare`).
            targets: (k, H, W) float32 CPU targets.
            call, items: the render call and the batch indices of the k items; with the seed,
                they fix each item's samples.
            loss: (coverage (H, W), target (H, W)) -> scalar.
            requires_grad: also run each item's backward pass.

        Returns:
            losses (k,) float64, coverage (k, H, W) float32, and d(sum of losses)/d(vertices)
            (k, V, 3) float32 (zeros without ``requires_grad``).
        """
        return self._loss_items(vertices, call, items,
                                lambda coverage, index: loss(coverage, targets[index]),
                                requires_grad)

    def _loss_items(self, vertices: Tensor, call: int, items: Sequence[int],
                    loss_fn: Callable[[Tensor, int], Tensor],
                    requires_grad: bool) -> tuple[Tensor, Tensor, Tensor]:
        """Per-item forward, loss and (with ``requires_grad``) backward of the fused losses.

        ``loss_fn(coverage, index)`` gets the index into ``vertices`` (k, V, 3); ``items`` are
        the batch indices that fix the samples. Returns losses (k,) float64, coverage (k, H, W)
        float32 and d(sum of losses)/d(vertices) (k, V, 3) float32 (zeros without
        ``requires_grad``).
        """
        count = vertices.shape[0]
        losses = torch.zeros(count, dtype=torch.float64)
        grad_vertices = torch.zeros((count, vertices.shape[1], 3), dtype=torch.float32)
        images = []
        for index, item in enumerate(items):
            values = self._load(vertices[index], (call, item), requires_grad)
            coverage = self._render_item(call, item).requires_grad_(requires_grad)
            grad_coverage = None
            with torch.set_grad_enabled(requires_grad):
                loss = loss_fn(coverage, index)
                if not isinstance(loss, Tensor) or loss.numel() != 1:
                    raise ValueError("loss_fn: must return a scalar tensor")
                if requires_grad:
                    (grad_coverage,) = torch.autograd.grad(loss, coverage, allow_unused=True)
            losses[index] = float(loss.detach())
            images.append(coverage.detach())
            if grad_coverage is not None and bool(grad_coverage.any()):
                # coverage = 1 - image, so the image receives the negated gradient.
                grad_vertices[index] = self._vertex_gradient(
                    values, (-grad_coverage).contiguous(), call, item)
        return losses, torch.stack(images), grad_vertices


class _RenderSilhouettes(torch.autograd.Function):
    """Autograd bridge: forward renders coverage, backward runs Mitsuba's ``render_backward``
    per item with the incoming image gradients."""

    @staticmethod
    def forward(ctx: Any, vertices: Tensor, renderer: SilhouetteRenderer,
                faces: np.ndarray) -> Tensor:
        call = renderer._next_call()
        ctx.renderer, ctx.faces, ctx.call = renderer, faces, call
        ctx.render, ctx.seed = renderer._renders, renderer.seed
        ctx.topology = renderer._topology.ident
        ctx.save_for_backward(vertices)
        return renderer._forward(vertices.detach(), call, requires_grad=True)

    @staticmethod
    def backward(ctx: Any, grad_coverage: Tensor) -> tuple[Tensor | None, None, None]:
        (vertices,) = ctx.saved_tensors
        renderer: SilhouetteRenderer = ctx.renderer
        renderer._restore_topology(ctx.topology, vertices.shape[1], ctx.faces)
        return renderer._backward(vertices.detach(), grad_coverage, ctx.call, ctx.render,
                                  ctx.seed), None, None


class _RenderedLoss(torch.autograd.Function):
    """Autograd bridge of the fused losses (:meth:`SilhouetteRenderer.render_loss`,
    :meth:`~SilhouetteRenderer.render_target_loss`): ``run(vertices, call)`` computes the loss
    (a float, or a scalar tensor: the batched path keeps it on the device), the coverage and the
    vertex gradients during the forward pass; the backward returns the gradients, scaled."""

    @staticmethod
    def forward(ctx: Any, vertices: Tensor, renderer: SilhouetteRenderer,
                run: Callable[[Tensor, int], tuple[float | Tensor, Tensor, Tensor]]
                ) -> tuple[Tensor, Tensor]:
        total, coverage, grad_vertices = run(vertices.detach(), renderer._next_call())
        ctx.save_for_backward(grad_vertices.to(dtype=vertices.dtype, device=vertices.device))
        coverage = coverage.to(dtype=vertices.dtype, device=vertices.device)
        ctx.mark_non_differentiable(coverage)
        if isinstance(total, Tensor):
            return total.to(dtype=vertices.dtype, device=vertices.device), coverage
        return vertices.new_tensor(total), coverage

    @staticmethod
    def backward(ctx: Any, grad_loss: Tensor, grad_coverage: Tensor | None
                 ) -> tuple[Tensor, None, None]:
        (grad_vertices,) = ctx.saved_tensors
        return grad_vertices * grad_loss, None, None


def assembly_camera_vertices(assembly: Assembly, rotation: Tensor, translation: Tensor,
                             level: int = 3) -> tuple[Tensor, Tensor]:
    """Merged assembly meshes moved to the camera frame: vertices (B, N, 3), faces (F, 3).

    Args:
        assembly: :class:`sq_mitsuba.geometry.assembly.Assembly` of batch size B or 1 (broadcast).
        rotation: (B, 3, 3) body-to-camera rotations R.
        translation: (B, 3) body-to-camera translations t: ``x_cam = R x_body + t``.
        level: icosphere subdivision level of each primitive's mesh (3: 642 vertices).

    Raises:
        ValueError: naming ``rotation`` where it is no rotation (a scaled matrix would draw
            a scaled assembly: a value check), ``translation`` or ``assembly``.
    """
    check_rotations("rotation", rotation)
    check_tensor("translation", translation, (3,), min_dims=2)
    if rotation.dim() != 3 or translation.dim() != 2 or rotation.shape[0] != translation.shape[0]:
        raise ValueError(f"rotation, translation: expected (B, 3, 3) and (B, 3), got "
                         f"{tuple(rotation.shape)} and {tuple(translation.shape)}")
    vertices, faces = assembly.merged_mesh(level)  # (A, N, 3), (F, 3)
    count = rotation.shape[0]
    if vertices.shape[0] not in (1, count):
        raise ValueError(f"assembly: batch size {vertices.shape[0]} does not match the "
                         f"{count} poses")
    vertices = vertices.to(rotation.dtype).expand(count, -1, -1)
    camera_vertices = torch.einsum("bij,bnj->bni", rotation, vertices) + translation[:, None, :]
    return camera_vertices, faces


def render_assembly(assembly: Assembly, rotation: Tensor, translation: Tensor,
                    renderer: SilhouetteRenderer, level: int = 3) -> Tensor:
    """Silhouettes (B, H, W) of superquadric assemblies at camera poses.

    Args: see :func:`assembly_camera_vertices`; ``renderer`` draws them.

    Returns:
        (B, H, W) coverage, differentiable w.r.t. the assembly parameters and the pose.
    """
    vertices, faces = assembly_camera_vertices(assembly, rotation, translation, level)
    return renderer.render(vertices, faces)


def render_assembly_loss(assembly: Assembly, rotation: Tensor, translation: Tensor,
                         renderer: SilhouetteRenderer, loss_fn: Callable[[Tensor, int], Tensor],
                         level: int = 3) -> tuple[Tensor, Tensor]:
    """``sum_i loss_fn(silhouette_i, i)`` with one BVH rebuild per item (see
    :meth:`SilhouetteRenderer.render_loss`); returns (loss, coverage (B, H, W) detached)."""
    vertices, faces = assembly_camera_vertices(assembly, rotation, translation, level)
    return renderer.render_loss(vertices, faces, loss_fn)
