"""Mitsuba's limit of 2^32 samples a render, said by every renderer in its own options' words
before any work (past it Mitsuba splits the render into passes: a 1024 px preview at 4096 spp
took 24 GB and was killed for memory; a silhouette of 2048 px at 4096 spp failed inside
Mitsuba as an internal error)."""

from __future__ import annotations

import pytest

from sq_mitsuba.data.contact_sheet import ContactSheetOptions
from sq_mitsuba.geometry.camera import Camera
from sq_mitsuba.render.backend import MAX_SAMPLES_PER_RENDER
from sq_mitsuba.render.silhouette.renderer import SilhouetteRenderer


def test_the_limit_is_mitsubas_wavefront():
    assert MAX_SAMPLES_PER_RENDER == 2**32 - 1


def test_a_preview_of_more_samples_than_a_render_takes_is_refused():
    with pytest.raises(ValueError, match=r"^spp: 4096 at a tile of 1024 x 1024 px is "
                                         r"4,294,967,296 samples per render, more than "
                                         r"Mitsuba's 2\^32 .*; lower --spp or --size$"):
        ContactSheetOptions(size=1024, spp=4096)
    assert ContactSheetOptions(size=1024, spp=4095).spp == 4095  # 1024^2 x 4095 < 2^32


def test_a_silhouette_renderer_of_more_samples_than_a_render_takes_is_refused():
    camera = Camera.from_fov(30.0, 2048, 2048)
    with pytest.raises(ValueError, match=r"^spp: 1024 \(sppp 1\) at 2048 x 2048 px is "
                                         r"4,294,967,296 samples per render"):
        SilhouetteRenderer(camera, spp=1024, sppp=1)
    with pytest.raises(ValueError, match=r"^spp: 1 \(sppp 1024\) at 2048 x 2048 px"):
        SilhouetteRenderer(camera, spp=1, sppp=1024)  # the gradient's edge samples too
