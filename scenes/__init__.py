"""Shipped scene presets (``space.json``, ``materials.json``), installed as package data
``sq_mitsuba.scenes`` so they are found from a wheel as well as from a checkout."""
