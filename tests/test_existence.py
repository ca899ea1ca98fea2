"""Existence probabilities per primitive: the probabilistic Chamfer loss against today's
chamfer_loss (every p = 1) and against brute force over every existence pattern, gradients
by finite differences, the parsimony term and its refusal without existence, a network grown
from a checkpoint with fewer primitives, and pruning in predictions end to end (files,
stand-ins that change no silhouette or counted sample, refinement, export, old checkpoints)."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math

import numpy as np
import pytest
import torch
import trimesh
from output_checks import one_torch_thread  # noqa: F401 (autouse fixture)
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.config import to_dict
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.image_turns import rotate_batch
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.inference.predictor import Predictor
from sq_mitsuba.model.checkpoint import (
    GROWN_OFFSET,
    SHIPPED_MODEL,
    checkpoint_payload,
    load_weights,
    model_from_checkpoint,
    read_checkpoint,
    write_checkpoint,
)
from sq_mitsuba.model.existence import (
    STAND_IN_SCALE,
    existence_surface_samples,
    expected_nearest,
    gathered_primitives,
    kept_primitives,
    parsimony_loss,
    probabilistic_chamfer_loss,
)
from sq_mitsuba.model.losses import chamfer_loss, counted_surface_samples
from sq_mitsuba.model.network import NetworkConfig, SuperquadricNet
from sq_mitsuba.training.batch import TrainingBatch
from sq_mitsuba.training.config import load_train_config
from sq_mitsuba.training.loss_terms import (
    LossConfig,
    LossContext,
    LossTermError,
    check_terms,
    compute_terms,
)

SIZE = 32
CAMERA = Camera.default(SIZE)
TINY = {"image_size": SIZE, "latent_dim": 16, "hidden_dim": 16, "drop_connect_rate": 0.0}


def _assembly(batch: int, count: int, seed: int) -> Assembly:
    """Random overlapping primitives (tapered, rotated) in float64."""
    generator = torch.Generator().manual_seed(seed)
    raw = torch.randn(batch, count, 16, generator=generator, dtype=torch.float64)
    raw[..., 5:8] *= 0.4  # centres near each other: many samples inside another primitive
    return Assembly.from_raw(raw)


def _cloud(batch: int, count: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(batch, count, 3, generator=generator, dtype=torch.float64) - 0.5


# ------------------------------------------------------------------------------ the loss


@pytest.mark.parametrize("squared", [True, False])
@pytest.mark.parametrize("method", ["kdtree", "dense"])
def test_every_primitive_present_is_todays_chamfer_loss(method, squared):
    assembly = _assembly(3, 4, seed=0)
    target = _cloud(3, 300, seed=1)
    points, keep = counted_surface_samples(assembly, 1)
    expected = chamfer_loss(points, keep, target, squared=squared)
    samples, inside = existence_surface_samples(assembly, 1)
    assert bool(inside.any()) and not bool(keep.all())  # the union filter is at work
    ones = torch.ones(3, 4, dtype=torch.float64)
    value = probabilistic_chamfer_loss(samples, inside, ones, target, method=method,
                                       squared=squared)
    assert float(value) == pytest.approx(float(expected), rel=1e-12)
    # An item none of whose samples is free: chamfer_loss keeps them all, and so does this.
    covered = torch.ones_like(inside)
    value = probabilistic_chamfer_loss(samples, covered, ones, target, method=method,
                                       squared=squared)
    keep_none = torch.zeros_like(keep)
    assert float(value) == pytest.approx(
        float(chamfer_loss(points, keep_none, target, squared=squared)), rel=1e-12)


def _brute_force(points, inside, probabilities, target, threshold=0.5, squared=True):
    """The loss by enumerating all 2^M existence patterns (module docstring of
    sq_mitsuba.model.existence): prediction -> target as the ratio of the expected sum of the
    counted samples' distances to their expected number, target -> prediction as the
    expected nearest, the farthest primitive standing in for the empty pattern."""
    batch, count, per, _ = points.shape
    eye = torch.eye(count, dtype=torch.bool)[:, :, None]
    total = 0.0
    for b in range(batch):
        distance = torch.cdist(points[b].reshape(-1, 3), target[b])  # (M V, K)
        squared_ = distance.square() if squared else distance
        to_target = squared_.min(1).values.view(count, per)
        covered = inside[b] & ~eye  # (holder, owner, V)
        all_covered = bool(covered.any(0).all())
        excluded = (covered & (probabilities[b] >= threshold)[:, None, None]).any(0)
        if bool(excluded.all()):
            excluded[:] = False
        nearest = squared_.view(count, per, -1).masked_fill(excluded[..., None], math.inf)
        nearest = nearest.min(1).values  # (M, K)
        found = ~excluded.all(1)
        numerator = denominator = backward = 0.0
        for pattern in itertools.product((False, True), repeat=count):
            exists = torch.tensor(pattern)
            chance = torch.where(exists, probabilities[b], 1 - probabilities[b]).prod()
            counted = exists[:, None] & ~(covered & exists[:, None, None]).any(0)
            if all_covered:
                counted = exists[:, None].expand(count, per)
            numerator = numerator + chance * to_target[counted].sum()
            denominator = denominator + chance * counted.sum()
            alive = exists & found
            closest = nearest[alive].min(0).values if bool(alive.any()) else \
                nearest[found].max(0).values
            backward = backward + chance * closest.mean()
        total = total + numerator / denominator + backward
    return total / batch


def test_the_expectation_equals_brute_force_over_every_existence_pattern():
    assembly = _assembly(2, 4, seed=2)
    target = _cloud(2, 60, seed=3)
    points, inside = existence_surface_samples(assembly, 0)
    generator = torch.Generator().manual_seed(4)
    for probabilities in (torch.rand(2, 4, generator=generator, dtype=torch.float64),
                          torch.tensor([[0.9, 0.2, 0.7, 0.05], [0.3, 0.6, 0.95, 0.45]],
                                       dtype=torch.float64)):
        for squared in (True, False):
            value = probabilistic_chamfer_loss(points, inside, probabilities, target,
                                               squared=squared)
            expected = _brute_force(points, inside, probabilities, target, squared=squared)
            assert float(value) == pytest.approx(float(expected), rel=1e-10)


def test_expected_nearest_equals_brute_force_with_missing_primitives():
    generator = torch.Generator().manual_seed(5)
    distances = torch.rand(6, 5, generator=generator, dtype=torch.float64)
    probabilities = torch.rand(6, 5, generator=generator, dtype=torch.float64)
    found = torch.rand(6, 5, generator=generator) > 0.3
    found[:, 0] = True
    value = expected_nearest(distances, probabilities, found)
    for row in range(6):
        expected = 0.0
        for pattern in itertools.product((False, True), repeat=5):
            exists = torch.tensor(pattern) & found[row]
            chance = torch.where(torch.tensor(pattern), probabilities[row],
                                 1 - probabilities[row]).prod()
            closest = distances[row][exists].min() if bool(exists.any()) else \
                distances[row][found[row]].max()
            expected += float(chance * closest)
        assert float(value[row]) == pytest.approx(expected, rel=1e-12)
    # Every p = 1: the plain minimum.
    assert torch.equal(expected_nearest(distances, torch.ones_like(distances)),
                       distances.min(-1).values)


def test_gradients_match_finite_differences():
    generator = torch.Generator().manual_seed(6)
    points = torch.rand(2, 3, 5, 3, generator=generator, dtype=torch.float64) - 0.5
    target = torch.rand(2, 7, 3, generator=generator, dtype=torch.float64) - 0.5
    inside = torch.rand(2, 3, 3, 5, generator=generator) > 0.6
    # Away from the 0.5 at which a primitive starts hiding the samples inside it.
    probabilities = torch.tensor([[0.9, 0.2, 0.75], [0.35, 0.6, 0.95]], dtype=torch.float64)

    def loss(p: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return probabilistic_chamfer_loss(x, inside, p, target)

    assert torch.autograd.gradcheck(loss, (probabilities.requires_grad_(),
                                           points.requires_grad_()))
    distances = torch.rand(4, 5, generator=generator, dtype=torch.float64)
    found = torch.tensor([True, False, True, True, True])
    assert torch.autograd.gradcheck(lambda d, p: expected_nearest(d, p, found), (
        distances.requires_grad_(),
        torch.rand(4, 5, generator=generator, dtype=torch.float64).requires_grad_()))


def test_bad_input_is_a_one_line_error_naming_it():
    points, inside = existence_surface_samples(_assembly(1, 2, seed=7), 0)
    target = _cloud(1, 10, seed=8)
    ones = torch.ones(1, 2, dtype=torch.float64)
    for call, name in (
            (lambda: probabilistic_chamfer_loss(points, inside, ones[:, :1], target),
             "probabilities"),
            (lambda: probabilistic_chamfer_loss(points, inside, 2 * ones, target),
             "probabilities"),
            (lambda: probabilistic_chamfer_loss(points, inside[..., :1], ones, target),
             "inside"),
            (lambda: probabilistic_chamfer_loss(points, inside, ones, target.float()),
             "target"),
            (lambda: kept_primitives(ones, 1.5), "threshold"),
            (lambda: parsimony_loss(ones[0]), "probabilities")):
        with pytest.raises(ValueError) as error:
            call()
        assert str(error.value).startswith(name) and "\n" not in str(error.value)


# ------------------------------------------------------------------------------ training


def test_parsimony_is_the_expected_count_and_needs_existence():
    probabilities = torch.tensor([[0.9, 0.1, 0.5], [1.0, 0.0, 0.25]])
    assert float(parsimony_loss(probabilities)) == pytest.approx((1.5 + 1.25) / 2)
    config = LossConfig(weights={"chamfer": 10.0, "parsimony": 1e-3})
    image = torch.zeros(1, 1, SIZE, SIZE)
    for existence in (True, False):
        net = SuperquadricNet(NetworkConfig(**TINY, num_primitives=3, existence=existence))
        with torch.no_grad():
            output = net.eval()(image, CAMERA.matrix())
        assert (output.existence_logits is None) is not existence
        assert output.raw.shape == (1, 3, 16)
        if existence:
            check_terms(config, output)
            assert output.existence == pytest.approx(torch.full((1, 3), 0.9), abs=2e-3)
            continue
        with pytest.raises(LossTermError) as error:
            check_terms(config, output)
        message = str(error.value)
        assert message.startswith("loss.weights.parsimony:") and "existence_logits" in message
        assert "\n" not in message


def test_a_distributed_run_refuses_a_head_no_weighted_term_reads():
    """DistributedDataParallel waits for a gradient of every parameter its outputs reach: a
    mask head with the mask term unweighted stopped a 2-process run at its second step. The
    check follows the gradients of a probe: refused naming the head; accepted once the term
    is weighed, the head frozen, or in one process."""
    net = SuperquadricNet(NetworkConfig(**TINY, num_primitives=2, mask_head=True)).eval()
    output = net(torch.zeros(1, 1, SIZE, SIZE), CAMERA.matrix())
    unread = LossConfig(weights={"chamfer": 10.0, "rotation": 0.1})
    with pytest.raises(LossTermError, match=r"^network output 'mask_logits': no weighted loss "
                                            r"term reads it, so \d+ parameters \(mask_head\.\*\)"):
        check_terms(unread, output, net)
    check_terms(unread, output)  # one process: its mask head just stays put
    check_terms(LossConfig(weights={"chamfer": 10.0, "mask": 1.0}), output, net)
    # A pose-only run leaves the shape's branch (read through the assembly, from raw) unread.
    pose_only = LossConfig(weights={"rotation_6d": 1.0, "translation": 1.0})
    with pytest.raises(LossTermError, match=r"^network output 'raw', 'mask_logits'.*"
                                            r"\(latent_head\.\*, mask_head\.\*, sq_generator"):
        check_terms(pose_only, output, net)
    net.freeze_except(("encoder.", "sq_generator.", "pose_head.", "latent_head."))
    frozen = net(torch.zeros(1, 1, SIZE, SIZE), CAMERA.matrix())
    check_terms(unread, frozen, net)


def test_the_chamfer_term_follows_the_existence_logits():
    """A network with existence trains the probabilistic Chamfer (equal to today's term once
    every primitive surely exists) and the parsimony term."""
    torch.manual_seed(4)
    net = SuperquadricNet(NetworkConfig(**TINY, num_primitives=3, existence=True)).eval()
    with torch.no_grad():
        output = net(torch.rand(2, 1, SIZE, SIZE), CAMERA.matrix())
    eye = torch.eye(3).expand(2, 1, 3, 3)
    batch = TrainingBatch(torch.rand(2, 1, SIZE, SIZE), torch.zeros(2, 1, SIZE, SIZE),
                          eye[:, 0], torch.tensor([[0.0, 0.0, 3.0]] * 2), torch.arange(2),
                          _cloud(2, 50, seed=13).float(), torch.rand(2, 8, 3),
                          torch.zeros(2, 8), eye)
    context = LossContext(LossConfig(weights={"chamfer": 10.0, "parsimony": 1e-3}, level=1))
    terms = compute_terms(output, batch, context)
    points, inside = existence_surface_samples(output.assembly, 1)
    expected = probabilistic_chamfer_loss(points, inside, output.existence,
                                          batch.surface_points)
    assert torch.equal(terms["chamfer"], expected)
    assert torch.equal(terms["parsimony"], output.existence.sum(1).mean())
    sure = dataclasses.replace(output, existence_logits=torch.full((2, 3), 1e3))
    plain = dataclasses.replace(output, existence_logits=None)
    torch.testing.assert_close(compute_terms(sure, batch, context, ("chamfer",))["chamfer"],
                               compute_terms(plain, batch, context, ("chamfer",))["chamfer"])


def test_a_grown_network_trains_and_validates_its_kept_primitives(train_dataset, tmp_path):
    """tiny.toml grown by init_from from two primitives to three with existence: one epoch
    (4 steps) logs the probabilistic Chamfer and the parsimony term, and validates."""
    import csv

    from sq_mitsuba.config import apply_overrides
    from sq_mitsuba.training.train import train

    config = load_train_config("train/configs/tiny.toml")
    torch.manual_seed(5)
    source = SuperquadricNet(config.network)
    start = write_checkpoint(tmp_path / "m2.pt", checkpoint_payload(source, CAMERA))
    grown = apply_overrides(config, [
        "network.num_primitives=3", "network.existence=true", "loss.weights.parsimony=1e-3",
        f'init_from="{start}"', "optim.epochs=1", "validation.images=2",
        f'data.cache_dir="{tmp_path / "cache"}"'])
    result = train(grown, train_dataset, tmp_path / "run", progress=False)
    assert result.steps == 4
    with open(tmp_path / "run" / "log.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert all(float(row["parsimony"]) > 0 and float(row["chamfer"]) > 0 for row in rows)
    assert len(result.validation) == 1 and math.isfinite(result.validation[0]["chamfer_l1"])
    trained = read_checkpoint(tmp_path / "run" / "last.pt")
    assert trained["config"]["network"]["existence"] is True
    assert trained["model"]["sq_generator.layers.2.bias"].shape == (3, 17)


def test_the_shipped_model_is_the_broad_recipes_network_of_eight_primitives():
    """The shipped model was grown from five primitives into eight by the broad recipe
    (train/shipped_model.sh step 4; the growth itself: test_init_from_grows_...): its
    network is that recipe's, and the file says so."""
    config = load_train_config("train/configs/broad_parsimony.toml")
    assert (config.network.num_primitives, config.network.existence) == (8, True)
    assert config.loss.weights["parsimony"] == 0.02
    payload = read_checkpoint(SHIPPED_MODEL)
    shipped, _ = model_from_checkpoint(payload)
    assert shipped.config == dataclasses.replace(config.network, pretrained=None)
    # Trained with that price (the runs' config travels with the averaged file).
    assert payload["config"]["loss"]["weights"]["parsimony"] == 0.02
    # As train/shipped_model.sh exports it: two fine-tunes, a quarter of the way from the
    # start, the existence column from the fine-tunes alone (--keep-existence).
    assert len(payload["source"]["averaged"]) == 2
    assert payload["source"]["start"]["share"] == 0.75
    assert payload["source"]["start"]["checkpoint"] == "model_archetypes.pt"
    assert payload["source"]["start"]["existence"] == "the fine-tunes' average"


