"""Predictor and checkpoints: input forms (uint8/float, with or without a channel dim, any
size), intrinsics that follow the resizing, input errors, the folded fast path, and checkpoint
round trips and failures."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

import sq_mitsuba
from sq_mitsuba.config import to_dict
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.inference.predictor import Prediction, Predictor
from sq_mitsuba.model import checkpoint
from sq_mitsuba.model.checkpoint import checkpoint_payload, read_checkpoint, write_checkpoint
from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet

SIZE = 64
CAMERA = Camera.default(SIZE)


def scene(size: int, supersample: int = 4) -> torch.Tensor:
    """A grey test scene (1, size, size) in [0, 1] at any resolution: a bright tilted ellipse
    (a body) and a dimmer one (a panel) on black, each pixel the mean of supersample^2 point
    samples, so images of one scene at two sizes agree up to sampling."""
    offsets = (torch.arange(supersample, dtype=torch.float64) + 0.5) / supersample
    centres = (torch.arange(size, dtype=torch.float64)[:, None] + offsets).reshape(-1) / size
    v, u = torch.meshgrid(centres, centres, indexing="ij")  # fractions of the image side

    def ellipse(cu: float, cv: float, a: float, b: float, angle_deg: float) -> torch.Tensor:
        c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
        x, y = u - cu, v - cv
        return (((c * x + s * y) / a) ** 2 + ((-s * x + c * y) / b) ** 2 <= 1).double()

    image = 0.85 * ellipse(0.42, 0.56, 0.16, 0.09, 30.0)
    image = torch.maximum(image, 0.4 * ellipse(0.62, 0.45, 0.2, 0.03, 30.0))
    image = image.reshape(size, supersample, size, supersample).mean(dim=(1, 3))
    return image[None].float()


@torch.no_grad()
def calibrate_batchnorm(net: SuperquadricNet, images: torch.Tensor) -> None:
    """Set the BatchNorm running statistics to those of ``images`` (as training would), so the
    eval-mode network responds to its input."""
    for module in net.modules():
        if isinstance(module, nn.BatchNorm2d):
            module.reset_running_stats()
            module.momentum = None  # cumulative average over the calibration passes
    net.train()
    net(images, CAMERA.matrix())
    net.eval()


@pytest.fixture(scope="module")
def net() -> SuperquadricNet:
    """An untrained network whose outputs depend on the image: calibrated BatchNorm, and last
    layers scaled up from their small initial weights."""
    torch.manual_seed(0)
    model = SuperquadricNet(NetworkConfig(image_size=SIZE, num_primitives=3, latent_dim=64,
                                          hidden_dim=64))
    gen = torch.Generator().manual_seed(1)
    shifts = torch.rand(8, 2, generator=gen) * 0.3 - 0.15
    batch = torch.stack([torch.roll(scene(SIZE), (int(dy * SIZE), int(dx * SIZE)), (1, 2))
                         for dx, dy in shifts])
    calibrate_batchnorm(model, torch.cat([batch, torch.rand(8, 1, SIZE, SIZE)]))
    with torch.no_grad():
        model.pose_head.mlp[-1].weight.mul_(1000.0)
        model.sq_generator.layers[2].weight.mul_(1000.0)
    return model


@pytest.fixture(scope="module")
def predictor(net) -> Predictor:
    return Predictor(net, CAMERA)


def two_scenes() -> torch.Tensor:
    """(2, 64, 64) float: the scene, and the scene mirrored and dimmed."""
    image = scene(SIZE)[0]
    return torch.stack([image, 0.6 * image.flip(-1)])


def assert_same(a: Prediction, b: Prediction, atol: float = 0.0) -> None:
    torch.testing.assert_close(a.assembly.params, b.assembly.params, rtol=0, atol=atol)
    for name in ("rotation", "translation", "quaternion", "pixel", "depth"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=atol,
                                   msg=name)


def test_prediction_fields(predictor):
    x = two_scenes()
    prediction = predictor.predict(x)
    assert prediction.assembly.params.shape == (2, 3, 16)
    assert prediction.rotation.shape == (2, 3, 3) and prediction.translation.shape == (2, 3)
    assert bool((prediction.quaternion[:, 0] >= 0).all())
    torch.testing.assert_close(quaternion_to_matrix(prediction.quaternion), prediction.rotation,
                               rtol=0, atol=1e-5)
    torch.testing.assert_close(CAMERA.project(prediction.translation), prediction.pixel,
                               rtol=0, atol=1e-3)
    assert bool((prediction.translation[:, 2] > 0).all())
    # The outputs follow the image.
    assert float((prediction.pixel[0] - prediction.pixel[1]).abs().max()) > 0.2
    assert prediction.camera == CAMERA
    assert predictor.num_primitives == 3 and predictor.image_size == SIZE
    # Ordinary tensors: refinement can start autograd from them.
    assert not prediction.translation.is_inference() and not prediction.translation.requires_grad
    start = prediction.translation.clone().requires_grad_(True)
    (start * prediction.translation).sum().backward()
    torch.testing.assert_close(start.grad, prediction.translation)


def test_uint8_float_numpy_and_channel_dim_agree(predictor):
    x8 = (two_scenes() * 255).round().to(torch.uint8)
    reference = predictor.predict(x8)
    assert_same(predictor.predict(x8.float() / 255), reference)
    assert_same(predictor.predict(x8[:, None]), reference)
    assert_same(predictor.predict(x8.numpy()), reference)


def test_flipped_and_strided_numpy_images_are_copied(predictor):
    """A mirrored view (negative strides), a Fortran-ordered and a big-endian array are valid
    images: read as their C-ordered native copies."""
    x = two_scenes().numpy()
    reference = predictor.predict(np.ascontiguousarray(x[:, :, ::-1]))
    assert_same(predictor.predict(x[:, :, ::-1]), reference)
    assert_same(predictor.predict(x[:, ::-1, ::-1][:, ::-1]), reference)
    assert_same(predictor.predict(np.asfortranarray(x)), predictor.predict(x))
    assert_same(predictor.predict(x[:, :, ::-1].astype(">f4")), reference)


def test_larger_image_of_the_same_scene_gives_a_close_pose(predictor):
    small = predictor.predict(scene(SIZE))
    large = predictor.predict(scene(2 * SIZE))  # the camera is rescaled to 128 px
    explicit = predictor.predict(scene(2 * SIZE), camera=CAMERA.rescaled(2 * SIZE))
    assert_same(large, explicit)
    assert large.camera == CAMERA.rescaled(2 * SIZE)
    depth = float(small.depth[0])
    torch.testing.assert_close(large.translation, small.translation, rtol=0, atol=0.01 * depth)
    torch.testing.assert_close(large.pixel, 2 * small.pixel, rtol=0, atol=0.5)
    torch.testing.assert_close(large.camera.project(large.translation), large.pixel, rtol=0,
                               atol=1e-3)
    # An up-sampled input (32 px -> 64) goes through the same path.
    tiny = predictor.predict(scene(SIZE // 2))
    assert tiny.camera == CAMERA.rescaled(SIZE // 2)
    torch.testing.assert_close(tiny.translation, small.translation, rtol=0, atol=0.05 * depth)


def test_other_camera_moves_the_translation_consistently(predictor):
    other = Camera(110.0, 110.0, 25.0, 40.0, SIZE, SIZE)
    default = predictor.predict(two_scenes())
    moved = predictor.predict(two_scenes(), camera=other)
    torch.testing.assert_close(moved.pixel, default.pixel, rtol=0, atol=1e-4)
    torch.testing.assert_close(other.project(moved.translation), moved.pixel, rtol=0, atol=1e-3)
    torch.testing.assert_close(moved.depth, default.depth * other.fx / CAMERA.fx, rtol=1e-5,
                               atol=0)


def test_the_camera_follows_images_of_another_size_and_the_same_aspect():
    """A 640 x 480 camera for 320 x 240 images: every intrinsic halved, by hand (the width and
    the height told apart); another aspect ratio is refused."""
    from sq_mitsuba.inference.images import camera_for

    camera = Camera(800.0, 780.0, 321.0, 239.0, 640, 480)
    assert camera_for(camera, 640, 480) is camera
    half = camera_for(camera, 320, 240)
    assert (half.fx, half.fy, half.cx, half.cy, half.width, half.height) == (
        400.0, 390.0, 160.5, 119.5, 320, 240)
    with pytest.raises(ValueError, match="another aspect ratio"):
        camera_for(camera, 240, 320)


def test_upsampling_keeps_pixel_centres_where_they_are():
    """A ramp whose value is its pixel centre's x, upsampled 16 -> 24 px: each new pixel
    centre (j + 0.5) * 16 / 24 reads the ramp there (inside the edge half pixels, by hand);
    shrunk 16 -> 8, a linear ramp is kept at the new centres away from the border (a symmetric
    filter's mean of a line)."""
    from sq_mitsuba.inference.images import resize_images

    ramp = (torch.arange(16, dtype=torch.float64) + 0.5).expand(1, 1, 16, 16)
    grown = resize_images(ramp, 24)[0, 0, 0]
    centres = (torch.arange(24, dtype=torch.float64) + 0.5) * 16 / 24
    inside = (centres >= 0.5) & (centres <= 15.5)
    torch.testing.assert_close(grown[inside], centres[inside], atol=1e-9, rtol=0)
    shrunk = resize_images(ramp, 8)[0, 0, 0]
    torch.testing.assert_close(shrunk[1:-1], ramp[0, 0, 0].reshape(8, 2).mean(-1)[1:-1],
                               atol=1e-9, rtol=0)


def test_the_network_reads_an_image_resized_as_its_training_images(train_dataset):
    """The predictor's resize of a rendered PNG equals the dataset reader's (the training
    images' pixels) within one grey level of rounding, shrunk 64 -> 40 and grown 64 -> 80:
    a box filter ("area"), used before, differed at edges by tens of levels."""
    import numpy as np
    from PIL import Image

    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.inference.images import resize_images

    for size in (40, 80):
        dataset = Spe3rDataset(train_dataset, "train", image_size=size, num_surface=8,
                               num_occupancy=8)
        for item in (0, 5):
            png = dataset.image_file(item)
            grey = np.asarray(Image.open(png).convert("L"), dtype=np.float32) / 255.0
            ours = resize_images(torch.from_numpy(grey)[None, None], size)[0]
            theirs = dataset[item]["image"]
            assert ours.shape == theirs.shape == (1, size, size)
            assert float((ours - theirs).abs().max()) <= 1.01 / 255


def test_bad_input_is_a_one_line_error_naming_the_argument(predictor):
    x = two_scenes()
    nan = x.clone()
    nan[0, 3, 4] = float("nan")
    cases = [
        (nan, "images: contains NaN"),
        (x[0], "images: expected shape"),  # (H, W): no batch dim
        (x[:, None].expand(2, 3, SIZE, SIZE), "images: expected shape"),
        (x * 255, r"images: float values must lie in \[0, 1\]"),
        (x.to(torch.int32), "images: expected uint8 or floating point"),
        ([[0.0]], "images: expected a torch.Tensor or numpy array"),
    ]
    for images, message in cases:
        with pytest.raises(ValueError, match=f"^{message}") as info:
            predictor.predict(images)
        assert "\n" not in str(info.value)
    with pytest.raises(ValueError, match=r"^camera: none given, and the predictor's camera is "
                       r"for 64 x 64 images, the images are 96 x 64 \(another aspect ratio\); "
                       r"pass theirs, e.g. Camera.from_fov\(fov_x_deg, 96, 64\)$"):
        predictor.predict(torch.zeros(1, 64, 96))
    with pytest.raises(ValueError, match=r"^camera: is for 64 x 64 images, the images are 96"):
        predictor.predict(torch.zeros(1, 64, 96), camera=CAMERA)
    with pytest.raises(ValueError, match=r"^camera: expected a Camera"):
        predictor.predict(x, camera=CAMERA.matrix())


def test_eval_mode_is_used_and_the_mode_restored(net, predictor):
    x = two_scenes()
    reference = predictor.predict(x)
    net.train()
    try:
        assert_same(predictor.predict(x), reference)  # BatchNorm in eval mode, no dropping
        assert net.training
    finally:
        net.eval()


def test_fast_path_matches_eager(net, predictor):
    """The folded network, and the folded network traced at every batch size it meets (a
    trace may fix the batch size, so each shape gets its own, and only a few are kept)."""
    x = two_scenes()
    folded = Predictor(net, CAMERA, fast=True)
    assert folded._traced is None  # tracing is asked for, not the fast path's default
    for images in (x, scene(2 * SIZE)):
        assert_same(folded.predict(images), predictor.predict(images), atol=1e-4)
    # It runs its own folded copy, a snapshot: changing the network's weights after does not
    # reach it (as it reaches the eager predictor).
    before = folded.predict(x).assembly.params.clone()
    weight = next(net.sq_generator.parameters())
    kept = weight.detach().clone()
    with torch.no_grad():
        weight.add_(0.5)
    try:
        torch.testing.assert_close(folded.predict(x).assembly.params, before, rtol=0, atol=0)
        assert not torch.allclose(predictor.predict(x).assembly.params, before, atol=1e-3)
    finally:
        with torch.no_grad():
            weight.copy_(kept)
    with pytest.raises(ValueError, match=r"^traced: traces the folded network of the fast"):
        Predictor(net, CAMERA, traced=True)
    fast = Predictor(net, CAMERA, fast=True, traced=True)
    assert_same(fast.predict(x), predictor.predict(x), atol=1e-4)
    assert_same(fast.predict(scene(2 * SIZE)), predictor.predict(scene(2 * SIZE)), atol=1e-4)
    three = torch.cat([x, x[:1].flip(-2)])
    assert_same(fast.predict(three), predictor.predict(three), atol=1e-4)
    assert_same(fast.predict(x), predictor.predict(x), atol=1e-4)  # a kept trace, reused
    assert len(fast._traced) == 3
    for batch in range(4, 6):  # five shapes traced in all: the oldest is dropped
        fast.predict(three[:1].expand(batch, -1, -1))
    assert len(fast._traced) == 4


def test_checkpoint_round_trip(net, predictor, tmp_path):
    path = tmp_path / "run" / "model.pt"
    payload = checkpoint_payload(net, CAMERA, config={"seed": 3, "network": {}}, step=7)
    assert write_checkpoint(path, payload) == path
    assert [p.name for p in path.parent.iterdir()] == ["model.pt"]  # no temporary left
    # The same payload is the same bytes, whatever the file's (or its temporary's) name.
    again = write_checkpoint(tmp_path / "elsewhere" / "other.pt", payload)
    assert again.read_bytes() == path.read_bytes()
    stored = read_checkpoint(path)
    assert stored["format"] == "sq_mitsuba.checkpoint" and stored["version"] == 1
    assert stored["step"] == 7 and stored["config"]["seed"] == 3
    assert stored["config"]["network"] == to_dict(net.config)
    loaded = sq_mitsuba.load_model(path)
    assert loaded.camera == CAMERA and not loaded.model.training and loaded.source == path
    x = two_scenes()
    assert_same(loaded.predict(x), predictor.predict(x))
    assert_same(load_model(path, fast=True).predict(x), predictor.predict(x), atol=1e-4)
    traced = load_model(path, fast=True, traced=True)
    assert traced._traced is not None and load_model(path, fast=True)._traced is None
    assert_same(traced.predict(x), predictor.predict(x), atol=1e-4)
    # Refused before the checkpoint is read (a missing file would say so otherwise).
    with pytest.raises(ValueError, match=r"^traced: traces the folded network"):
        load_model(tmp_path / "missing.pt", traced=True)


def test_checkpoint_as_the_training_writes_it(net, predictor, tmp_path):
    """A hand-built payload with the documented keys and typical training extras."""
    optimizer = torch.optim.Adam(net.parameters())
    payload = {
        "format": "sq_mitsuba.checkpoint", "version": 1,
        "config": {"network": to_dict(net.config), "optim": {"lr": 1e-3}},
        "model": net.state_dict(), "camera": CAMERA.to_speed_dict(),
        "optimizer": optimizer.state_dict(), "rng": {"torch": torch.get_rng_state()},
        "history": [{"step": 1, "loss": 0.5}], "best": None,
    }
    path = write_checkpoint(tmp_path / "last.pt", payload)
    assert_same(load_model(path).predict(two_scenes()), predictor.predict(two_scenes()))


def test_unreadable_checkpoints_are_one_line_errors_naming_the_file(net, tmp_path):
    good = write_checkpoint(tmp_path / "good.pt", checkpoint_payload(net, CAMERA))
    missing = tmp_path / "missing.pt"
    with pytest.raises(FileNotFoundError, match=f"^checkpoint: no such file {missing}$"):
        load_model(missing)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all\n" * 10)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    unsafe = tmp_path / "unsafe.pt"
    torch.save({"format": "sq_mitsuba.checkpoint", "path": Path("x")}, unsafe)
    other = tmp_path / "other.pt"
    torch.save({"a": torch.zeros(2)}, other)
    newer = tmp_path / "newer.pt"
    torch.save({**read_checkpoint(good), "version": 2}, newer)
    cases = [(garbage, "not a readable checkpoint"), (truncated, "not a readable checkpoint"),
             (unsafe, "not a readable checkpoint"), (other, "not an sq_mitsuba checkpoint"),
             (newer, "checkpoint version 2"), (tmp_path, "is not a file")]
    for path, message in cases:
        with pytest.raises(ValueError, match=message) as info:
            load_model(path)
        text = str(info.value)
        assert text.startswith(f"{path}: ") and "\n" not in text, text


def test_mismatched_checkpoints_are_refused(net, tmp_path):
    payload = checkpoint_payload(net, CAMERA)
    payload["config"]["network"]["num_primitives"] = 4
    path = write_checkpoint(tmp_path / "four.pt", payload)
    with pytest.raises(ValueError, match=f"^{path}: weights do not fit config.network"):
        load_model(path)
    payload["config"]["network"]["num_primitives"] = 3
    payload["config"]["network"]["pretrained"] = str(tmp_path / "imagenet-b0.pth")  # absent
    path = write_checkpoint(tmp_path / "pretrained.pt", payload)
    assert load_model(path).model.config.pretrained is None  # the checkpoint's weights rule
    payload["config"]["network"]["num_primitives"] = 0
    with pytest.raises(ValueError, match=r"config\.network\.num_primitives"):
        write_checkpoint(tmp_path / "zero.pt", payload)
    assert not (tmp_path / "zero.pt").exists()


def test_bad_payloads_are_refused_before_writing(net, tmp_path):
    good = checkpoint_payload(net, CAMERA)
    target = tmp_path / "bad.pt"
    cases = [
        ({**good, "extra": np.zeros(3)}, "payload.extra: ndarray"),
        ({**good, "seed": np.float64(1.0)}, "payload.seed: float64"),
        ({**good, "format": "other"}, "payload: format 'other'"),
        ({k: v for k, v in good.items() if k != "camera"}, "payload: missing 'camera'"),
        ({**good, "camera": {"Nu": 64}}, "payload.camera: "),
        ({**good, "config": {}}, "payload: 'config' must be a dict with a 'network' dict"),
    ]
    for payload, message in cases:
        with pytest.raises(ValueError, match=f"^{message}"):
            write_checkpoint(target, payload)
        assert not target.exists()
    target.write_bytes(b"old")
    with pytest.raises(ValueError):
        write_checkpoint(target, cases[0][0])
    assert target.read_bytes() == b"old"  # an existing file is left as it was


def test_shipped_model(net, predictor, tmp_path, monkeypatch):
    shipped = tmp_path / "weights" / "model.pt"
    monkeypatch.setattr(checkpoint, "SHIPPED_MODEL", shipped)
    with pytest.raises(FileNotFoundError, match="no trained model is shipped") as info:
        sq_mitsuba.load_model()
    assert "sq-mitsuba train" in str(info.value) and "\n" not in str(info.value)
    write_checkpoint(shipped, checkpoint_payload(net, CAMERA))
    assert_same(sq_mitsuba.load_model().predict(two_scenes()), predictor.predict(two_scenes()))


def test_reading_from_turned_copies_turns_with_the_image(train_dataset):
    """predict(turns=4) of an image rolled by 90 deg is Rz(90 deg) times that of the image
    (the four copies are the same four images) up to the half turns of the body frame and the
    grid's cell mapping (about a cell, 9 deg): over the fixture's test images, by
    construction and more than the plain network, which is roll-equivariant only as far as
    training taught it. Its assembly, depth, image position and mask, means over the copies
    mapped back, are the image's, rolled where they turn with it; ``read_turns`` of the plain
    prediction reads the same running only the turned copies. Bad ``turns`` and a network without a
    distribution head are one-line errors, and ``can_turn`` says so beforehand."""
    from sq_mitsuba.data.spe3r import Spe3rDataset
    from sq_mitsuba.geometry.image_turns import rotate_batch, z_rotation
    from sq_mitsuba.geometry.metrics import rotation_error_deg
    from sq_mitsuba.geometry.so3_grid import half_turns

    shipped = sq_mitsuba.load_model()
    dataset = Spe3rDataset(train_dataset, "test", num_surface=10, num_occupancy=2)
    images = torch.stack([dataset[i]["image"] for i in range(len(dataset))]).float()
    camera = dataset.camera
    quarter = torch.full((len(images),), math.pi / 2)
    rolled = rotate_batch(images, quarter)
    roll = z_rotation(quarter.double())
    errors = {}
    for turns in (1, 4):
        read = shipped.predict(images, camera, turns=turns)
        read_rolled = shipped.predict(rolled, camera, turns=turns)
        errors[turns] = rotation_error_deg(read_rolled.rotation.double(),
                                           roll @ read.rotation.double(), half_turns())
    assert float(errors[4].median()) < min(15.0, float(errors[1].median())), errors
    torch.testing.assert_close(read.rotation_hypotheses[:, 0], read.rotation)
    # The rest is the mean over the copies, each mapped back: the rolled image's four copies
    # are the image's four, so its reading is the image's, rolled (the shape not at all), and
    # it keeps the same primitives (decided by the copies' mean existence) where the unturned
    # passes of the two alone would not on some images.
    if read.existence is not None:
        torch.testing.assert_close(read_rolled.existence, read.existence, atol=1e-5, rtol=0)
        assert torch.equal(read_rolled.primitive_index, read.primitive_index)
        alone = [shipped.predict(batch, camera).primitive_index for batch in (images, rolled)]
        assert not torch.equal(*alone)
    torch.testing.assert_close(read_rolled.assembly.params, read.assembly.params,
                               atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(read_rolled.depth, read.depth, atol=1e-4, rtol=1e-4)
    centre = torch.tensor([images.shape[-1] / 2, images.shape[-2] / 2])  # of the given images
    rolled_pixel = (roll[:, :2, :2].float() @ (read.pixel - centre)[..., None])[..., 0] + centre
    torch.testing.assert_close(read_rolled.pixel, rolled_pixel, atol=1e-3, rtol=0)
    torch.testing.assert_close(read_rolled.mask, rotate_batch(read.mask[:, None], quarter)[:, 0],
                               atol=1e-3, rtol=0)
    plain = shipped.predict(images, camera)
    assert not torch.equal(read.assembly.params, plain.assembly.params)
    # read_turns reuses the plain pass: the same reading as predict(turns=4), one pass fewer.
    passes = []
    run = shipped._run
    shipped._run = lambda x, matrix: passes.append(len(x)) or run(x, matrix)
    try:
        reused = shipped.read_turns(images, plain, 4, camera)
    finally:
        del shipped._run
    assert passes == [3 * len(images)]  # the three turned copies only
    for name in ("rotation", "rotation_hypotheses", "rotation_scores",
                 "rotation_log_probabilities", "translation", "mask"):
        torch.testing.assert_close(getattr(reused, name), getattr(read, name), atol=1e-5,
                                   rtol=1e-5, msg=name)
    torch.testing.assert_close(reused.assembly.params, read.assembly.params)
    assert torch.allclose(plain.rotation_log_probabilities.logsumexp(-1), torch.zeros(1),
                          atol=1e-4)
    with pytest.raises(ValueError, match=r"^prediction: expected this predictor.s one-pass"):
        shipped.read_turns(images[:1], plain, 4, camera)  # another batch's prediction
    longer_lens = Camera(camera.fx * 1.5, camera.fy * 1.5, camera.cx, camera.cy, camera.width,
                         camera.height)
    with pytest.raises(ValueError, match=r"^prediction: .* this camera"):
        shipped.read_turns(images, plain, 4, longer_lens)  # made with another camera
    assert shipped.can_turn(camera)
    image = images[:1]
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match=r"^turns: expected an integer in \[1, 360\]"):
            shipped.predict(image, camera, turns=bad)
    regressing = Predictor(SuperquadricNet(NetworkConfig(image_size=64)), camera)
    assert not regressing.can_turn(camera)
    with pytest.raises(ValueError, match=r"turns: .* needs a rotation-distribution head"):
        regressing.predict(image, camera, turns=4)
    assert regressing.predict(image, camera).rotation_log_probabilities is None
    with pytest.raises(ValueError, match=r"turns: .* needs a rotation-distribution head"):
        regressing.read_turns(image, regressing.predict(image, camera), 4, camera)
    off_centre = Camera(camera.fx, camera.fy, camera.cx + 5.0, camera.cy, camera.width,
                        camera.height)
    assert not shipped.can_turn(off_centre)
    with pytest.raises(ValueError, match=r"^turns: the images' camera \(128 x 128 px, .*principal "
                                         r"point \(74, 64\)\) stretched .*principal point "
                                         r"\(55.5, 48\); turned copies need"):
        shipped.predict(image, off_centre, turns=4)


def test_the_turned_copies_mask_is_their_mean_computed_copy_by_copy():
    """``turned_back_mask`` resizes one copy at a time (a 4,000 px image's 8 copies at once held
    2 GB): equal to the mean over every copy resized at once, the unturned copy's mask
    included and each turned copy weighted by where it covers the image."""
    import torch.nn.functional as F

    from sq_mitsuba.geometry.image_turns import rotate_batch, turned_back_mask

    generator = torch.Generator().manual_seed(0)
    batch, copies, height, width = 2, 3, 40, 56
    mask = torch.rand(batch, height, width, generator=generator, dtype=torch.float64)
    logits = torch.randn(copies * batch, 1, 12, 12, generator=generator)
    angles = torch.tensor([0.7, 2.0, 4.1])
    undo = -angles.repeat_interleave(batch)
    back = rotate_batch(logits, undo)
    cover = rotate_batch(torch.ones_like(back), undo)
    back, cover = (F.interpolate(t, size=(height, width), mode="bilinear",
                                 align_corners=False)[:, 0] for t in (back, cover))
    cover = cover.clamp(0, 1).reshape(copies, batch, height, width).double()
    probability = back.sigmoid().reshape(copies, batch, height, width).double()
    expected = (mask + (cover * probability).sum(0)) / (1 + cover.sum(0))
    torch.testing.assert_close(turned_back_mask(mask, logits, angles, height, width), expected)
    for args, name in (((mask[0], logits, angles), "mask"),
                       ((mask[None], logits, angles), "mask"),
                       ((mask, logits[1:], angles), "turned_logits"),
                       ((mask, logits[:, 0], angles), "turned_logits"),
                       ((mask, logits, angles[None]), "angles")):
        with pytest.raises(ValueError, match=f"^{name}: expected shape"):
            turned_back_mask(*args, height, width)
    with pytest.raises(ValueError, match=r"^mask: expected shape \(\.\.\., N, 40, 50\)"):
        turned_back_mask(mask, logits, angles, height, 50)


def test_a_camera_that_cannot_turn_is_named_with_its_own_and_its_stretched_numbers():
    """Square pixels on a 128 x 64 image become fx 60, fy 120 on the network's 96 x 96
    input: the message gives both cameras, not the training option that shares the check."""
    shipped = sq_mitsuba.load_model()
    wide = Camera(80.0, 80.0, 64.0, 32.0, 128, 64)
    assert not shipped.can_turn(wide)
    with pytest.raises(ValueError, match=r"^turns: the images' camera \(128 x 64 px, fx 80, fy "
                                         r"80, principal point \(64, 32\)\) stretched to the "
                                         r"network's 96 x 96 input has fx 60, fy 120, ") as info:
        shipped.predict(torch.zeros(1, 64, 128), wide, turns=4)
    assert "augment" not in str(info.value) and "\n" not in str(info.value)
    assert shipped.can_turn(Camera(80.0, 40.0, 64.0, 32.0, 128, 64))  # fx / W = fy / H


def test_read_turns_of_one_is_predict_of_one_for_any_network_and_camera(predictor):
    """``read_turns(images, reading, 1)`` is ``predict(images, turns=1)``: the reading itself,
    for a regressing head and for a camera that cannot turn alike."""
    x = two_scenes()
    reading = predictor.predict(x, turns=1)
    assert predictor.read_turns(x, reading, 1) is reading
    shipped = sq_mitsuba.load_model()
    off_centre = Camera(150.0, 150.0, 53.0, 48.0, 96, 96)
    image = scene(96)
    plain = shipped.predict(image, off_centre, turns=1)
    assert shipped.read_turns(image, plain, 1, off_centre) is plain
    for bad in (0, True):
        with pytest.raises(ValueError, match=r"^turns: expected an integer in \[1, 360\]"):
            shipped.read_turns(image, plain, bad, off_centre)
    turned = shipped.predict(image, turns=4)
    with pytest.raises(ValueError, match=r"^prediction: expected this predictor.s one-pass"):
        shipped.read_turns(image, turned, 1)


def test_refine_checks_turns_and_takes_the_one_pass_reading_only(predictor):
    """``refine`` refuses what ``predict`` refuses for ``turns``, and a reading from turned
    copies as ``network`` (the fit reads its own copies from the one pass), before any work;
    an empty mask keeps the search from running where a check would be missing."""
    x = two_scenes()
    empty = torch.zeros(2, SIZE, SIZE, dtype=torch.bool)
    network = predictor.predict(x)
    for bad in (0, -5, True, 2.5):
        with pytest.raises(ValueError, match=r"^turns: expected an integer in \[1, 360\]"):
            predictor.predict(x, turns=bad, refine=True, mask=empty)
        with pytest.raises(ValueError, match=r"^turns: expected an integer in \[1, 360\]"):
            predictor.refine(x, network, turns=bad, mask=empty)
    with pytest.raises(ValueError, match=r"^turns: .* needs a rotation-distribution head"):
        predictor.refine(x, network, turns=4, mask=empty)
    assert predictor.refine(x, network, turns=1, mask=empty).fit.turns == 1
    shipped = sq_mitsuba.load_model()
    image = scene(96)
    turned = shipped.predict(image, turns=4)
    for turns in (None, 1, 4):
        with pytest.raises(ValueError, match=r"^network: read from 4 turned copies") as info:
            shipped.refine(image, turned, turns=turns, mask=torch.zeros(1, 96, 96))
        assert "\n" not in str(info.value)
