"""``sq-mitsuba fit`` end to end on small synthetic masks, and its input errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from sq_mitsuba.cli import main
from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.geometry.rotation import matrix_to_quaternion, random_rotations
from sq_mitsuba.render.silhouette import SilhouetteRenderer, render_assembly


@pytest.fixture(scope="module")
def fit_inputs(tmp_path_factory):
    """Two 48 x 48 masks of a box-like superquadric, labels.json and camera.json."""
    root = tmp_path_factory.mktemp("fit_inputs")
    camera = Camera.default(48)
    rotations = random_rotations(2, generator=torch.Generator().manual_seed(2),
                                 dtype=torch.float64)
    translations = torch.tensor([[0.05, 0.0, 2.0], [0.0, -0.05, 2.2]], dtype=torch.float64)
    target = Assembly.from_values(torch.tensor([[[0.4, 0.25, 0.15]]], dtype=torch.float64),
                                  torch.tensor([[[0.1, 0.1]]], dtype=torch.float64))
    with torch.no_grad():
        masks = render_assembly(target, rotations, translations,
                                SilhouetteRenderer(camera, spp=32)) > 0.5
    paths = []
    for index, mask in enumerate(masks):
        path = root / f"img{index:06d}.png"
        Image.fromarray((mask.numpy() * 255).astype(np.uint8)).save(path)
        paths.append(path)
    quaternions = matrix_to_quaternion(rotations)
    labels = [{"filename": f"img{i:06d}.jpg", "q_vbs2tango_true": quaternions[i].tolist(),
               "r_Vo2To_vbs_true": translations[i].tolist()} for i in (1, 0)]
    (root / "labels.json").write_text(json.dumps(labels))
    (root / "camera.json").write_text(json.dumps(camera.to_speed_dict()))
    return root, paths


def test_fit_command_writes_assembly_mesh_and_figure(fit_inputs, tmp_path, capsys):
    root, masks = fit_inputs
    out = tmp_path / "fit"
    code = main(["fit", "--masks", *map(str, masks), "--poses", str(root / "labels.json"),
                 "--camera", str(root / "camera.json"), "--primitives", "1", "--steps", "4",
                 "--resolution", "32", "--out", str(out), "--quiet"])
    assert code == 0
    assert "mean IoU" in capsys.readouterr().out
    assembly = Assembly.load(out / "assembly.json")
    assert assembly.params.shape == (1, 1, 16)
    assert (out / "assembly.glb").read_bytes()[:4] == b"glTF"
    assert (out / "fit.png").read_bytes()[:4] == b"\x89PNG"
    log = json.loads((out / "fit_log.json").read_text())
    assert len(log["final_iou"]) == 2 and len(log["loss_per_step"]) == 4
    assert not list(out.glob(".*tmp*"))  # atomic writes leave no temporary files


def test_fit_help_documents_the_input_format(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    assert "q_vbs2tango_true" in capsys.readouterr().out


def test_fit_command_input_errors(fit_inputs, tmp_path, capsys):
    root, masks = fit_inputs
    base = ["fit", "--poses", str(root / "labels.json"), "--out", str(tmp_path / "o"),
            "--steps", "1", "--quiet"]
    stray = tmp_path / "other.png"
    Image.fromarray(np.zeros((48, 48), np.uint8)).save(stray)
    assert main([*base, "--masks", str(stray)]) == 2
    assert "no label" in capsys.readouterr().err
    assert main([*base, "--masks", str(tmp_path / "missing.png")]) == 2
    assert "missing.png" in capsys.readouterr().err
    bad_labels = tmp_path / "labels.json"
    bad_labels.write_text(json.dumps([{"filename": masks[0].name, "q_vbs2tango_true": [1, 0],
                                       "r_Vo2To_vbs_true": [0, 0, 2]}]))
    assert main(["fit", "--masks", str(masks[0]), "--poses", str(bad_labels),
                 "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "quaternion" in capsys.readouterr().err
    assert main([*base, "--masks", str(masks[0]), "--primitives", "0"]) == 2
    assert not (tmp_path / "o").exists()
