"""Lean Mitsuba integrators for black meshes before an environment: ``silhouette_projective``
(differentiable, for training) and ``target_coverage`` (the dataset's mask pass).

:class:`SilhouetteRenderer`'s scene is a black, non-emitting mesh in front of a constant
environment, seen with ``max_depth = 1``. There a camera ray's radiance is the environment's
where it escapes and zero where it hits the mesh, so a path tracer's loop (BSDF sampling,
emitter sampling, Russian roulette) has nothing to add. ``prb_projective`` still traces that
loop, in Python, for the primal image and twice per silhouette sample of the backward pass (the
radiance on either side of the edge): most of a 128 x 128 backward pass went to it.

This integrator is a :class:`PathProjectiveIntegrator` (``prb_projective``) whose radiance
estimates are one ray-visibility test each; the silhouette sampling, its Jacobian and the
splatting of gradients are Mitsuba's own. It renders the same images and gradients as
``prb_projective`` for scenes of this kind (tested against it) and is wrong for any other:
only non-emitting shapes, one environment emitter, ``max_depth = 1``.

``target_coverage`` is the same shortcut without gradients, for the mask pass of the dataset
renderer (:class:`~sq_mitsuba.render.space.SpaceScene`: the target's mesh before a constant
environment, at many stratified samples per pixel, the coverage being one minus the pixel
value). Mitsuba's ``path`` with ``max_depth = 1`` renders that right, but its kernel still
carries the whole path-tracing loop, masked off lane by lane; at 256 samples per pixel it was
90 % of the time of a 128 px dataset image. ``target_coverage`` renders the same coverage bit
for bit (tested, also inside the ``aov`` integrator that adds depth, whose depth then agrees
to float32 rounding) in a third of the time (``sq-mitsuba bench dataset``).
"""

from __future__ import annotations

from typing import Any

from sq_mitsuba.render.backend import interrupts_deferred, mitsuba

PLUGIN = "silhouette_projective"
COVERAGE_PLUGIN = "target_coverage"
#: ``silhouette_projective`` for a scene of many items in tiles of one film
#: (:mod:`sq_mitsuba.render.silhouette.tiled`): the silhouette samples shared equally by items.
TILED_PLUGIN = "silhouette_projective_tiled"
#: The variants the integrators are registered in: Mitsuba keeps plugins per variant, so a
#: process that changes variant registers them again.
_registered: set[str] = set()


