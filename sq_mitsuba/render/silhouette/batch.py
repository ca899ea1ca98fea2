"""Forward silhouettes of one mesh seen from many poses, in one Mitsuba launch per chunk.

Scoring pose hypotheses needs hundreds of silhouettes of *one* shape, without gradients. A
silhouette is the same whether the object turns by R about the camera or the camera turns by
R^T about the object, so :class:`PoseSilhouettes` keeps the mesh fixed in its body frame
(one Mitsuba scene, one BVH per shape) and casts, for every pose (R, t) and pixel sample, the
camera ray moved into the body frame:

    origin = -R^T t,   direction = R^T ((u - cx) / fx, (v - cy) / fy, 1)

(``x_cam = R x_body + t``, OpenCV camera frame). All views' rays go to Mitsuba's
``Scene.ray_test`` in one Dr.Jit kernel (rays built from a few gathers, the visibility test,
a block sum over a pixel's samples), so the cost grows with the number of rays only.

Measured (busy 2-core machine, ``sq-mitsuba bench eval`` has the current figures): 256 views
at 32 x 32 px, 1 sample per pixel, in about 0.1 s; Mitsuba's ``batch`` sensor (one sub-sensor
per view) took 0.3 s for the same and grows faster with the views (a virtual call per
sub-sensor), and the differentiable
:class:`~sq_mitsuba.render.silhouette.renderer.SilhouetteRenderer` rebuilds the BVH for every
view (12-25 ms each).

Convention: pixel (i, j) covers [j, j + 1) x [i, i + 1) in (u, v); with ``spp = 1`` its one
sample is the pixel centre (a point-sampled mask, no noise), with more the samples are uniform
in the pixel. Every view uses the same sub-pixel positions (drawn from the seed and the call),
so the difference between two views' scores is never sampling noise. Geometry behind the
camera is invisible (rays start at the camera's centre and run forward).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from sq_mitsuba.checks import check_int, check_tensor
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.render.backend import interrupts_deferred, mitsuba
from sq_mitsuba.render.silhouette.seeds import CALL_SEED_STRIDE

__all__ = ["PoseSilhouettes"]

MESH_ID = "pose_mesh"
#: Rays per Dr.Jit launch at most (bounds memory: about 100 bytes per ray in flight).
DEFAULT_MAX_RAYS = 1 << 22


class PoseSilhouettes:
    """Coverage images of one body-frame mesh at many camera poses (forward only).

    Args:
        camera: intrinsics and resolution of the images.
        spp: samples per pixel (1: the pixel centre; more: uniform in the pixel, coverage in
            steps of ``1 / spp``).
        seed: base seed of the sub-pixel positions (with ``spp > 1``).
        max_rays: rays per launch at most; more views are rendered in several launches.
    """

    def __init__(self, camera: Camera, spp: int = 1, seed: int = 0,
                 max_rays: int = DEFAULT_MAX_RAYS) -> None:
        if not isinstance(camera, Camera):
            raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
        spp, max_rays = check_int("spp", spp), check_int("max_rays", max_rays)
        self.camera, self.spp, self.seed = camera, spp, int(seed) & 0xFFFFFFFF
        self.max_rays = max_rays
        self._mi = mitsuba()
        self._scene: Any = None
        self._params: Any = None
        self._topology: tuple[int, bytes] | None = None
        self._calls = 0
        self.scenes_built = 0

    def __repr__(self) -> str:
        c = self.camera
        return f"PoseSilhouettes({c.width}x{c.height}, spp={self.spp})"

    def render(self, vertices: Tensor, faces: Tensor, rotation: Tensor,
               translation: Tensor) -> Tensor:
        """Coverage (N, H, W) float32 in [0, 1] of the mesh at N poses.

        Args:
            vertices: (V, 3) body-frame vertices of one mesh.
            faces: (F, 3) integer indices into V.
            rotation: (N, 3, 3) body-to-camera rotations R (N >= 1).
            translation: (N, 3) or (3,) body-to-camera translations t (``x_cam = R x + t``).

        Returns:
            (N, H, W) float32 CPU tensor: pixel (i, j) of view k is the fraction of its samples
            whose camera ray meets the mesh.
        """
        check_tensor("vertices", vertices, (None, 3), min_dims=2)
        check_tensor("rotation", rotation, (3, 3), min_dims=3)
        check_tensor("translation", translation, (3,))
        if vertices.dim() != 2 or vertices.shape[0] < 3:
            raise ValueError(f"vertices: expected shape (V, 3) with V >= 3, got "
                             f"{tuple(vertices.shape)}")
        if rotation.dim() != 3 or rotation.shape[0] < 1:
            raise ValueError(f"rotation: expected shape (N, 3, 3) with N >= 1, got "
                             f"{tuple(rotation.shape)}")
        count = rotation.shape[0]
        if translation.dim() == 1:
            translation = translation.expand(count, 3)
        if tuple(translation.shape) != (count, 3):
            raise ValueError(f"translation: expected shape ({count}, 3) or (3,), got "
                             f"{tuple(translation.shape)}")
        with interrupts_deferred():  # Ctrl-C waits for Mitsuba (see interrupts_deferred)
            self._load(vertices, faces)
        self._calls += 1
        pixels = self.camera.height * self.camera.width
        per_launch = max(1, self.max_rays // (pixels * self.spp))
        rotation = rotation.detach().to("cpu", torch.float64)
        translation = translation.detach().to("cpu", torch.float64)
        images = []
        for start in range(0, count, per_launch):
            with interrupts_deferred():
                images.append(self._launch(rotation[start:start + per_launch],
                                           translation[start:start + per_launch]))
        return torch.cat(images).reshape(count, self.camera.height, self.camera.width)

    # ------------------------------------------------------------------ internals

    def _load(self, vertices: Tensor, faces: Tensor) -> None:
        """Put the mesh in the scene: vertices swapped when the faces are the last ones, a new
        scene otherwise."""
        mi = self._mi
        from sq_mitsuba.render.silhouette.renderer import _check_faces

        faces_np = _check_faces(faces, vertices.shape[0])
        key = (vertices.shape[0], faces_np.tobytes())
        positions = mi.Float(np.ascontiguousarray(
            vertices.detach().to("cpu", torch.float32).numpy()).ravel())
        if self._topology != key:
            self._scene = self._params = None
            mesh = mi.Mesh(MESH_ID, vertex_count=vertices.shape[0],
                           face_count=faces_np.shape[0], has_vertex_normals=False,
                           has_vertex_texcoords=False)
            mesh_params = mi.traverse(mesh)
            mesh_params["vertex_positions"] = positions
            mesh_params["faces"] = mi.UInt32(faces_np.ravel())
            mesh_params.update()
            self._scene = mi.load_dict({"type": "scene", MESH_ID: mesh})
            self._params = mi.traverse(self._scene)
            self._params.keep([f"{MESH_ID}.vertex_positions"])
            self._topology = key
            self.scenes_built += 1
            return
        self._params[f"{MESH_ID}.vertex_positions"] = positions
        self._params.update()

    def _launch(self, rotation: Tensor, translation: Tensor) -> Tensor:
        """Coverage (n * H * W,) of n views, one Dr.Jit launch."""
        mi = self._mi
        import drjit as dr

        camera, spp = self.camera, self.spp
        views = rotation.shape[0]
        pixels = camera.height * camera.width
        inverse = rotation.transpose(-1, -2)  # R^T: camera-frame directions to the body frame
        origins = -(inverse @ translation[..., None])[..., 0]
        matrices = mi.Float(np.ascontiguousarray(inverse.reshape(-1).float().numpy()))
        centres = mi.Float(np.ascontiguousarray(origins.reshape(-1).float().numpy()))
        # Opaque values: one compiled kernel serves every view count, camera and seed.
        per_view = dr.opaque(mi.UInt32, pixels * spp)
        index = dr.arange(mi.UInt32, views * pixels * spp)
        view = index // per_view
        sample = index - view * per_view  # pixel * spp + sub-sample
        pixel = sample // dr.opaque(mi.UInt32, spp)
        row = pixel // dr.opaque(mi.UInt32, camera.width)
        column = pixel - row * dr.opaque(mi.UInt32, camera.width)
        if spp == 1:
            du = dv = dr.opaque(mi.Float, 0.5)
        else:
            # A hash of (pixel and sub-sample, call): the same in every view. (A PCG32 of
            # views x pixels lanes would give every lane, so every view, its own stream.)
            state = (2 * (self.seed + CALL_SEED_STRIDE * self._calls)) & 0xFFFFFFFF
            du = mi.sample_tea_float32(sample, dr.opaque(mi.UInt32, state))
            dv = mi.sample_tea_float32(sample, dr.opaque(mi.UInt32, (state + 1) & 0xFFFFFFFF))
        x = (mi.Float(column) + du - dr.opaque(mi.Float, camera.cx)) / dr.opaque(
            mi.Float, camera.fx)
        y = (mi.Float(row) + dv - dr.opaque(mi.Float, camera.cy)) / dr.opaque(
            mi.Float, camera.fy)

        def entry(array: Any, stride: int, k: int) -> Any:
            return dr.gather(mi.Float, array, view * stride + k)

        direction = mi.Vector3f(*[entry(matrices, 9, 3 * r) * x + entry(matrices, 9, 3 * r + 1)
                                  * y + entry(matrices, 9, 3 * r + 2) for r in range(3)])
        origin = mi.Point3f(*[entry(centres, 3, k) for k in range(3)])
        hit = dr.select(self._scene.ray_test(mi.Ray3f(origin, direction)), 1.0, 0.0)
        coverage = dr.block_sum(hit, spp) / spp if spp > 1 else hit
        return torch.from_numpy(np.array(coverage, dtype=np.float32))
