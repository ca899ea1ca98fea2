"""The model library's limits: ``generate --workers`` and ``import``'s face count against
memory, refused before any work.

The checks run as on a machine of a given size: ``available_memory`` (the machine's size,
not the part under test) is replaced by a small number, in the module that reads it."""

from __future__ import annotations

from pathlib import Path

import pytest
import trimesh

from sq_mitsuba.cli import main
from sq_mitsuba.data import library, mesh_processing
from sq_mitsuba.data.library import (
    GENERATE_WORKER_BYTES,
    GenerateOptions,
    ImportOptions,
    import_models,
)
from sq_mitsuba.data.mesh_processing import IMPORT_BYTES_PER_FACE, file_face_count
from sq_mitsuba.data.solids import FUSION_RESOLUTION, fusion_memory_bytes

SPHERE_FACES = 1280  # an icosphere of 3 subdivisions


def _machine_of(monkeypatch: pytest.MonkeyPatch, module: object, size: int | None) -> None:
    monkeypatch.setattr(module, "available_memory", lambda *args, **kwargs: size)


@pytest.fixture(scope="module")
def sphere() -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=3)
    assert len(mesh.faces) == SPHERE_FACES
    return mesh


# ------------------------------------------------------------------------ generate


def test_generate_workers_beyond_memory_are_refused(monkeypatch):
    _machine_of(monkeypatch, library, 5 * GENERATE_WORKER_BYTES)
    GenerateOptions(count=256, workers=5)
    with pytest.raises(ValueError, match=r"^workers: 6 \(6 processes\) needs about .* "
                                         r"expected a value in \[1, 5\]$"):
        GenerateOptions(count=256, workers=6)
    # Workers beyond the models start no process; one worker builds in this process.
    GenerateOptions(count=5, workers=256)
    _machine_of(monkeypatch, library, 1)
    GenerateOptions(count=256, workers=1)
    _machine_of(monkeypatch, library, None)  # unknown: not checked
    GenerateOptions(count=256, workers=256)


def test_cli_generate_refuses_before_any_model(tmp_path, monkeypatch, capsys):
    # Room for the parser's defaults (import's depth fusion at its default resolution) and
    # not for 16 generator processes.
    memory = max(fusion_memory_bytes(FUSION_RESOLUTION), 15 * GENERATE_WORKER_BYTES)
    assert memory < 16 * GENERATE_WORKER_BYTES
    _machine_of(monkeypatch, library, memory)
    out = tmp_path / "lib"
    code = main(["models", "generate", "--count", "16", "--workers", "16", "--points", "100",
                 "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert "--workers: 16 (16 processes) needs about" in err
    assert not out.exists()


# ------------------------------------------------------------------------ import


@pytest.mark.parametrize("suffix,kind", [(".stl", "binary"), (".stl", "ascii"), (".ply", None),
                                         (".off", None), (".obj", None)])
def test_face_counts_read_without_parsing(sphere, tmp_path, suffix, kind):
    path = tmp_path / f"sphere{suffix}"
    if kind == "ascii":
        path.write_text(trimesh.exchange.stl.export_stl_ascii(sphere))
    else:
        sphere.export(path)
    assert file_face_count(path) == SPHERE_FACES


def test_face_count_is_unknown_where_the_file_does_not_say(sphere, tmp_path):
    glb = tmp_path / "sphere.glb"
    sphere.export(glb)
    assert file_face_count(glb) is None
    ply = tmp_path / "odd.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    assert file_face_count(ply) is None


def test_cli_import_refuses_a_mesh_beyond_memory_before_any_output(sphere, tmp_path,
                                                                    monkeypatch, capsys):
    stl = tmp_path / "sphere.stl"
    sphere.export(stl)
    _machine_of(monkeypatch, mesh_processing, SPHERE_FACES * IMPORT_BYTES_PER_FACE - 1)
    out = tmp_path / "lib"
    code = main(["models", "import", str(stl), "--out", str(out), "--points", "100"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert f"{stl} ({SPHERE_FACES:,} faces) needs about" in err
    assert not out.exists()


def test_a_mesh_whose_file_does_not_say_is_refused_once_loaded(sphere, tmp_path, monkeypatch):
    glb = tmp_path / "sphere.glb"
    sphere.export(glb)
    _machine_of(monkeypatch, mesh_processing, SPHERE_FACES * IMPORT_BYTES_PER_FACE - 1)
    out = tmp_path / "lib"
    summary = import_models([glb], ImportOptions(out=out, points=100), progress=False)
    assert summary.failures, summary.written
    assert f"{glb} ({SPHERE_FACES:,} faces) needs about" in summary.failures["sphere"]
    assert not (out / "sphere").exists()  # nothing of that model written
    # With room for it, the same file imports.
    _machine_of(monkeypatch, mesh_processing, SPHERE_FACES * IMPORT_BYTES_PER_FACE)
    summary = import_models([glb], ImportOptions(out=out, points=100), progress=False)
    assert summary.ok and Path(out / summary.written[0] / "models").is_dir()
