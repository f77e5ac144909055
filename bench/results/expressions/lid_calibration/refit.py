"""A dataset's clip fitted again from its stored detections by the product's fit under one
calibration of ``variant.py`` (``README.md``); the copy shares the frames (hard links).

    PYTHONPATH=. python bench/results/expressions/lid_calibration/refit.py SRC DST [CALIBRATION.json]

Without a calibration file, the fit's own (``load_calibration``); the control (``ctl``) ran so
on the tree before the change, the shipped calibration.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch


def main(src: str, dst: str, calibration: str | None = None) -> None:
    import eva_engine.align.objective as objective
    from bench.expressions import stored_targets
    from eva_engine.align.clip import fit_clip
    from eva_engine.align.face_calibration import DetectorCalibration
    from eva_engine.align.stages import FitConfig
    from eva_engine.body import load_body_model
    from eva_engine.data import load_dataset
    from eva_engine.data.dataset import ParamNames, _save_params

    torch.set_num_threads(1)
    if calibration is not None:
        cal = DetectorCalibration.from_json(json.loads(Path(calibration).read_text()))
        objective.load_calibration = lambda *a, **k: cal
    source, target = Path(src), Path(dst)
    model = load_body_model("anny")
    ds = load_dataset(source)
    started = time.perf_counter()
    fit = fit_clip(model, stored_targets(ds), ds.timestamps, FitConfig())
    print(f"fitted {len(ds)} frames in {time.perf_counter() - started:.0f} s", flush=True)
    if target.exists():
        shutil.rmtree(target)
    subprocess.run(["cp", "-al", str(source), str(target)], check=True)
    for avatar in target.glob("avatar-*"):
        shutil.rmtree(avatar)
    (target / "params.safetensors").unlink()
    _save_params(target / "params.safetensors", fit.params, ParamNames.of(model), "fitted")


if __name__ == "__main__":
    main(*sys.argv[1:])
