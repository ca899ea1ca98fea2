"""Datasets in the SPE3R layout, one module per role.

- :mod:`.layout`: paths, splits, labels, manifest and model files (what every role shares);
- :mod:`.render_options`: the render's settings, its summary, the checks before any work;
- :mod:`.manifest`: ``dataset.json``: what it records, how a run's settings compare;
- :mod:`.writer`: render a dataset with Mitsuba's path tracer (manifest, resume, grow, shards);
- :mod:`.dataset`: :class:`Spe3rDataset`, a torch Dataset over ours or the SPE3R release;
- :mod:`.check`: bookkeeping, every file, and masks re-rendered at label poses;
- :mod:`.preview`: a contact sheet with mask outlines and body axes.
"""

from sq_mitsuba.data.spe3r.check import CheckOptions, CheckReport, check_dataset
from sq_mitsuba.data.spe3r.dataset import MissingModelWarning, Spe3rDataset
from sq_mitsuba.data.spe3r.layout import (
    FAILURES,
    IMAGES,
    MANIFEST,
    MASKS,
    MESH_FILE,
    MODELS,
    SAMPLE_ARRAYS,
    SAMPLES_FILE,
    VALIDATION_INDICES,
    DatasetError,
    check_model_points,
    dataset_models,
    is_validation,
    label_problem,
    load_model,
    read_manifest,
    read_samples,
    read_splits,
    validation_indices,
)
from sq_mitsuba.data.spe3r.preview import PreviewOptions, preview_dataset
from sq_mitsuba.data.spe3r.render_options import (
    RenderOptions,
    RenderSummary,
    estimate_render_memory,
)
from sq_mitsuba.data.spe3r.writer import render_dataset, render_image, render_model

__all__ = [
    "FAILURES", "IMAGES", "MANIFEST", "MASKS", "MESH_FILE", "MODELS", "SAMPLES_FILE",
    "SAMPLE_ARRAYS", "VALIDATION_INDICES", "CheckOptions", "CheckReport", "DatasetError",
    "MissingModelWarning", "PreviewOptions", "RenderOptions", "RenderSummary", "Spe3rDataset",
    "check_dataset", "check_model_points", "dataset_models", "estimate_render_memory",
    "is_validation", "label_problem", "load_model", "preview_dataset", "read_manifest",
    "read_samples", "read_splits", "render_dataset", "render_image", "render_model",
    "validation_indices",
]
