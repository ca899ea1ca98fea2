"""Evaluation layer: metrics, figures, reports, studies and the benchmark suites
(:mod:`sq_mitsuba.evaluation.bench`). May import every layer below it."""