def test_the_shipped_model_keeps_the_primitives_each_image_needs(train_dataset):
    """The shipped model's count follows the spacecraft (train/configs/broad_parsimony.toml,
    `export --keep-existence`): on the fixture's images (unseen spacecraft of the archetype
    catalogue) each reading keeps the primitives whose existence reaches the predictor's
    threshold, some fewer than all eight, where a model mixed back whole kept every one."""
    from sq_mitsuba.data.spe3r import Spe3rDataset

    predictor = load_model()
    dataset = Spe3rDataset(train_dataset, "test", num_surface=10, num_occupancy=2)
    images = torch.stack([dataset[i]["image"] for i in range(len(dataset))]).float()
    reading = predictor.predict(images, dataset.camera)
    kept = (reading.primitive_index >= 0).sum(dim=1)
    assert torch.equal(kept, (reading.existence >= predictor.min_existence).sum(dim=1).clamp(min=1))
    assert int(kept.min()) >= 1 and int(kept.max()) <= predictor.num_primitives
    assert int(kept.min()) < predictor.num_primitives, kept


def _check_grown(source: SuperquadricNet, grown: SuperquadricNet, camera: Camera) -> None:
    """The grown network reads an image as its source, its extra primitives copies of the
    source's moved by GROWN_OFFSET in raw translation, every primitive present at p ~ 0.9."""
    size = source.config.image_size
    images = torch.rand(2, 1, size, size, generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        before, after = source(images, camera.matrix()), grown(images, camera.matrix())
    count, total = source.config.num_primitives, grown.config.num_primitives
    # Equal up to float32 rounding: the grouped product runs over more columns.
    torch.testing.assert_close(after.raw[:, :count], before.raw, rtol=1e-5, atol=1e-5)
    copies = before.raw[:, torch.arange(count, total) % count]
    moved = after.raw[:, count:] - copies
    torch.testing.assert_close(moved[..., :5], torch.zeros_like(moved[..., :5]), atol=1e-5,
                               rtol=0)
    torch.testing.assert_close(moved[..., 8:], torch.zeros_like(moved[..., 8:]), atol=1e-5,
                               rtol=0)
    offsets = moved[..., 5:8].norm(dim=-1)
    torch.testing.assert_close(offsets, torch.full_like(offsets, GROWN_OFFSET), atol=1e-5,
                               rtol=0)
    assert after.existence == pytest.approx(torch.full((2, total), 0.9), abs=5e-3)
    for name in ("rotation", "translation"):
        torch.testing.assert_close(getattr(after, name), getattr(before, name))


def test_init_from_grows_a_network_only_with_existence(tmp_path):
    torch.manual_seed(1)
    source = SuperquadricNet(NetworkConfig(**TINY, num_primitives=2)).eval()
    path = write_checkpoint(tmp_path / "m2.pt", checkpoint_payload(source, CAMERA))
    state = read_checkpoint(path)["model"]
    grown = SuperquadricNet(NetworkConfig(**TINY, num_primitives=5, existence=True))
    load_weights(grown, state, "init_from", partial=True)
    _check_grown(source, grown.eval(), CAMERA)
    plain = SuperquadricNet(NetworkConfig(**TINY, num_primitives=5))
    with pytest.raises(ValueError, match=r"^init_from: weights do not fit config\.network "
                                         r"\(sq_generator.*only with network\.existence"):
        load_weights(plain, state, "init_from", partial=True)
    with pytest.raises(ValueError, match="weights do not fit"):  # a full load never grows
        load_weights(grown, state, "checkpoint")


# ------------------------------------------------------------------------------ pruning


def test_kept_primitives_and_invisible_stand_ins():
    probabilities = torch.tensor([[0.9, 0.2, 0.7, 0.6], [0.3, 0.45, 0.1, 0.2]])
    rows = kept_primitives(probabilities)
    assert rows.tolist() == [[0, 2, 3], [1, -1, -1]]  # the second keeps its most probable
    assert kept_primitives(probabilities, 0.0).tolist() == [[0, 1, 2, 3]] * 2
    assert kept_primitives(probabilities, width=4).tolist() == [[0, 2, 3, -1], [1, -1, -1, -1]]
    assembly = _assembly(2, 4, seed=10)
    pruned = Assembly(gathered_primitives(assembly.params, rows))
    assert torch.equal(pruned.params[0], assembly.params[0, [0, 2, 3]])
    assert torch.equal(pruned.params[1, 0], assembly.params[1, 1])
    stand_in = pruned.params[1, 1]
    assert torch.equal(stand_in[:3], STAND_IN_SCALE * assembly.params[1, 1, :3])
    assert torch.equal(stand_in[3:], assembly.params[1, 1, 3:])
    # Strictly inside the primitive it copies: its samples do not count, and the union holds
    # the same points (occupancy > 0.5, as the 3D IoU reads it).
    _, keep = counted_surface_samples(pruned, 2)
    assert not bool(keep.view(2, 3, -1)[1, 1:].any())
    alone = Assembly(pruned.params[1:, :1])
    points = _cloud(1, 4000, seed=11) * 1.2
    assert torch.equal(Assembly(pruned.params[1:]).union_occupancy(points) > 0.5,
                       alone.union_occupancy(points) > 0.5)
    # So for any primitive: 60 random ones (tapered, rotated, box-like to round).
    hosts = _assembly(10, 6, seed=12).params.reshape(60, 1, 16)
    shrunk = gathered_primitives(hosts, torch.full((60, 2), -1).index_fill_(1, torch.tensor(0),
                                                                            0))[:, 1:]
    samples = Assembly(shrunk).surface_points(3)[:, 0]  # (60, 642, 3)
    assert float(Assembly(hosts).inside_outside(samples).max()) < 1.0


def _existence_network() -> SuperquadricNet:
    """A tiny network with existence whose four primitives' probabilities differ by image:
    about 0.94, 0.55 to 0.76, 0.94, 0.03."""
    torch.manual_seed(2)
    net = SuperquadricNet(NetworkConfig(**TINY, num_primitives=4, existence=True,
                                        pose_head="grid", rotation_cells=512))
    last = net.sq_generator.layers[2]
    with torch.no_grad():
        last.bias[:, 16] = torch.tensor([3.0, 0.0, 3.0, -3.0])
        last.weight[:, :, 16] *= 10.0  # the image moves the logits
        # Batch-norm statistics of the test scenes (as training would set them), so that the
        # eval-mode network responds to its input.
        for module in net.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.reset_running_stats()
                module.momentum = None
        net.train()(_scenes(4)[:, None], CAMERA.matrix())
    return net.eval()


def _scenes(count: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(12)
    images = torch.zeros(count, SIZE, SIZE)
    for k in range(count):
        top, left = torch.randint(4, 14, (2,), generator=generator).tolist()
        images[k, top:top + 14, left:left + 12] = 0.3 + 0.6 * k / count
    return images


def test_predictions_drop_the_primitives_that_do_not_exist():
    net = _existence_network()
    images = _scenes(4)
    every = Predictor(net, CAMERA, min_existence=0.0).predict(images)
    probabilities = every.existence
    assert probabilities.shape == (4, 4) and every.assembly.params.shape == (4, 4, 16)
    assert every.primitive_index.tolist() == [[0, 1, 2, 3]] * 4
    # A threshold at which the images keep different numbers of primitives.
    threshold = float(probabilities[:, 1].median())
    assert float(probabilities[:, 1].min()) < threshold < float(probabilities[:, 1].max())
    predictor = Predictor(net, CAMERA, min_existence=threshold)
    pruned = predictor.predict(images)
    keep = probabilities >= threshold
    assert pruned.assembly.params.shape == (4, 3, 16)
    for k in range(4):
        own = pruned.item_assembly(k)
        assert torch.equal(own.params[0], every.assembly.params[k, keep[k]])
        assert pruned.primitive_index[k].tolist() == \
            torch.nonzero(keep[k]).flatten().tolist() + [-1] * (3 - int(keep[k].sum()))
    # The stand-ins change no silhouette (the same samples: the renderer reseeded).
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

    assert bool((pruned.primitive_index < 0).any())
    renderer = SilhouetteRenderer(CAMERA, spp=4)
    with torch.no_grad():
        for k in range(4):
            pose = (pruned.rotation[k:k + 1], pruned.translation[k:k + 1])
            renderer.reseed(5)
            padded = render_assembly(pruned.assembly[k], *pose, renderer, 2)
            renderer.reseed(5)
            alone = render_assembly(pruned.item_assembly(k), *pose, renderer, 2)
            assert torch.equal(padded, alone) and float(alone.sum()) > 0
    # A reading from turned copies keeps the primitives of the copies' mean existence: the
    # mean of every primitive over the copies, pruned by it.
    turned = predictor.predict(images, turns=4)
    assert (pruned.turns, turned.turns) == (1, 4)
    with pytest.raises(ValueError, match=r"^prediction: expected this predictor.s one-pass"):
        predictor.read_turns(images, turned, 4)  # a reading is not turned twice
    every_turned = Predictor(net, CAMERA, min_existence=0.0).predict(images, turns=4)
    torch.testing.assert_close(turned.existence, every_turned.existence)
    assert torch.equal(turned.primitive_index,
                       kept_primitives(every_turned.existence.double(), threshold))
    torch.testing.assert_close(turned.assembly.params, gathered_primitives(
        every_turned.assembly.params, turned.primitive_index))
    torch.testing.assert_close(turned.primitives, every_turned.assembly.params)
    copies = [predictor.predict(rotate_batch(images[:, None], torch.full((4,), k * math.pi / 2)
                                             )[:, 0]).existence for k in range(4)]
    assert float((copies[1] - copies[0]).abs().max()) > 0.05  # the copies read differently
    torch.testing.assert_close(turned.existence, torch.stack(copies).mean(0),
                               atol=1e-3, rtol=0)  # the network's batches of 4 and 12
    assert Predictor(net, CAMERA).predict(images).assembly.params.shape[1] == \
        int((probabilities >= 0.5).sum(1).max())  # the default threshold: 0.5
    with pytest.raises(ValueError, match=r"^min_existence: expected a number in \[0, 1\]"):
        Predictor(net, CAMERA, min_existence=2.0)


def test_refinement_fits_the_kept_primitives():
    from sq_mitsuba.inference.refine import RefineOptions
    from sq_mitsuba.inference.search import SearchOptions

    net = _existence_network()
    images = _scenes(2)
    predictor = Predictor(net, CAMERA, min_existence=0.5)
    network = predictor.predict(images)
    masks = (images > 0.1).float()
    fitted = predictor.refine(images, network, mask=masks,
                              search=SearchOptions(grid=128, screen_steps=2, resolution=32),
                              refinement=RefineOptions(steps=3, patience=3, resolution=32))
    start = fitted.fit.start  # the reading from turned copies: their primitives are fitted
    assert fitted.assembly.params.shape == start.assembly.params.shape
    assert torch.equal(fitted.primitive_index, start.primitive_index)
    assert fitted.primitives is None and start.primitives is not None
    torch.testing.assert_close(start.scaled(2.0).primitives[..., :3],
                               2.0 * start.primitives[..., :3])  # sizes scale with the target
    with pytest.raises(ValueError, match=r"^prediction: expected this predictor.s one-pass"):
        predictor.read_turns(images, fitted, 4)  # the turned copies read the network's own
    for k in range(2):
        assert fitted.item_assembly(k).num_primitives == start.item_assembly(k).num_primitives


@pytest.mark.parametrize("start", ["reference", "best"])
def test_a_sequence_holds_the_chosen_frames_own_primitives(start):
    from sq_mitsuba.inference.sequence import SequenceOptions

    net = _existence_network()
    images = _scenes(4)
    probabilities = Predictor(net, CAMERA, min_existence=0.0).predict(images).existence
    predictor = Predictor(net, CAMERA, min_existence=float(probabilities[:, 1].median()))
    result = predictor.predict_sequence(images, mask=(images > 0.1).float(),
                                        options=SequenceOptions(steps=2, spp=2, start=start))
    rows = result.frames.primitive_index
    assert bool((rows < 0).any())  # some frames keep fewer: stand-ins in the frames' batch
    counts = (rows >= 0).sum(1).tolist()
    assert result.assembly.num_primitives in counts
    if start == "reference":
        assert result.assembly.num_primitives == counts[result.reference]


def test_predict_writes_the_kept_primitives_and_export_carries_existence(tmp_path, capsys):
    net = _existence_network()
    images = _scenes(1)
    checkpoint = write_checkpoint(tmp_path / "model.pt", checkpoint_payload(net, CAMERA))
    Image.fromarray((images[0].numpy() * 255).astype(np.uint8)).save(tmp_path / "a.png")
    kept = int((Predictor(net, CAMERA).predict(images).existence >= 0.5).sum())
    assert 1 <= kept < 4
    for extra, count in (([], kept), (["--set", "min_existence=0"], 4)):
        out = tmp_path / f"out{count}"
        assert main(["predict", str(tmp_path / "a.png"), "--checkpoint", str(checkpoint),
                     "--out", str(out), "--set", "min_target=0", "--quiet", *extra]) == 0, \
            capsys.readouterr().err
        data = json.loads((out / "a.assembly.json").read_text())
        assert len(data["primitives"]) == count
        assert len(trimesh.load(out / "a.glb").geometry) == count
    exported = tmp_path / "exported.pt"
    assert main(["export", "--checkpoint", str(checkpoint), "--out", str(exported)]) == 0, \
        capsys.readouterr().err
    loaded = load_model(exported)
    assert loaded.model.config.existence
    assert loaded.predict(images).primitive_index.tolist() == \
        Predictor(net, CAMERA).predict(images).primitive_index.tolist()


def test_the_baseline_keeps_the_primitives_that_exist_on_average(train_dataset):
    from sq_mitsuba.evaluation.scoring import baseline_prediction
    from sq_mitsuba.inference.refine import raw_from_assembly

    net = _existence_network()
    with torch.no_grad():  # probabilities 0.95, 0.27, 0.95, 0.05 whatever the image
        net.sq_generator.layers[2].weight[:, :, 16] = 0.0
        net.sq_generator.layers[2].bias[:, 16] = torch.tensor([3.0, -1.0, 3.0, -3.0])
    raw, rotation, _ = baseline_prediction(Predictor(net, CAMERA), train_dataset, 6)
    mean, rotation_all, _ = baseline_prediction(Predictor(net, CAMERA, min_existence=0.0),
                                                train_dataset, 6)
    assert raw.shape == mean.shape == (1, 4, 16) and torch.equal(rotation, rotation_all)
    # Primitives 0 and 2 (the mean of the network's raw outputs), then two stand-ins.
    rows = torch.tensor([[0, 2, -1, -1]])
    expected = raw_from_assembly(Assembly(gathered_primitives(Assembly.from_raw(mean).params,
                                                              rows)))
    torch.testing.assert_close(raw, expected)
    torch.testing.assert_close(raw[:, :2], mean[:, [0, 2]])


def test_a_checkpoint_without_the_field_loads_without_existence(tmp_path):
    torch.manual_seed(3)
    net = SuperquadricNet(NetworkConfig(**TINY, num_primitives=2)).eval()
    payload = checkpoint_payload(net, CAMERA)
    del payload["config"]["network"]["existence"]  # as written before the field existed
    assert "existence" in to_dict(net.config)
    path = write_checkpoint(tmp_path / "old.pt", payload)
    predictor = load_model(path)
    assert not predictor.model.config.existence
    prediction = predictor.predict(_scenes(2))
    assert prediction.existence is None and prediction.primitive_index is None
    expected = Predictor(net, CAMERA).predict(_scenes(2))
    assert torch.equal(prediction.assembly.params, expected.assembly.params)
    assert torch.equal(prediction.item_assembly(1).params, expected.assembly.params[1:])
