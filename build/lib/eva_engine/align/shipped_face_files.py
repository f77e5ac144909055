"""The face-mesh files shipped in the package (``align/shipped/``): the default Anny's
correspondence (``align.face_mesh``) and its detector calibration (``align.face_calibration``),
built from scratch on the project's own renders and written gzipped with their cache keys.
``load_correspondence`` and ``load_calibration`` read them where the keys match the installed
body model, MediaPipe and code, and build their own otherwise. Run after a change to either key
(a test fails until the shipped keys match the code's):

    make face-mesh-files    # python -m eva_engine.align.shipped_face_files
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

from eva_engine.align import face_calibration, face_mesh
from eva_engine.body import BodyModel, load_body_model


def shipped_file(file_name: str) -> Path:
    return face_mesh.SHIPPED_DIR / f"{file_name}.gz"


def write_shipped_files(model: BodyModel) -> list[Path]:
    """Build the correspondence and the calibration of ``model`` (no cache read) and write both
    to ``align/shipped/``, byte for byte the same for the same content (no time stamp)."""
    with face_mesh.shared_painted_face(model) as renderer:
        corr = face_mesh.build_correspondence(model, renderer=renderer())
        calibration = face_calibration.build_calibration(model, corr, renderer=renderer())
    written = []
    for file_name, key, built in (
        (face_mesh.FILE_NAME, face_mesh.cache_key(model), corr),
        (face_calibration.FILE_NAME, face_calibration.cache_key(corr), calibration),
    ):
        path = shipped_file(file_name)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(gzip.compress(json.dumps({"key": key, **built.to_json()}).encode(), mtime=0))
        written.append(path)
    return written


def main() -> None:
    for path in write_shipped_files(load_body_model("anny")):
        print(f"wrote {path} ({path.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
