"""Shared test configuration.

Threads: 2 when pytest runs alone (the reference machine has 2 cores); ``make test`` runs the
files in one pytest-xdist worker process per core (``-n <cores> --dist loadfile``, so each
file's module fixtures are built once) with the cores shared out between the workers (see
:func:`_threads_per_process`). Fixtures that build Mitsuba scenes are
session-scoped: the first kernels compile for seconds, later renders reuse them.

Device (in the style of kornia's conftest): ``pytest --device cpu|cuda`` (default ``cpu``)
chooses the torch device of the tests that take the :func:`device` fixture: the torch code
that runs on a GPU in training (network forward and backward, the losses, the superquadric and
rotation maths, the nearest-neighbour gathers, the loss terms). Such a test builds its inputs
as before (on the CPU, from the same seeds) and moves them and its modules to ``device``, so
it asserts the same on either device. ``pytest --device cuda`` on a machine without CUDA
skips those tests, with the reason, and runs the others on the CPU as usual; on the GPU,
float32 matrix products and convolutions keep full float32 precision (no TF32), so the
tolerances written for the CPU still hold::

    pytest --device cuda tests/test_network.py tests/test_losses.py
    pytest --device cuda -m "not slow"        # the inner loop, on the GPU
"""

from __future__ import annotations

import os

import pytest
import torch


