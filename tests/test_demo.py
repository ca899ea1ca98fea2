"""``sq-mitsuba demo`` end to end at the tiny size on the tiny trained checkpoint: every output
exists and is well formed, the page links only files that exist and shows the network's own
prediction, a headless browser loads every picture, and bad input is a one-line error that
writes nothing.

The end-to-end tests (the tiny demo run, the headless Chromium, the trained checkpoint) are
marked ``slow``: ``make test-fast`` (``pytest -m "not slow"``) leaves them out and runs only the
unit tests of the demo's parts; ``make test`` runs them all."""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
import socket
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from output_checks import assert_picture, error_line, one_torch_thread  # noqa: F401 (autouse fixture)
from PIL import Image

from sq_mitsuba.apps.demo_files import DEMO_FORMAT, MANIFEST
from sq_mitsuba.apps.demo_options import DEMO_CATALOGUE_SEED, SIZES, DemoSize
from sq_mitsuba.cli import main
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.rotation import quaternion_to_matrix
from sq_mitsuba.inference.loading import load_model
from sq_mitsuba.model import checkpoint as checkpoint_module

TINY = SIZES["tiny"]


class _Links(HTMLParser):
    """Every <img src> and <a href> of a page."""

    def __init__(self) -> None:
        super().__init__()
        self.images: list[str] = []
        self.links: list[str] = []
        self.body: dict[str, str | None] | None = None

    def handle_starttag(self, tag, attrs):
        attributes = dict(attrs)
        if tag == "img":
            self.images.append(attributes["src"])
        elif tag == "a":
            self.links.append(attributes["href"])
        elif tag == "body":
            self.body = attributes


def page_links(path: Path) -> _Links:
    parser = _Links()
    parser.feed(path.read_text(encoding="utf-8"))
    parser.close()
    return parser


@pytest.fixture(scope="module")
def demo_checkpoint(request):
    """The model the demo tests run: the shipped one when this checkout has it (what
    `make demo` runs), else the tiny trained fixture."""
    from sq_mitsuba.model.checkpoint import SHIPPED_MODEL

    if SHIPPED_MODEL.is_file():
        return SHIPPED_MODEL
    return request.getfixturevalue("eval_checkpoint")


