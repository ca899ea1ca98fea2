"""Ray-cast previews agree with the projective silhouette renderer."""

from __future__ import annotations

import numpy as np
import torch

from sq_mitsuba.geometry.assembly import Assembly
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.render.preview import render_face_ids
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer, render_assembly


def test_face_ids_cover_the_silhouette_and_name_the_primitives():
    assembly = Assembly.from_values(
        size=torch.tensor([[[0.3, 0.1, 0.1], [0.05, 0.3, 0.02]]]),
        shape=torch.tensor([[[0.2, 0.2], [0.1, 0.1]]]),
        translation=torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.05, -0.2]]]))
    vertices, faces = assembly.merged_mesh(3)
    camera = Camera.default(64)
    translation = torch.tensor([[0.05, 0.0, 1.6]])
    face, shade = render_face_ids((vertices[0] + translation).numpy(), faces.numpy(), camera)
    coverage = render_assembly(assembly, torch.eye(3)[None], translation,
                               SilhouetteRenderer(camera, spp=64))[0].numpy() > 0.5
    hit = face >= 0
    assert (hit & coverage).sum() / (hit | coverage).sum() > 0.98
    primitive = face[hit] // (len(faces) // 2)
    assert set(np.unique(primitive)) == {0, 1}
    assert shade[hit].min() >= 0.25 and shade[hit].max() <= 1.0 and (shade[~hit] == 0).all()
