"""Rendering layer: Mitsuba 3 and Dr.Jit, imported lazily.

Backend set-up (:func:`sq_mitsuba.render.backend.mitsuba`), differentiable silhouettes bridged
into torch, the physically based space scene and its configuration, depth maps, material
presets and model previews. Imports the geometry layer only; the geometry layer never imports
this one.
"""
