"""The Python API's inputs, as a sweep of its public calls found them (2026-12-02): a value no
caller means is refused in one line naming the argument, before any work; a value a caller
may mean (an integer mask, a numpy switch, a negative index, a batch past the network's chunk)
gives what its ordinary spelling gives.

References: the same call with the ordinary input (a bool mask, a non-negative index, one
network call on the whole batch)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import sq_mitsuba
from sq_mitsuba.config import ConfigError, validate
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.inference.fit import fit_assembly
from sq_mitsuba.inference.search import SearchOptions
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly


@pytest.fixture(scope="module")
def shipped():
    return sq_mitsuba.load_model()


@pytest.fixture(scope="module")
def views():
    """Masks (2, 32, 32) bool of one superquadric from two poses, their camera and poses."""
    camera = Camera.default(32)
    rotations = torch.eye(3, dtype=torch.float64).repeat(2, 1, 1)
    rotations[1] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    translations = torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64).repeat(2, 1)
    target = Assembly.from_values(torch.tensor([[[0.4, 0.2, 0.12]]], dtype=torch.float64),
                                  torch.tensor([[[0.3, 0.7]]], dtype=torch.float64))
    with torch.no_grad():
        masks = render_assembly(target, rotations, translations,
                                SilhouetteRenderer(camera, spp=16, seed=1)) > 0.5
    assert masks.any(dim=(1, 2)).all()
    return masks, camera, rotations, translations


def test_fit_reads_integer_masks_as_non_zero_and_refuses_floats_outside_0_1(views):
    """A 0/255 mask was fitted as a target 255 times as heavy (its loss 24,940 against 0.149)
    and, resized, a widened one: integers now read as the bool mask they spell."""
    masks, camera, rotations, translations = views
    settings = {"num_primitives": 1, "steps": 2, "resolution": 32}
    as_bool = fit_assembly(masks, camera, rotations, translations, **settings)
    as_bytes = fit_assembly(masks.to(torch.uint8) * 255, camera, rotations, translations,
                            **settings)
    torch.testing.assert_close(as_bytes.raw, as_bool.raw, rtol=0, atol=0)
    for bad in (masks.double() * 255, masks.double() * 2 - 1):
        with pytest.raises(ValueError, match=r"^masks: float values must lie in \[0, 1\], "):
            fit_assembly(bad, camera, rotations, translations, **settings)


def test_fit_names_a_camera_and_a_callback_that_are_not_ones(views):
    masks, camera, rotations, translations = views
    with pytest.raises(ValueError, match=r"^camera: expected a Camera .*got NoneType$"):
        fit_assembly(masks, None, rotations, translations, steps=1)
    with pytest.raises(ValueError, match=r"^callback: expected a function .*got int$"):
        fit_assembly(masks, camera, rotations, translations, steps=1, callback=5)


@pytest.mark.parametrize(("camera", "needle"), [
    (Camera(1e30, 1e30, 128.0, 128.0, 256, 256), r"fx = 1e\+30 gives a .* deg field of view"),
    (Camera(400.0, 400.0, -1e9, 128.0, 256, 256), r"the principal point \(-1e\+09, 128\) is far "
                                                  r"from the centre \(128, 128\)"),
    (Camera(400.0, 400.0, 128.0, 250.0, 256, 256), r"the principal point \(128, 250\) is far"),
    (Camera(1.0, 1.0, 128.0, 128.0, 256, 256), r"fx = 1 gives a 179 deg field of view"),
])
def test_predict_refuses_a_camera_no_camera_has(shipped, camera, needle):
    """Such a camera gave translations of inf or 6e6 m, refined or not; a camera file with the
    same matrix was refused already."""
    image = np.zeros((1, 256, 256), np.uint8)
    image[0, 100:150, 90:170] = 200
    with pytest.raises(ValueError, match=r"^camera: " + needle):
        shipped.predict(image, camera)


def test_a_sane_camera_of_any_size_reads_as_before(shipped):
    image = np.zeros((1, 256, 256), np.uint8)
    image[0, 100:150, 90:170] = 200
    given = shipped.predict(image, Camera.default(256))
    own = shipped.predict(image)  # the predictor's camera, rescaled: the same field of view
    torch.testing.assert_close(given.translation, own.translation)


def test_options_given_as_empty_tables_are_refused_not_taken_as_the_defaults(shipped):
    image = np.zeros((2, 64, 64), np.uint8)
    image[:, 20:40, 16:48] = 200
    with pytest.raises(ValueError, match=r"^search: expected a SearchOptions, got dict"):
        shipped.predict_sequence(image, search={})
    with pytest.raises(ValueError, match=r"^refinement: expected a RefineOptions, got dict"):
        shipped.predict(image, refine=True, refinement={})


def test_load_model_switches_are_bools_numpy_ones_included():
    for bad in ("yes", 1, 0.0):
        with pytest.raises(ValueError, match=rf"^fast: expected True or False, got {bad!r}$"):
            sq_mitsuba.load_model(fast=bad)
    with pytest.raises(ValueError, match=r"^traced: expected True or False"):
        sq_mitsuba.load_model(fast=True, traced="no")
    assert sq_mitsuba.load_model(fast=np.bool_(True)).fast


def test_given_relative_rotations_must_be_real(shipped):
    image = np.zeros((2, 64, 64), np.uint8)
    image[:, 20:40, 16:48] = 200
    relative = torch.eye(3, dtype=torch.complex64).repeat(2, 1, 1)
    with pytest.raises(ValueError, match=r"^relative_rotations: expected \(2, 3, 3\) real .* "
                                         r"torch.complex64$"):
        shipped.predict_sequence(image, relative_rotations=relative)


def test_a_config_refuses_numpy_numbers_saying_which_python_type_to_give():
    with pytest.raises(ConfigError, match=r"^grid: expected an integer, got np.int64\(64\) "
                                          r"\(numpy's: give int\(\.\.\.\)\)$"):
        validate(SearchOptions(grid=np.int64(64)))


def test_dataset_items_index_as_a_list_does(train_dataset):
    """``ds[-1]`` failed inside numpy (its points' seed negative), ``ds[torch.tensor(1)]`` in
    numpy's SeedSequence, and a seed of -1 or 0.5 only at the first item."""
    from sq_mitsuba.data.spe3r import Spe3rDataset

    dataset = Spe3rDataset(train_dataset, "val", image_size=32, num_surface=20,
                           num_occupancy=20)
    last = len(dataset) - 1
    for same in (-1, np.int64(last), torch.tensor(last)):
        item = dataset[same]
        torch.testing.assert_close(item["surface_points"], dataset[last]["surface_points"])
        assert item["index"] == dataset[last]["index"]
    with pytest.raises(IndexError, match=rf"^item: {len(dataset)} out of range for the "
                                         rf"{len(dataset)} items of "):
        dataset[len(dataset)]
    with pytest.raises(TypeError, match=r"^item: expected an integer, got float$"):
        dataset[0.0]
    for seed in (-1, 0.5, "a", True):
        with pytest.raises(ValueError, match=r"^seed: expected an integer >= 0, got "):
            Spe3rDataset(train_dataset, "val", seed=seed)
    assert Spe3rDataset(train_dataset, "val", seed=np.int64(3)).seed == 3


def test_a_batch_past_the_networks_chunk_reads_as_one_call(shipped, monkeypatch):
    """More than RUN_CHUNK images (B x turned copies: 360 copies of 16 images asked for 26 GB
    in one call) run in chunks, their outputs joined as one call's, to float rounding."""
    import sq_mitsuba.inference.predictor as predictor_module
    from sq_mitsuba.inference.traced import run_in_chunks

    rng = np.random.default_rng(0)
    images = np.zeros((5, 64, 64), np.uint8)
    for k in range(5):
        top, left = rng.integers(8, 30, 2)
        images[k, top:top + 24, left:left + 30] = rng.integers(80, 255)
    whole = shipped.predict(images, turns=4)  # 20 turned copies: chunks of 2
    monkeypatch.setattr(predictor_module, "RUN_CHUNK", 2)
    chunked = shipped.predict(images, turns=4)
    for field in ("rotation", "translation", "rotation_hypotheses", "rotation_scores", "mask"):
        torch.testing.assert_close(getattr(chunked, field), getattr(whole, field),
                                   atol=1e-4, rtol=1e-4, msg=field)
    torch.testing.assert_close(chunked.assembly.params, whole.assembly.params, atol=1e-4,
                               rtol=1e-4)
    # A chunk as large as the batch is the one call itself, every field.
    x = torch.rand(3, 1, 96, 96)
    matrix = Camera.default(96).matrix()
    network = shipped.model.eval()
    with torch.inference_mode():
        one, joined = network(x, matrix), run_in_chunks(network, x, matrix, chunk=3)
    for field in dataclasses.fields(one):
        assert (getattr(one, field.name) is None) == (getattr(joined, field.name) is None)
        if getattr(one, field.name) is not None:
            assert torch.equal(getattr(one, field.name), getattr(joined, field.name))


@pytest.mark.parametrize("resolution", [-5, 0, 2.5, True, 8])
def test_process_mesh_refuses_a_fusion_resolution_before_any_work(resolution):
    """-5 failed as a reshape inside the depth renderer; 2.5 and 0 were taken."""
    import trimesh

    from sq_mitsuba.data.mesh_processing import TaggedMesh, process_mesh

    box = trimesh.creation.box((1.0, 0.5, 0.3))
    mesh = TaggedMesh(np.asarray(box.vertices), np.asarray(box.faces),
                      np.zeros(len(box.faces), np.int64))
    with pytest.raises(ValueError, match=r"^resolution: expected an integer >= 16, got "):
        process_mesh(mesh, method="fusion", resolution=resolution)


def test_a_meta_tensor_is_named_not_failed_on_inside_torch():
    """Every geometry call checks its tensors with check_tensor: a meta tensor failed there on
    its value check ("Tensor.item() cannot be called on meta tensors")."""
    from sq_mitsuba.geometry.rotation import quaternion_to_matrix

    with pytest.raises(ValueError, match=r"^quaternion: a meta tensor \(a shape without "
                                         r"values\); give its values$"):
        quaternion_to_matrix(torch.zeros(2, 4, device="meta"))
    with pytest.raises(ValueError, match=r"^params: a meta tensor"):
        Assembly(torch.zeros(1, 2, 16, device="meta"))


def test_a_fits_learning_rate_is_at_most_one(shipped):
    """lr = 1e30 ran the refinement into NaN poses, refused deep inside the renderer naming
    an internal argument; Adam's steps are about lr in the raw parameters."""
    from sq_mitsuba.inference.fit import FitOptions
    from sq_mitsuba.inference.refine import RefineOptions
    from sq_mitsuba.inference.search import SEARCH_REFINEMENT
    from sq_mitsuba.inference.sequence import SequenceOptions

    for options in (RefineOptions, SequenceOptions, FitOptions):
        with pytest.raises(ConfigError, match=r"lr: expected a value in \(0, 1\], got 1e\+30"):
            validate(options(lr=1e30))
        validate(options(lr=1.0))
    image = np.zeros((1, 64, 64), np.uint8)
    image[0, 20:40, 16:48] = 200
    with pytest.raises(ValueError, match=r"lr: expected a value in \(0, 1\]"):
        shipped.predict(image, refine=True,
                        refinement=dataclasses.replace(SEARCH_REFINEMENT, lr=1e30))


def test_an_assembly_loaded_onto_a_device_this_torch_lacks_is_one_line(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this torch has CUDA")
    path = tmp_path / "a.json"
    Assembly.from_values(torch.tensor([[[0.3, 0.2, 0.1]]]), torch.tensor([[[0.5, 0.5]]])).save(
        path)
    with pytest.raises(ValueError, match=r": device: 'cuda' cannot hold the assembly \(Torch not"):
        Assembly.load(path, device="cuda")
    with pytest.raises(ValueError, match=r": device: 'nonsense' cannot hold the assembly"):
        Assembly.load(path, device="nonsense")


def test_values_out_of_range_are_named_as_given(views):
    size, shape = torch.tensor([[[0.3, 0.2, 0.1]]]), torch.tensor([[[0.5, 0.5]]])
    with pytest.raises(ValueError, match=r"^size: must be positive$"):
        Assembly.from_values(-size, shape)
    with pytest.raises(ValueError, match=r"^shape: must lie in \[0, 1\]$"):
        Assembly.from_values(size, shape + 1)
    with pytest.raises(ValueError, match=r"^taper: must satisfy \|k\| < 1$"):
        Assembly.from_values(size, shape, taper=torch.full((1, 1, 2), 2.0))
    masks, camera, rotations, translations = views
    with pytest.raises(ValueError, match=r"^init_raw: degenerate 6D rotation"):
        fit_assembly(masks, camera, rotations, translations, num_primitives=1, steps=1,
                     init_raw=torch.zeros(1, 1, 16))


def test_a_batch_beyond_the_machines_memory_is_refused_in_one_line(shipped, monkeypatch):
    """predict(16 images of 8192 px) failed inside torch's allocator ("you tried to allocate
    4294967296 bytes"), naming neither the images nor a limit: the batch's need is estimated
    first, and the refusal says how many such images a call can take."""
    from sq_mitsuba import machine
    from sq_mitsuba.inference.images import BYTES_PER_INPUT_PIXEL

    images = torch.zeros(4, 64, 64, dtype=torch.uint8)
    per_image = 64 * 64 * BYTES_PER_INPUT_PIXEL
    monkeypatch.setattr(machine, "available_memory", lambda: 3 * per_image)
    with pytest.raises(ValueError, match=r"^images: 4 of 64 x 64 px \(16 bytes a pixel\) needs "
                                         r"about 256 KiB of memory, more than the 192 KiB this "
                                         r"process may use; give at most 3 such images a call$"):
        shipped.predict(images)
    monkeypatch.setattr(machine, "available_memory", lambda: 4 * per_image)
    assert shipped.predict(images).rotation.shape == (4, 3, 3)


def test_turned_copies_beyond_the_machines_memory_are_refused_in_one_line(shipped, monkeypatch):
    """Each turned copy holds about 108 KB until it is read back: `eval --batch-size 1024
    --turns 360` asked for about 40 GB. Refused naming turns, by check_turns (which eval
    calls with its batch size before any work) and by predict (a machine of 1.75 MiB here)."""
    from sq_mitsuba import machine
    from sq_mitsuba.inference.turned_copies import TURN_COPY_BYTES

    images = torch.zeros(2, 64, 64, dtype=torch.uint8)
    monkeypatch.setattr(machine, "available_memory", lambda: 2 * 7 * TURN_COPY_BYTES - 1)
    message = (r"^turns: 8 turned copies of 2 images needs about 1\.75 MiB of memory, more "
               r"than the 1\.75 MiB this process may use; give fewer turns, or fewer images")
    with pytest.raises(ValueError, match=message):
        shipped.check_turns(8, images=2)
    with pytest.raises(ValueError, match=message):
        shipped.predict(images, turns=8)
    shipped.check_turns(8, images=1)  # one image a call fits
    monkeypatch.setattr(machine, "available_memory", lambda: 2 * 7 * TURN_COPY_BYTES)
    assert shipped.predict(images, turns=8).turns == 8
