"""Rendering layer: Mitsuba 3 and Dr.Jit. Import :func:`sq_mitsuba.render.backend.mitsuba`
to get a configured ``mitsuba`` module; nothing here is imported by the geometry layer."""