@pytest.fixture(scope="module")
def demo(demo_checkpoint, tmp_path_factory):
    """The tiny demo, run once through the command line into a folder that holds an earlier
    demo (its demo.json and a stale picture), beside the temporary folder of a killed one:
    returns the output folder and what was printed."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("demo") / "demo_output"
    out.mkdir()
    (out / MANIFEST).write_text(json.dumps({"format": DEMO_FORMAT}))  # a demo's record
    (out / "images").mkdir()
    (out / "images" / "stale.png").write_text("from an earlier demo")
    # The temporary folder of an earlier demo killed before it could clean up.
    dead = subprocess.Popen(["true"])
    dead.wait()
    (out.parent / f".{out.name}.new.{dead.pid}.abcd").mkdir()
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        from sq_mitsuba.model.checkpoint import SHIPPED_MODEL

        # No --checkpoint for the shipped model: the demo's default, as `make demo` runs it.
        model = [] if demo_checkpoint == SHIPPED_MODEL else ["--checkpoint", str(demo_checkpoint)]
        code = main(["demo", "--size", "tiny", *model, "--out", str(out), "--quiet"])
    assert code == 0
    return out, printed.getvalue()


def test_presets_are_valid_and_the_seed_is_not_the_training_catalogue():
    from sq_mitsuba.config import validate

    for preset in SIZES.values():
        validate(preset)
    assert DEMO_CATALOGUE_SEED != 0
    assert SIZES["default"] == DemoSize()


@pytest.mark.slow
def test_demo_writes_every_output_well_formed(demo, demo_checkpoint):
    out, printed = demo
    # The earlier demo was replaced as a whole, and nothing is left beside the folder (the
    # killed demo's temporary folder is gone too).
    assert not (out / "images" / "stale.png").exists()
    assert sorted(p.name for p in out.parent.iterdir()) == [out.name]
    lines = printed.strip().splitlines()
    assert str(out / "index.html") in lines[-1]
    assert re.search(r"done in \d+ s \(wall\)", lines[-1])

    page = page_links(out / "index.html")
    count = TINY.models * TINY.images
    primitives = load_model(demo_checkpoint).num_primitives
    # Per image: input, two silhouettes, the assembly and the true mesh; then the pass: the
    # shared assembly from six sides and one overlay per frame.
    assert len(page.images) == 5 * count + 1 + TINY.pass_frames
    for src in page.images:
        assert not src.startswith(("data:", "/", "http")), src
        assert src.endswith(".png")
        assert_picture(out / src)
    for href in page.links:
        assert (out / href).is_file(), href
    glbs = [h for h in page.links if h.endswith(".glb") and not h.startswith("pass/")]
    jsons = [h for h in page.links
             if h.endswith(".assembly.json") and not h.startswith("pass/")]
    assert len(glbs) == len(jsons) == 2 * count
    for path in jsons:
        # The primitives the image keeps (a network with existence drops some), and its GLB
        # beside it holds one closed mesh for each.
        assembly = Assembly.load(out / path)
        kept = assembly.params.shape[1]
        assert assembly.params.shape == (1, kept, 16) and 1 <= kept <= primitives
        glb = path.replace(".assembly.json", ".glb")
        assert glb in glbs
        scene = trimesh.load(out / glb)
        assert len(scene.geometry) == kept
        assert all(mesh.is_watertight for mesh in scene.geometry.values())
    for path in out.rglob("*.json"):
        json.loads(path.read_text())

    # The Markdown twin shows the same pictures and links the same files.
    markdown = (out / "index.md").read_text()
    md_images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", markdown)
    md_links = re.findall(r"(?<!!)\[[^\]]*\]\(([^)]+)\)", markdown)
    assert md_images == page.images
    assert set(md_links) == set(page.links) - set(page.images)

    record = json.loads((out / MANIFEST).read_text())
    assert record["checkpoint"] == str(demo_checkpoint)
    assert record["images"] == count and len(record["models"]) == TINY.models
    assert record["options"]["seed"] == DEMO_CATALOGUE_SEED


def _rows(path):
    with open(path, newline="", encoding="utf-8") as handle:
        return list(csv.DictReader(handle))


@pytest.mark.slow
def test_demo_shows_the_networks_own_prediction_of_unseen_models(demo, demo_checkpoint):
    out, _ = demo
    data = out / "data"
    # Every demo spacecraft is a test model, and none is in the training catalogue's seed.
    splits = dict(line.split(",") for line in (data / "splits.csv").read_text().splitlines())
    assert len(splits) == TINY.models and set(splits.values()) == {"test"}
    for model in splits:
        card = json.loads((out / "models" / model / "models" / "model_card.json").read_text())
        assert card["catalogue_seed"] == DEMO_CATALOGUE_SEED
    rows = _rows(out / "per_image.csv")
    assert sorted({r["method"] for r in rows}) == ["baseline", "network", "refined"]
    assert len(rows) == 3 * TINY.models * TINY.images
    # The page's summary numbers are the mean of per_image.csv (2D IoU before and after).
    html_text = (out / "index.html").read_text()
    for method, label in (("network", "network"),
                          ("refined", "search + refined (image&#x27;s mask)")):
        mean = np.mean([float(r["iou_2d"]) for r in rows if r["method"] == method])
        assert f"<td>{label}</td>" in html_text and f"<td>{mean:.3f}</td>" in html_text
    # The mask fitted is named: the network's mask head where the model has one (the shipped
    # model), else the threshold segmentation (the tiny trained fixture).
    from sq_mitsuba.model.checkpoint import read_checkpoint

    has_head = read_checkpoint(demo_checkpoint)["config"]["network"].get("mask_head", False)
    assert ("mask head" if has_head else "threshold segmentation") in html_text
    for r in rows:
        if r["method"] == "refined" and r["search_score"]:
            assert r["mask_source"] == ("network" if has_head else "segmentation")
            assert 0 <= float(r["search_score"]) <= 1 and 0 <= float(r["refine_iou_after"]) <= 1

    # The network's files hold the prediction the checkpoint makes from the stored image.
    predictor = load_model(demo_checkpoint)
    for model in splits:
        labels = json.loads((data / model / "labels.json").read_text())
        label = labels[0]
        stem = f"{model}_0000"
        image = np.asarray(Image.open(data / model / "images" / label["filename"]))
        size = predictor.image_size
        small = np.asarray(Image.fromarray(image).resize((size, size), Image.BILINEAR))
        camera = predictor.camera.rescaled(size, size)
        expected = predictor.predict(torch.from_numpy(small.astype(np.float32) / 255)[None],
                                     camera)
        pose = json.loads((out / "assemblies" / f"{stem}.pose.json").read_text())
        rotation = quaternion_to_matrix(torch.tensor(pose["network"]["q_vbs2tango"]))
        assert torch.allclose(rotation, expected.rotation[0], atol=1e-3)
        assert np.allclose(pose["network"]["r_Vo2To_vbs"], expected.translation[0].numpy(),
                           atol=1e-3)
        assert np.allclose(pose["truth"]["r_Vo2To_vbs"], label["r_Vo2To_vbs_true"], atol=1e-6)
        truth = quaternion_to_matrix(torch.tensor(pose["truth"]["q_vbs2tango"]))
        assert torch.allclose(truth, quaternion_to_matrix(
            torch.tensor(label["q_vbs2tango_true"])), atol=1e-6)
        network = Assembly.load(out / "assemblies" / f"{stem}.network.assembly.json")
        assert torch.allclose(network.params.float(), expected.assembly.params, atol=1e-3)
        # Refinement changed something.
        refined = Assembly.load(out / "assemblies" / f"{stem}.refined.assembly.json")
        moved = not torch.allclose(refined.params, network.params) or \
            pose["refined"] != pose["network"]
        row = next(r for r in rows if r["model"] == model and r["method"] == "refined")
        assert moved or not row["search_score"]  # searched: the pose moved


@pytest.mark.slow
def test_the_demos_pass_is_scored_from_the_files_it_shows(demo):
    """The pass section's numbers are what its files hold: the shared assembly of
    sequence.assembly.json drawn again here at each frame's pose.json gives per_frame.csv's
    2D IoU against the rendered mask (a plain pixel count), and the poses' quaternions its
    frame-to-frame rotation errors against the labels'."""
    from sq_mitsuba.apps.demo_options import DemoOptions
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly

    out, printed = demo
    root = out / "pass"
    frames = TINY.pass_frames
    record = json.loads((out / MANIFEST).read_text())["pass"]
    models = sorted(json.loads((out / MANIFEST).read_text())["models"])
    assert record["model"] == models[0] and record["frames"] == frames
    assert f"a pass of {frames} frames of {models[0]}" in printed
    labels = json.loads((root / "data" / models[0] / "labels.json").read_text())
    assert [label["frame_in_pass"] for label in labels] == list(range(frames))
    assert {label["pass"] for label in labels} == {0}

    rows = _rows(root / "per_frame.csv")
    assert [(r["method"], int(r["frame"])) for r in rows] == [
        (method, k) for method in ("network", "frames", "sequence") for k in range(frames)]
    sequence = [r for r in rows if r["method"] == "sequence"]
    # Three readings, not one scored thrice: each frame's own two differ from each other.
    by_method = {m: [r["chamfer_l1_paper"] for r in rows if r["method"] == m]
                 for m in ("network", "frames", "sequence")}
    assert by_method["network"] != by_method["frames"] != by_method["sequence"]
    # The page and the manifest show the rows' means.
    html_text = (out / "index.html").read_text()
    assert f"A pass of {frames} images" in html_text
    for method in ("network", "frames", "sequence"):
        mean = np.mean([float(r["iou_2d"]) for r in rows if r["method"] == method])
        assert record["summary"][method]["iou_2d"] == pytest.approx(mean, abs=1e-6)
        assert f"<td>{mean:.3f}</td>" in html_text

    camera = Camera.load(root / "data" / "camera.json")
    assert record["resolution"] == camera.width  # scored as rendered, not at the network's size
    assembly = Assembly.load(root / "sequence" / "sequence.assembly.json")
    poses = [json.loads((root / "sequence" / f"{Path(label['filename']).stem}.pose.json")
                        .read_text()) for label in labels]
    rotation = quaternion_to_matrix(torch.tensor([p["q_vbs2tango"] for p in poses],
                                                 dtype=torch.float64))
    translation = torch.tensor([p["r_Vo2To_vbs"] for p in poses], dtype=torch.float64)
    # Each pose names its frame from the demo's folder (written elsewhere first), as the
    # single images' do.
    assert all((out / p["image"]).is_file() and not Path(p["image"]).is_absolute()
               for p in poses)
    renderer = SilhouetteRenderer(camera, spp=DemoOptions().silhouette_spp)
    drawn = render_assembly(Assembly(assembly.params.double().expand(frames, -1, -1)), rotation,
                            translation, renderer, DemoOptions().level).numpy() > 0.5
    for k, label in enumerate(labels):
        mask = np.asarray(Image.open(root / "data" / models[0] / "masks" / label["filename"])
                          .convert("L")) > 127
        iou = (drawn[k] & mask).sum() / max((drawn[k] | mask).sum(), 1)
        # Measured within 0.002 of the soft silhouette's IoU the scoring takes.
        assert float(sequence[k]["iou_2d"]) == pytest.approx(iou, abs=0.01), k
    truth = quaternion_to_matrix(torch.tensor([label["q_vbs2tango_true"] for label in labels],
                                              dtype=torch.float64))
    for k in range(1, frames):
        step = rotation[k] @ rotation[k - 1].T
        true_step = truth[k] @ truth[k - 1].T
        cosine = ((step.T @ true_step).trace() - 1) / 2
        error = math.degrees(math.acos(max(-1.0, min(1.0, float(cosine)))))
        assert float(sequence[k]["relative_rotation_deg"]) == pytest.approx(error, abs=0.1)
    assert sequence[0]["relative_rotation_deg"] == ""