def register() -> None:
    """Register the ``silhouette_projective``, ``silhouette_projective_tiled`` and
    ``target_coverage`` integrators with Mitsuba in the active variant (idempotent; sets up
    the variant first)."""
    mi = mitsuba()
    if mi.variant() in _registered:
        return
    import drjit as dr

    # Importing Mitsuba's AD integrators compiles their @dr.syntax functions: Ctrl-C there
    # would come out as a RuntimeError holding the generated code (see interrupts_deferred).
    with interrupts_deferred():
        from mitsuba.ad.integrators.prb_projective import PathProjectiveIntegrator

    def environment_radiance(scene: Any, ray: Any, escaped: Any) -> Any:
        """The environment's radiance (Spectrum) along ``ray`` where ``escaped``, else 0."""
        environment = scene.environment()
        if environment is None:
            return mi.Spectrum(0.0)
        interaction = dr.zeros(mi.SurfaceInteraction3f)
        interaction.wi = -ray.d
        interaction.wavelengths = ray.wavelengths
        return dr.select(escaped, environment.eval(interaction, escaped), 0.0)

    class SilhouetteProjectiveIntegrator(PathProjectiveIntegrator):
        """``prb_projective`` for a black mesh against an environment (see the module)."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            if self.max_depth != 1:
                raise ValueError(f"{PLUGIN}: max_depth must be 1, got {self.max_depth}")

        def sample(self, mode: Any, scene: Any, sampler: Any, ray: Any, depth: Any,
                   δL: Any, state_in: Any, active: Any, project: bool = False,
                   si_shade: Any = None, **kwargs: Any) -> tuple[Any, Any, list, Any]:
            if project:
                raise ValueError(f"{PLUGIN}: indirect silhouettes (sppi > 0) are not supported")
            active = mi.Bool(active)
            if si_shade is not None:  # starts on a surface, which emits nothing
                return mi.Spectrum(0.0), active, [], mi.Spectrum(0.0)
            escaped = active & ~scene.ray_test(mi.Ray3f(dr.detach(ray)), active)
            radiance = environment_radiance(scene, ray, escaped)
            return radiance, active, [], radiance

        def sample_radiance_difference(self, scene: Any, ss: Any, curr_depth: Any,
                                       sampler: Any, wavelengths: Any,
                                       active: Any) -> tuple[Any, Any]:
            # Foreground: the black surface at the silhouette point, 0. Background: the ray
            # grazing past the edge, the environment if it escapes.
            ray = ss.spawn_ray(wavelengths)
            escaped = active & ~scene.ray_test(ray, active)
            difference = -environment_radiance(scene, ray, escaped)
            return difference, escaped & (dr.max(dr.abs(difference)) > 0)

    class TargetCoverageIntegrator(mi.SamplingIntegrator):
        """The environment where a camera ray escapes, zero where it is blocked."""

        def sample(self, scene: Any, sampler: Any, ray: Any, medium: Any = None,
                   active: Any = True, **kwargs: Any) -> tuple[Any, Any, list]:
            active = mi.Bool(active)
            escaped = active & ~scene.ray_test(ray, active)
            return environment_radiance(scene, ray, escaped), active, []

    class TiledDetail(mi.ad.ProjectiveDetail):
        """Primary silhouette sampling of a tiled scene: each item gets an equal share.

        Mitsuba weights a silhouette edge by the angle it subtends at the viewpoint. In a
        tiled scene an item is sheared towards its tile, so far tiles subtend smaller angles
        and would get fewer samples. Here an edge's weight is its angle in the item's own,
        unsheared frame (what a one-item scene uses), normalised so every active item has
        total weight 1: an item's expected sample count and their spread along its edges
        are those of its own render. Any positive weights are unbiased (the pdf uses them).
        """

        layout: Any = None
        "Set by the tiled renderer before a backward pass: see ``TiledIntegrator``."

        def init_primarily_visible_silhouette(self, scene: Any, sensor: Any) -> None:
            layout = self.layout
            if layout is None:  # not tiled: Mitsuba's own weights
                super().init_primarily_visible_silhouette(scene, sensor)
                return
            (mesh,) = scene.silhouette_shapes()
            indices, _ = mesh.precompute_silhouette(mi.ScalarPoint3f(0.0))
            face = indices // 3
            corner = indices - 3 * face
            following = dr.select(corner == 2, face * 3, indices + 1)
            start = dr.gather(mi.UInt32, layout.faces, indices)
            end = dr.gather(mi.UInt32, layout.faces, following)
            p0 = dr.gather(mi.Point3f, layout.positions, start)
            p1 = dr.gather(mi.Point3f, layout.positions, end)
            weight = dr.unit_angle(dr.normalize(p0), dr.normalize(p1))
            item = face // layout.faces_per_item
            active = dr.gather(mi.Bool, layout.active, item)
            weight = dr.select(active & dr.isfinite(weight), weight, 0.0)
            totals = dr.zeros(mi.Float, layout.items)
            dr.scatter_reduce(dr.ReduceOp.Add, totals, weight, item)
            total = dr.gather(mi.Float, totals, item)
            weight = dr.select(total > 0, weight / total, 0.0)
            self.primary_indices = [indices]
            self.primary_distributions = [mi.DiscreteDistribution(weight)]
            self.primary_shape_distribution = mi.DiscreteDistribution(mi.Float([1.0]))

    class TiledIntegrator(SilhouetteProjectiveIntegrator):
        """``silhouette_projective`` whose primary silhouette samples are shared equally by
        the items of a tiled scene. Its ``layout`` (None: Mitsuba's weights) has ``faces``
        (UInt32, the scene mesh's faces), ``positions`` (Float, each item's vertices in its
        own frame), ``faces_per_item``, ``items`` and ``active`` (Bool per item: False gives
        an item no samples)."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            self.proj_detail = TiledDetail(self)

        @property
        def layout(self) -> Any:
            return self.proj_detail.layout

        @layout.setter
        def layout(self, value: Any) -> None:
            self.proj_detail.layout = value

    mi.register_integrator(PLUGIN, lambda props: SilhouetteProjectiveIntegrator(props))
    mi.register_integrator(TILED_PLUGIN, lambda props: TiledIntegrator(props))
    mi.register_integrator(COVERAGE_PLUGIN, lambda props: TargetCoverageIntegrator(props))
    _registered.add(mi.variant())
