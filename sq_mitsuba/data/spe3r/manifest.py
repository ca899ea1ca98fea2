"""The manifest of a dataset in the SPE3R layout (``dataset.json``): what it records
(:func:`manifest_record`: the settings that decide its pixels, the tool, the plan of models
and splits, its state) and how a run's settings are compared with it
(:func:`settings_differences`: one line per setting that differs, the scene's first differing
field named). :mod:`.writer` writes it and refuses a run into a folder of other settings.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

from sq_mitsuba.config import config_hash, to_dict
from sq_mitsuba.data.frames import PASS_FRAMING
from sq_mitsuba.data.spe3r.layout import MANIFEST_FORMAT
from sq_mitsuba.version import __version__

if TYPE_CHECKING:
    from sq_mitsuba.data.spe3r.render_options import RenderOptions
    from sq_mitsuba.geometry.camera import Camera
    from sq_mitsuba.render.scene_config import SceneConfig

__all__ = ["IDENTITY", "dataset_settings", "manifest_plan", "manifest_record",
           "settings_differences"]

#: Settings compared between a run and the manifest of its output folder, in message order.
IDENTITY = ("seed", "resolution", "spp", "exr", "camera", "scene_hash", "pass_frames",
            "pass_framing")
# What a manifest written before a setting existed meant by it (a dataset of independent
# images records no pass framing at all).
_IDENTITY_BEFORE = {"pass_frames": 1, "pass_framing": None}


def dataset_settings(options: RenderOptions, camera: Camera) -> dict[str, Any]:
    """The settings that decide a dataset's pixels, as the manifest records them."""
    settings = {"seed": options.seed, "resolution": options.resolution, "spp": options.spp,
                "exr": options.exr, "camera": camera.to_speed_dict(),
                "scene_hash": config_hash(options.scene), "pass_frames": options.pass_frames}
    if options.pass_frames > 1:
        settings["pass_framing"] = PASS_FRAMING
    return json.loads(json.dumps(settings))  # as read back from the file


def manifest_record(options: RenderOptions, camera: Camera, plan: dict[str, str],
                    counts: dict[str, int], state: str,
                    hashes: dict[str, str] | None = None) -> dict[str, Any]:
    """``dataset.json``'s content: each model of ``plan`` ({model: split}) with its split,
    its image count in ``counts`` and, where given, its ``labels.json``'s SHA-256; the
    settings, the tool, ``images_per_model``, ``state`` ("rendering" or "complete") and the
    scene."""
    models = {}
    for model in sorted(plan):
        entry: dict[str, Any] = {"split": plan[model], "images": counts.get(model, 0)}
        if hashes and model in hashes:
            entry["labels_sha256"] = hashes[model]
        models[model] = entry
    return {
        "format": MANIFEST_FORMAT,
        "tool": {"name": "sq-mitsuba", "version": __version__},
        "settings": dataset_settings(options, camera),
        "images_per_model": options.images_per_model,
        "state": state,
        "models": models,
        "scene": to_dict(options.scene),
    }


def manifest_plan(manifest: dict[str, Any]) -> tuple[Any, ...]:
    """What a manifest promises (not its progress): settings, image count, models, splits."""
    return (manifest["settings"], manifest["images_per_model"],
            {m: e.get("split") for m, e in manifest["models"].items()})


def _describe_camera(camera: Any) -> str:
    try:
        matrix = camera["cameraMatrix"]
        return (f"{camera['Nu']} x {camera['Nv']} px, fx {matrix[0][0]:.6g}, "
                f"cx {matrix[0][2]:.6g}, cy {matrix[1][2]:.6g}")
    except (KeyError, IndexError, TypeError):
        return "unreadable"


def _first_difference(old: Any, new: Any, where: str = "") -> str | None:
    """Dotted path and values of the first difference of two JSON-like trees."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            found = _first_difference(old.get(key), new.get(key), f"{where}.{key}".lstrip("."))
            if found:
                return found
        return None
    return None if old == new else f"{where} {json.dumps(old)}, now {json.dumps(new)}"


def settings_differences(manifest: dict[str, Any], settings: dict[str, Any],
                         scene: SceneConfig) -> list[str]:
    """One line per :data:`IDENTITY` setting in which ``settings`` (a run's
    :func:`dataset_settings`) differ from ``manifest``'s, in that order; empty when none do."""
    stored = manifest["settings"]
    differences = []
    for key in IDENTITY:
        if stored.get(key, _IDENTITY_BEFORE.get(key)) == settings.get(key,
                                                                     _IDENTITY_BEFORE.get(key)):
            continue
        if key == "pass_framing":  # only news where the pass length is the same
            if stored.get("pass_frames", 1) == settings["pass_frames"]:
                differences.append(f"passes placed by an earlier framing ("
                                   f"{json.dumps(stored.get(key, 1))}; this run: "
                                   f"{json.dumps(settings[key])}, every frame holding the "
                                   "whole target)")
            continue
        if key == "camera":
            differences.append(f"camera {_describe_camera(stored.get(key))} (this run: "
                               f"{_describe_camera(settings[key])})")
        elif key == "scene_hash":
            detail = _first_difference(manifest.get("scene"), to_dict(scene))
            differences.append(f"scene config {stored.get(key)} (this run: {settings[key]}"
                               + (f"; {detail}" if detail else "") + ")")
        else:
            differences.append(f"{key} {json.dumps(stored.get(key))} (this run: "
                               f"{json.dumps(settings[key])})")
    return differences