# ------------------------------------------------------------------------------ browser


def _chromium() -> str:
    """A headless-capable Chromium, installed with apt-get when absent (once per session)."""
    for name in ("chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    command = ["apt-get", "install", "-y", "-qq", "chromium"]
    if os.geteuid() != 0:
        command = ["sudo", "-n", *command]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=600,
                              env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
    except (OSError, subprocess.TimeoutExpired) as error:
        pytest.skip(f"no chromium on PATH and apt-get install chromium failed: {error}")
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if done.returncode != 0 or not found:
        reason = (done.stderr.strip().splitlines() or ["no output"])[-1]
        pytest.skip(f"no chromium on PATH and `{' '.join(command)}` failed: {reason}")
    return found


@pytest.fixture(scope="session")
def chromium():
    return _chromium()


def _headless(chromium: str, *arguments: str) -> subprocess.CompletedProcess:
    return subprocess.run([chromium, "--headless", "--disable-gpu", "--no-sandbox",
                           "--hide-scrollbars", *arguments], capture_output=True, text=True,
                          timeout=120)


def broken_images(chromium: str, page: Path) -> int:
    """The page's own count of pictures that failed to load, read from the DOM after load."""
    done = _headless(chromium, "--dump-dom", "--virtual-time-budget=5000", page.as_uri())
    match = re.search(r'<body[^>]*data-broken-images="(\d+)"', done.stdout)
    assert match, f"the page did not report its pictures: {done.stderr[-500:]}"
    return int(match[1])


@pytest.mark.slow
def test_the_page_as_a_person_sees_it(demo, chromium, tmp_path):
    out, _ = demo
    shot = tmp_path / "page.png"
    done = _headless(chromium, f"--screenshot={shot}", "--window-size=1200,2000",
                     (out / "index.html").as_uri())
    assert shot.is_file(), done.stderr[-500:]
    pixels = np.asarray(Image.open(shot).convert("L"), dtype=np.float64)
    assert pixels.shape == (2000, 1200)
    assert pixels.std() > 10  # text, tables and pictures, not a blank page
    assert broken_images(chromium, out / "index.html") == 0
    # The check sees a missing picture: a copy of the page with one planted.
    page = out / "planted.html"
    text = (out / "index.html").read_text()
    page.write_text(text.replace("</body>", '<img src="images/missing.png" alt="x"></body>'))
    try:
        assert broken_images(chromium, page) == 1
    finally:
        page.unlink()


# ------------------------------------------------------------------------------ bad input


def _listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.mark.slow  # eval_checkpoint: renders a dataset and trains
@pytest.mark.parametrize("case", ["size", "checkpoint", "out", "foreign", "train"])
def test_bad_input_is_one_line_and_writes_nothing(case, eval_checkpoint, tmp_path, capsys):
    (tmp_path / "a_file").write_text("not a folder")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    arguments, expected = {
        "size": (["--size", "huge", "--checkpoint", str(eval_checkpoint)], "--size"),
        "checkpoint": (["--checkpoint", str(tmp_path / "missing.pt")],
                       str(tmp_path / "missing.pt")),
        "out": (["--checkpoint", str(eval_checkpoint), "--out", str(tmp_path / "a_file" / "x")],
                "a_file"),
        "foreign": (["--checkpoint", str(eval_checkpoint), "--out", str(foreign)],
                    "not a demo's output"),
        "train": (["--train", "--checkpoint", str(eval_checkpoint)], "--checkpoint"),
    }[case]
    before = _listing(tmp_path)
    # The last --size and --out given count (argparse): the case's own come after these.
    assert main(["demo", "--size", "tiny", "--out", str(tmp_path / "demo_output"),
                 *arguments, "--quiet"]) == 2
    assert expected in error_line(capsys)
    assert _listing(tmp_path) == before


@pytest.mark.parametrize("arguments, expected", [
    # The preset by --set alone is taken (the run then stops at the foreign folder).
    (["--set", "size=tiny"], "not a demo's output"),
    (["--set", "size=huge"], "--set size: expected one of"),
    (["--size", "tiny", "--set", "size=small"], "size is also given by --size; give it once"),
])
def test_the_size_by_set_counts_as_given_once(arguments, expected, tmp_path, capsys):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    assert main(["demo", "--out", str(foreign), *arguments, "--quiet"]) == 2
    assert expected in error_line(capsys)
    assert _listing(tmp_path) == ["foreign", "foreign/keep.txt"]


def test_without_a_shipped_model_the_demo_says_so_before_any_work(tmp_path, monkeypatch,
                                                                   capsys):
    monkeypatch.setattr(checkpoint_module, "SHIPPED_MODEL", tmp_path / "absent.pt")
    out = tmp_path / "demo_output"
    assert main(["demo", "--size", "tiny", "--out", str(out), "--quiet"]) == 2
    assert "no trained model is shipped" in error_line(capsys)
    assert _listing(tmp_path) == []


@pytest.mark.slow
def test_summary_ignores_nothing_it_should_show(demo):
    # Every metric of the page is finite for every image and method (no blank cells).
    out, _ = demo
    for row in _rows(out / "per_image.csv"):
        for metric in ("chamfer_l1_paper", "camera_chamfer", "iou_2d", "iou_3d",
                       "rotation_error_deg", "rotation_error_folded_deg",
                       "rotation_error_axes_deg", "translation_error_m"):
            assert math.isfinite(float(row[metric])), (row["method"], metric)
    assert "n/a" not in (out / "index.html").read_text()


def test_page_and_twin_carry_the_same_figures_and_escape_text(tmp_path):
    from sq_mitsuba.apps.demo_page import DemoPage, PageImage, write_page

    page = DemoPage(
        title="a <b> & c", intro=["x < y | z"], metric_labels={"iou_2d": "2D IoU"},
        summary=[("network", {"iou_2d": 0.5}), ("baseline", {"iou_2d": math.nan})],
        figures=[("images/training_curves.png", "training curves")],
        images=[PageImage("one", [("images/a.png", "input")],
                          [("network", {"iou_2d": 0.25})], [("assembly", "a.json")])],
        files=[("table", "per_image.csv")])
    html_path, md_path = write_page(tmp_path, page)
    links = page_links(html_path)
    assert links.images == ["images/training_curves.png", "images/a.png"]
    assert set(links.links) == {"images/training_curves.png", "images/a.png", "a.json",
                                "per_image.csv"}
    text = html_path.read_text()
    assert "<title>a &lt;b&gt; &amp; c</title>" in text and "x &lt; y | z" in text
    assert "<td>0.500</td>" in text and "<td>n/a</td>" in text
    markdown = md_path.read_text()
    assert re.findall(r"!\[[^\]]*\]\(([^)]+)\)", markdown) == links.images
    assert "| network | 0.250 |" in markdown and "| baseline | n/a |" in markdown


def test_a_running_demos_temporary_folder_is_left_alone(tmp_path):
    from sq_mitsuba.apps.demo import remove_stale_staging

    out = tmp_path / "demo_output"
    dead = subprocess.Popen(["true"])
    dead.wait()
    host = re.sub(r"[^A-Za-z0-9]", "_", socket.gethostname())
    stale = tmp_path / f".demo_output.new.{host}-{dead.pid}.x1"
    legacy = tmp_path / f".demo_output.new.{dead.pid}.x0"  # named before the host was
    live = tmp_path / f".demo_output.new.{host}-{os.getpid()}.x2"
    other = tmp_path / f".other.new.{host}-{dead.pid}.x3"
    # Another machine sharing the disk: its process ids are not this machine's to probe.
    elsewhere = tmp_path / f".demo_output.new.{host}x-{dead.pid}.x5"
    for path in (stale, legacy, live, other, elsewhere):
        path.mkdir()
    assert sorted(remove_stale_staging(out)) == sorted([stale, legacy])
    assert not stale.exists() and live.is_dir() and other.is_dir() and elsewhere.is_dir()
    # A name with glob characters is taken as it is (it matched nothing).
    bracketed = tmp_path / f".demo[1].new.{dead.pid}.x4"
    bracketed.mkdir()
    assert remove_stale_staging(tmp_path / "demo[1]") == [bracketed]


def test_folders_built_aside_and_renamed_get_the_usual_permissions(demo, tmp_path):
    """demo_output and a generated model's models/ are built in a mkdtemp folder (0700) and
    renamed into place: they get mkdir's permissions, so other users can read them."""
    from sq_mitsuba.data.library import GenerateOptions, generate_library

    umask = os.umask(0)
    os.umask(umask)
    usual = 0o777 & ~umask
    out, _ = demo
    assert out.stat().st_mode & 0o777 == usual
    library = tmp_path / "lib"
    generate_library(GenerateOptions(out=library, count=1, seed=7, points=200), progress=False)
    (models,) = library.glob("*/models")
    assert models.stat().st_mode & 0o777 == usual
