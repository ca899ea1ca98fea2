"""The worker side of :class:`~sq_mitsuba.render.silhouette.workers.SilhouetteWorkers`: the
process that ``python -m sq_mitsuba.render.silhouette.worker_process FD`` starts holds one
:class:`~sq_mitsuba.render.silhouette.renderer.SilhouetteRenderer` on one Dr.Jit thread and answers
requests over the socket ``FD`` until told to stop (see the pool's module for the protocol)."""

from __future__ import annotations

import os
import sys
from multiprocessing.connection import Connection

import numpy as np
import torch

from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.processes import ignore_group_signals
from sq_mitsuba.render.backend import mitsuba
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer


def serve(connection: Connection) -> None:
    """A worker's life: settings, then requests until ``None``."""
    settings = connection.recv()
    try:
        torch.set_num_threads(1)
        mitsuba(settings["variant"])
        import drjit as dr

        dr.set_thread_count(1)
        renderer = SilhouetteRenderer(Camera(**settings["camera"]), spp=settings["spp"],
                                      sppp=settings["sppp"],
                                      integrator=settings["integrator"])
    except Exception as error:  # reported to the parent, which raises it
        connection.send(("error", f"startup failed: {type(error).__name__}: {error}"))
        return
    connection.send(("ok", "ready"))
    while True:
        try:
            request = connection.recv()
        except EOFError:  # the parent is gone
            return
        except Exception as error:  # e.g. a loss function this process cannot import
            connection.send(("error", f"bad request: {type(error).__name__}: {error}"))
            continue
        if request is None:
            return
        seed, call, first, vertices, faces, targets, loss, requires_grad = request
        try:
            vertices = torch.from_numpy(vertices)
            renderer.seed = seed
            renderer._prepare(vertices, torch.from_numpy(faces.astype(np.int64)))
            losses, coverage, grad = renderer.target_loss_items(
                vertices, torch.from_numpy(targets), call,
                range(first, first + vertices.shape[0]), loss, requires_grad)
            connection.send(("ok", (losses.numpy(), coverage.numpy(), grad.numpy())))
        except Exception as error:
            connection.send(("error", f"{type(error).__name__}: {error}"))


if __name__ == "__main__":
    # Ctrl-C and SIGTERM to the group are the parent's: it finishes its step with the
    # workers' help, then closes them; a worker ends when its parent's socket closes.
    ignore_group_signals()
    serve(Connection(int(sys.argv[1])))
    os._exit(0)  # skip interpreter teardown of Dr.Jit's thread pool
