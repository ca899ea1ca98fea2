"""The wheel: every package folder is listed in pyproject.toml, and the scenes ship inside.

The wheel is built offline (``pip wheel --no-deps --no-build-isolation --no-index``) from a
copy of the sources in a temporary folder, so that setuptools' ``build/`` and ``*.egg-info``
never land in the working tree.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "sq_mitsuba"
SCENES = ROOT / "scenes"


def _listed_packages() -> list[str]:
    with open(ROOT / "pyproject.toml", "rb") as handle:
        return tomllib.load(handle)["tool"]["setuptools"]["packages"]


def _package_folders() -> set[str]:
    """Dotted names of sq_mitsuba and every folder under it that holds Python modules."""
    found = set()
    for folder in [PACKAGE, *PACKAGE.rglob("*")]:
        if folder.is_dir() and folder.name != "__pycache__" and any(folder.glob("*.py")):
            found.add(".".join(folder.relative_to(ROOT).parts))
    return found


def test_pyproject_lists_every_package_folder():
    listed = _listed_packages()
    assert len(listed) == len(set(listed)), "a package is listed twice"
    assert set(listed) == _package_folders() | {"sq_mitsuba.scenes"}
    # Every listed package is importable as a package (has an __init__.py).
    for name in listed:
        folder = SCENES if name == "sq_mitsuba.scenes" else ROOT.joinpath(*name.split("."))
        assert (folder / "__init__.py").is_file(), name


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    source = tmp_path_factory.mktemp("source")
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    shutil.copytree(PACKAGE, source / "sq_mitsuba", ignore=ignore)
    shutil.copytree(SCENES, source / "scenes", ignore=ignore)
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "--no-index", "--quiet", "-w", str(out), str(source)],
                   check=True, capture_output=True, text=True, timeout=120)
    wheels = list(out.glob("sq_mitsuba-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def test_wheel_ships_the_scenes_and_every_module(wheel):
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        space = archive.read("sq_mitsuba/scenes/space.json")
        materials = archive.read("sq_mitsuba/scenes/materials.json")
    assert space == (SCENES / "space.json").read_bytes()
    assert materials == (SCENES / "materials.json").read_bytes()
    for scene in SCENES.glob("*.json"):
        assert f"sq_mitsuba/scenes/{scene.name}" in names
    modules = {path.relative_to(ROOT).as_posix() for path in PACKAGE.rglob("*.py")
               if "__pycache__" not in path.parts}
    assert modules <= names, sorted(modules - names)
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    with zipfile.ZipFile(wheel) as archive:
        assert "sq-mitsuba = sq_mitsuba.cli:main" in archive.read(entry_points).decode()


def test_wheel_ships_the_trained_model(wheel):
    shipped = PACKAGE / "model" / "weights" / "model.pt"
    assert shipped.is_file(), "the shipped model is part of the repository"
    with zipfile.ZipFile(wheel) as archive:
        assert archive.read("sq_mitsuba/model/weights/model.pt") == shipped.read_bytes()


def test_the_version_is_the_one_pyproject_declares():
    import tomllib

    import sq_mitsuba

    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert sq_mitsuba.__version__ == declared
