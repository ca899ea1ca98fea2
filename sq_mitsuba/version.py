"""The package version (one place: the package root re-exports it, ``sq-mitsuba --version``
prints it; keep it equal to pyproject.toml's, which tests/test_packaging.py checks)."""

__version__ = "0.1.0"