def _threads_per_process() -> int:
    """Threads for one test process: 2 when pytest runs alone (the reference machine's
    cores); under pytest-xdist (``make test`` runs ``-n <cores>``) the cores shared out
    between its worker processes, at least one each. Two processes with two threads each on
    two cores are several times slower than one thread each: torch's threads wait for each
    other at every operation while the other process holds a core."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers is None:
        return 2
    cores = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
             else os.cpu_count() or 1)  # the cores this process may use (Linux), else all
    return max(1, cores // int(workers))


THREADS = _threads_per_process()
torch.set_num_threads(THREADS)
if os.environ.get("PYTEST_XDIST_WORKER"):
    # The same for Dr.Jit's thread pool and for every process a test starts (torch reads
    # OMP_NUM_THREADS when it loads).
    os.environ["OMP_NUM_THREADS"] = str(THREADS)
    import drjit

    drjit.set_thread_count(THREADS)

DEVICES = ("cpu", "cuda")


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--device", action="store", default="cpu", choices=DEVICES,
        help="torch device of the tests that take the `device` fixture (default: cpu); "
             "with cuda and no CUDA here, those tests are skipped")


def pytest_report_header(config: pytest.Config) -> str:
    return f"torch device of device-aware tests: {config.getoption('--device')}"


@pytest.fixture(scope="session")
def device(request: pytest.FixtureRequest) -> torch.device:
    """The ``torch.device`` of ``--device``; skips the test when it is CUDA and none is here."""
    name = request.config.getoption("--device")
    if name == "cuda":
        if not torch.cuda.is_available():
            why = ("this torch build has no CUDA" if torch.version.cuda is None
                   else "no CUDA device is visible")
            pytest.skip(f"--device cuda: CUDA is not available ({why}; torch "
                        f"{torch.__version__})")
        # Full float32 precision, as on the CPU: the tests' tolerances assume it.
        torch.backends.cuda.matmul.allow_tf32 = False
        torch.backends.cudnn.allow_tf32 = False
    return torch.device(name)


# --- silhouette renderer fixtures (issue 3) -------------------------------------------------


@pytest.fixture(scope="session")
def off_centre_camera():
    """128 x 128 camera with an off-centre principal point (tests the sensor's offsets)."""
    from sq_mitsuba.geometry.camera import Camera

    return Camera(150.0, 150.0, 70.0, 57.0, 128, 128)


@pytest.fixture(scope="session")
def precise_renderer(off_centre_camera):
    """High-sample renderer (spp 256, sppp 16) at 128 x 128 for pixel and gradient checks."""
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    return SilhouetteRenderer(off_centre_camera, spp=256, sppp=16, seed=11)


@pytest.fixture(scope="session")
def renderer64():
    """Default renderer at 64 x 64 with the default camera."""
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer

    return SilhouetteRenderer(Camera.default(64))


@pytest.fixture(scope="session")
def unit_sphere():
    """Level-4 icosphere (2,562 vertices): vertices (V, 3) float64, faces (F, 3) int64."""
    from sq_mitsuba.geometry.icosphere import icosphere

    vertices, faces = icosphere(4)
    return torch.tensor(vertices, dtype=torch.float64), torch.tensor(faces, dtype=torch.int64)


# --- training fixture (learning issue: tests/test_train.py, test_cache.py) ------------------


TRAIN_FIXTURE_IMAGES = 10
"""Images per model of :func:`train_dataset`: the val split takes images 4 and 9 (the SPE3R
rule, [0.4 n, 0.5 n) and [0.9 n, n)), the train split the other 8."""


@pytest.fixture(scope="session")
def train_dataset(tmp_path_factory):
    """A tiny SPE3R-layout dataset for training tests, built once per session: three generated
    spacecraft (two train, one test), 10 path-traced 64 px images each (spp 4)."""
    from sq_mitsuba.data.library import generate_model
    from sq_mitsuba.data.spacecraft import catalogue
    from sq_mitsuba.data.spe3r import RenderOptions, render_dataset

    models = tmp_path_factory.mktemp("train_models")
    entries = catalogue(3, 5)
    for entry in entries:
        generate_model(entry, models, points=3000)
    splits = [(entries[0].name, "train"), (entries[1].name, "train"), (entries[2].name, "test")]
    (models / "splits.csv").write_text("".join(f"{m},{s}\n" for m, s in splits))
    out = tmp_path_factory.mktemp("train_data") / "data"
    options = RenderOptions(images_per_model=TRAIN_FIXTURE_IMAGES, seed=5, resolution=64, spp=4)
    summary = render_dataset(models, out, options, progress=False)
    assert not summary.failures
    return out


# --- evaluation fixture (tests/test_evaluate.py, test_predict.py, test_study.py) ------------


EVAL_NETWORK = {"image_size": 64, "num_primitives": 2, "latent_dim": 32, "hidden_dim": 32}
"""The tiny network of :func:`eval_checkpoint` (NetworkConfig fields)."""


@pytest.fixture(scope="session")
def eval_checkpoint(train_dataset, tmp_path_factory):
    """A tiny trained checkpoint ``<tmp>/tiny_run/checkpoint.pt``: a 64 px network with M = 2
    (:data:`EVAL_NETWORK`), 8 Adam steps on the 16 training images of :func:`train_dataset`
    with a Chamfer-L2 + SPEED pose loss, written with ``checkpoint_payload`` /
    ``write_checkpoint`` (dataset camera, config name "tiny")."""
    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.model.checkpoint import checkpoint_payload, write_checkpoint
    from sq_mitsuba.model.losses import chamfer_loss, pose_loss
    from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

    dataset = Spe3rDataset(train_dataset, "train", image_size=64, num_surface=500,
                           num_occupancy=2)
    items = [dataset[i] for i in range(len(dataset))]
    batch = {key: torch.stack([item[key] for item in items])
             for key in ("image", "camera", "rotation", "translation", "surface_points")}
    # One thread: as fast for this tiny network, and it stays fast when other processes share
    # the cores (two threads then wait for each other at every operation, ~20x slower here).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    with torch.random.fork_rng():
        torch.manual_seed(0)
        network = SuperquadricNet(NetworkConfig(**EVAL_NETWORK))
        optimizer = torch.optim.Adam(network.parameters(), lr=1e-3)
        network.train()
        for _ in range(8):
            optimizer.zero_grad()
            output = network(batch["image"], batch["camera"])
            points, inside = output.assembly.surface_points_with_mask(2)
            size = points.shape[0]
            chamfer = chamfer_loss(points.reshape(size, -1, 3), (~inside).reshape(size, -1),
                                   batch["surface_points"])
            rotation, translation = pose_loss(output.rotation, output.translation,
                                              batch["rotation"], batch["translation"])
            (chamfer + rotation.mean() + translation.mean()).backward()
            optimizer.step()
    torch.set_num_threads(threads)
    path = tmp_path_factory.mktemp("eval_checkpoint") / "tiny_run" / "checkpoint.pt"
    path.parent.mkdir()
    write_checkpoint(path, checkpoint_payload(network.eval(), dataset.camera, {"name": "tiny"},
                                              step=8))
    return path
