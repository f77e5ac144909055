"""The calibrations compared here, written as JSON to OUT (``README.md``): ``shipped.json``, the
calibration shipped before this folder (eye outlines uncalibrated); ``every.json``, its eye
outlines regressed on the renders without a blink, every action's gain but the blinks' kept;
``eye.json``, the same with only the eye's own actions' gains (eyeSquint, eyeWide, eyeLook*).
The renders are the calibration's own (the same draw, views and detector; about a minute).

    PYTHONPATH=. python bench/results/expressions/lid_calibration/variant.py $TMPDIR/lidcal

``shipped.json`` copies ``align/shipped/``'s file (unchanged by this folder); the renders are read
by ``face_calibration.calibration_readings``, what ``build_calibration`` regresses.
"""

from __future__ import annotations

import gzip
import json
import sys
from pathlib import Path

import numpy as np
import torch


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
    x, y = fc.calibration_readings(model, corr)
    names = list(model.expression_names)
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
