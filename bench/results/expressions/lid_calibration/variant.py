"""The calibrations compared here, written as JSON to OUT (``README.md``): ``shipped.json``, the
calibration shipped before this folder (eye outlines uncalibrated); ``every.json``, its eye
outlines regressed on the renders without a blink, every action's gain but the blinks' kept;
``eye.json``, the same with only the eye's own actions' gains (eyeSquint, eyeWide, eyeLook*).
The renders are the calibration's own (the same draw, views and detector; about a minute).

    PYTHONPATH=. python bench/results/expressions/lid_calibration/variant.py $TMPDIR/lidcal

Run it on the tree before the change (``git show b50e4b2:eva_engine/align/face_calibration.py``'s
shipped file is what ``shipped.json`` copies).
"""

from __future__ import annotations

import gzip
import json
import sys
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import torch


def renders(model, corr) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The calibration's renders read by the detector: x [S, 1 + E] (a constant first) and
    y [S, L * 2], as ``build_calibration`` regresses them."""
    from mediapipe.python.solutions import face_mesh as mp_face_mesh

    from eva_engine.align import face_calibration as fc
    from eva_engine.align.face_mesh import face_mesh_pixels, head_camera, painted_face_renderer
    from eva_engine.geometry import project_points, to_camera

    reg, landmarks = corr.regressor(model)
    lm = landmarks.numpy()
    names = list(model.expression_names)
    expressions = fc.random_expressions(names, fc.SAMPLES, np.random.default_rng(0))
    cameras = [head_camera(model, yaw, pitch, 512) for yaw, pitch in fc.VIEWS_DEG]
    features, targets = [], []
    with (
        ExitStack() as stack,
        mp_face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=True) as detector,
    ):
        renderer = stack.enter_context(painted_face_renderer(model, 512))
        for expression in expressions:
            params = model.default_params(1)
            params.expression[0] = torch.from_numpy(expression).to(params.expression)
            with torch.no_grad():
                vertices = model(params).vertices[0]
                points = model.posed_points(params, reg)[0].double()
            for K, view in cameras:
                rgb = (renderer.render(vertices, view, K).rgb.numpy() * 255 + 0.5).astype(np.uint8)
                detected = face_mesh_pixels(detector, rgb)
                if detected is None:
                    continue
                uv = project_points(to_camera(points[None], view[None].double()), K[None].double())[0]
                features.append(expression)
                targets.append(fc.in_face_frame(detected[lm] - uv.numpy(), detected))
    x = np.concatenate([np.ones((len(features), 1)), np.array(features)], axis=1)
    return x, np.array(targets).reshape(len(features), -1), names


def main(out: str) -> None:
    from eva_engine.align import face_calibration as fc
    from eva_engine.align.face_mesh import SHIPPED_DIR, load_correspondence
    from eva_engine.body import load_body_model

    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(2)
    model = load_body_model("anny")
    corr = load_correspondence(model)
    shipped = json.loads(gzip.decompress((SHIPPED_DIR / f"{fc.FILE_NAME}.gz").read_bytes()))
    base = fc.DetectorCalibration.from_json(shipped)
    x, y, names = renders(model, corr)
    open_eyes = (x[:, [1 + names.index(n) for n in ("eyeBlinkLeft", "eyeBlinkRight")]] == 0).all(axis=1)
    xo, yo = x[open_eyes], y[open_eyes]
    w = np.linalg.solve(xo.T @ xo + fc.RIDGE * np.eye(x.shape[1]), xo.T @ yo)
    w = torch.from_numpy(w).float().reshape(1 + len(names), -1, 2)
    eye = torch.tensor([int(k) in fc.EYE_CONTOURS for k in base.landmarks])
    keep = {
        "every": [i for i, n in enumerate(names) if n not in ("eyeBlinkLeft", "eyeBlinkRight")],
        "eye": [i for i, n in enumerate(names) if n.startswith("eye") and not n.startswith("eyeBlink")],
    }
    (out_dir / "shipped.json").write_text(json.dumps(base.to_json()))
    for label, actions in keep.items():
        gain = base.gain.clone()
        gain[:, eye] = 0.0
        for a in actions:
            gain[a, eye] = w[1 + a, eye]
        (out_dir / f"{label}.json").write_text(
            json.dumps(fc.DetectorCalibration(base.landmarks, base.bias, gain).to_json())
        )
        print(f"wrote {out_dir / label}.json: {len(actions)} actions' gains, {int(eye.sum())} landmarks")


if __name__ == "__main__":
    main(sys.argv[1])
