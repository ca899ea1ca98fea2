"""``sq-mitsuba doctor``: versions, Mitsuba variant, LLVM and device, with a one-line verdict."""

from __future__ import annotations

import argparse
import platform


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "doctor", help="print versions, Mitsuba variant, LLVM version and device",
        description="Check that a Mitsuba variant runs here; print what the renderer uses.")
    parser.add_argument("--render", action="store_true",
                        help="also render and differentiate one small silhouette")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import numpy
    import torch

    from sq_mitsuba.render.backend import BackendError, describe

    rows = {"python": platform.python_version(), "torch": torch.__version__,
            "numpy": numpy.__version__}
    try:
        rows.update(describe())
    except (BackendError, RuntimeError) as error:
        for key, value in rows.items():
            print(f"{key:>14}: {value}")
        raise ValueError(str(error)) from None
    if args.render:
        rows["silhouette"] = _render_check()
    for key, value in rows.items():
        print(f"{key:>14}: {value}")
    print("ok: the renderer can run")
    return 0


def _render_check() -> str:
    import time

    import torch

    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.geometry.icosphere import icosphere
    from sq_mitsuba.render.silhouette import SilhouetteRenderer

    vertices, faces = icosphere(3)
    points = (torch.tensor(vertices, dtype=torch.float32) * 0.3
              + torch.tensor([0.0, 0.0, 2.0]))[None].requires_grad_(True)
    renderer = SilhouetteRenderer(Camera.default(64))
    start = time.perf_counter()
    coverage = renderer.render(points, torch.tensor(faces))
    coverage.sum().backward()
    seconds = time.perf_counter() - start
    finite = bool(torch.isfinite(points.grad).all())
    return (f"64 x 64 sphere: {float(coverage.detach().sum()):.1f} px covered, gradient "
            f"{'finite' if finite else 'NOT finite'}, {seconds:.2f} s (first call compiles)")
