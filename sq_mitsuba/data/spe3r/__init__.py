"""Datasets in the SPE3R layout, one module per role.

- :mod:`.layout`: paths, splits, labels and model files (what every role shares);
- :mod:`.writer`: render a dataset with Mitsuba's path tracer;
- :mod:`.dataset`: :class:`Spe3rDataset`, a torch Dataset over ours or the SPE3R release;
- :mod:`.check`: re-render masks at label poses and compare;
- :mod:`.preview`: a contact sheet with mask outlines and body axes.
"""

from sq_mitsuba.data.spe3r.check import CheckReport, check_dataset
from sq_mitsuba.data.spe3r.dataset import Spe3rDataset
from sq_mitsuba.data.spe3r.layout import (
    IMAGES,
    MASKS,
    MESH_FILE,
    MODELS,
    SAMPLES_FILE,
    VALIDATION_INDICES,
    DatasetError,
    dataset_models,
    load_model,
    read_splits,
)
from sq_mitsuba.data.spe3r.preview import preview_dataset
from sq_mitsuba.data.spe3r.writer import (
    RenderOptions,
    RenderSummary,
    render_dataset,
    render_image,
    render_model,
)

__all__ = [
    "IMAGES", "MASKS", "MESH_FILE", "MODELS", "SAMPLES_FILE", "VALIDATION_INDICES",
    "CheckReport", "DatasetError", "RenderOptions", "RenderSummary", "Spe3rDataset",
    "check_dataset", "dataset_models", "load_model", "preview_dataset", "read_splits",
    "render_dataset", "render_image", "render_model",
]
