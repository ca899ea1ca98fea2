"""Evaluation layer: the protocol that measures a model. :mod:`.evaluate` runs a split and
writes its tables and figures, scoring every method with :mod:`.scoring` (the metrics of
:mod:`sq_mitsuba.geometry.metrics`, the trivial baseline) into the tables of :mod:`.tables`,
over the split read by :mod:`.split`; :mod:`.report` collates evaluations into the paper's
tables, :mod:`.study` sweeps the illumination, :mod:`.mesh_ranking` asks whether the shape is
read from the image, :mod:`.figures` draws. May import every layer below it."""
