"""``sq-mitsuba doctor``'s checks of the render backend: versions, variant, and one
differentiated silhouette against its exact area (kept apart from :mod:`sq_mitsuba.render.backend`,
which the silhouette renderer itself imports)."""

from __future__ import annotations

from sq_mitsuba.render.backend import BackendError, describe

#: Radius and distance of the self-test sphere (body units, camera frame).
_TEST_RADIUS, _TEST_DISTANCE = 0.3, 2.0


def render_self_test(resolution: int = 64) -> str:
    """Render and differentiate one sphere silhouette; a one-line report.

    Checks the covered area against the sphere's exact projection (a disc of radius
    ``f r / sqrt(d^2 - r^2)`` pixels, within 3 %: the mesh is a level-3 icosphere, and Monte
    Carlo noise at 16 spp is well below that) and that the vertex gradient is finite and not
    zero.

    Raises:
        BackendError: the render or its gradient is wrong (one line saying what).
    """
    import math
    import time

    import torch

    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.geometry.icosphere import icosphere
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    camera = Camera.default(resolution)
    vertices, faces = icosphere(3)
    points = (torch.tensor(vertices, dtype=torch.float32) * _TEST_RADIUS
              + torch.tensor([0.0, 0.0, _TEST_DISTANCE]))[None].requires_grad_(True)
    renderer = SilhouetteRenderer(camera)
    start = time.perf_counter()
    coverage = renderer.render(points, torch.tensor(faces))
    coverage.sum().backward()
    seconds = time.perf_counter() - start
    area = float(coverage.detach().sum())
    disc = camera.fx * _TEST_RADIUS / math.sqrt(_TEST_DISTANCE**2 - _TEST_RADIUS**2)
    expected = math.pi * disc * camera.fy / camera.fx * disc
    finite = bool(torch.isfinite(points.grad).all())
    line = (f"{resolution} x {resolution} sphere: {area:.1f} px covered (exact {expected:.1f}), "
            f"gradient {'finite' if finite else 'NOT finite'}, {seconds:.2f} s "
            "(first call compiles)")
    if abs(area - expected) > 0.03 * expected:
        raise BackendError(f"silhouette self-test failed: {line}")
    if not finite or not bool(points.grad.abs().sum() > 0):
        raise BackendError(f"silhouette self-test failed: gradient not finite or zero; {line}")
    return line


def diagnose(render: bool = False) -> tuple[dict[str, str], str | None]:
    """What ``sq-mitsuba doctor`` prints: (rows, error).

    Rows: Python, torch and numpy versions, then :func:`describe` and, with ``render``, the
    line of :func:`render_self_test`. ``error`` is None when a variant runs (and the self-test
    passed), else one line saying what failed; the rows gathered until then are kept.
    """
    import platform

    import numpy
    import torch

    rows = {"python": platform.python_version(), "torch": torch.__version__,
            "numpy": numpy.__version__}
    try:
        rows.update(describe())
        if render:
            rows["silhouette"] = render_self_test()
    except (BackendError, RuntimeError) as error:
        return rows, " ".join(str(error).split())
    return rows, None
