"""The face-mesh files shipped in the package: current for the code and the installed body model
and MediaPipe, read instead of built, and ignored (built again) where their key is stale."""

from __future__ import annotations

import gzip
import json

import pytest
import torch

from eva_engine.align import face_calibration, face_mesh
from eva_engine.align.shipped_face_files import shipped_file

REGENERATE = "stale: run `make face-mesh-files` and commit eva_engine/align/shipped/"


def shipped_doc(file_name: str) -> dict:
    return json.loads(gzip.decompress(shipped_file(file_name).read_bytes()))


def test_the_shipped_files_are_current(anny_model):
    corr_doc = shipped_doc(face_mesh.FILE_NAME)
    assert corr_doc["key"] == face_mesh.cache_key(anny_model), REGENERATE
    corr = face_mesh.FaceMeshCorrespondence.from_json(corr_doc)
    assert shipped_doc(face_calibration.FILE_NAME)["key"] == face_calibration.cache_key(corr), REGENERATE


def test_an_empty_cache_reads_the_shipped_files_without_building(anny_model, tmp_path, monkeypatch):
    def no_build(*args, **kwargs):
        raise AssertionError("built although the shipped file is current")

    monkeypatch.setattr(face_mesh, "build_correspondence", no_build)
    monkeypatch.setattr(face_calibration, "build_calibration", no_build)
    corr = face_mesh.load_correspondence(anny_model, cache_dir=tmp_path)
    calibration = face_calibration.load_calibration(anny_model, corr, cache_dir=tmp_path)
    expected = face_mesh.FaceMeshCorrespondence.from_json(shipped_doc(face_mesh.FILE_NAME))
    assert torch.equal(corr.faces, expected.faces) and torch.equal(corr.barycentric, expected.barycentric)
    assert torch.equal(calibration.gain, torch.tensor(shipped_doc(face_calibration.FILE_NAME)["gain"]))


@pytest.mark.parametrize("content", ["stale key", "not gzip"])
def test_a_stale_or_broken_shipped_file_is_built_again(anny_model, tmp_path, monkeypatch, content):
    shipped = tmp_path / "shipped" / f"{face_mesh.FILE_NAME}.gz"
    shipped.parent.mkdir()
    doc = {**shipped_doc(face_mesh.FILE_NAME), "key": "0" * 16}
    shipped.write_bytes(gzip.compress(json.dumps(doc).encode()) if content == "stale key" else b"{")
    built = face_mesh.FaceMeshCorrespondence.from_json(shipped_doc(face_mesh.FILE_NAME))
    monkeypatch.setattr(face_mesh, "SHIPPED_DIR", shipped.parent)
    calls = []
    monkeypatch.setattr(face_mesh, "build_correspondence", lambda *a, **k: calls.append(1) or built)
    assert face_mesh.load_correspondence(anny_model, cache_dir=tmp_path / "cache") is built
    assert calls == [1]
    assert (tmp_path / "cache" / face_mesh.FILE_NAME).is_file()  # cached for the next time
