"""What each optimiser does in the face and refine stages: from a clip's stored fit, the two stages
run again (``FitProblem.run_stage``) with the expression's range kept by L-BFGS-B or by the range
penalty (torch's L-BFGS); per stage the loss evaluations, the first and last loss, and after it the
share of expression coefficients outside [0, 1] and the lowest one:

    PYTHONPATH=. python bench/results/expressions/bounded/stages.py data/face39/gesturing-noeyes

One thread; prints one line per variant and stage (``stages.log``)."""

from __future__ import annotations

import sys
import time

import torch

from bench.expressions import stored_targets
from eva_engine.align.objective import FitProblem
from eva_engine.align.stages import FitConfig
from eva_engine.body import load_body_model
from eva_engine.data import load_dataset

torch.set_num_threads(1)
ds = load_dataset(sys.argv[1])
model = load_body_model("anny")
for bounded in (False, True):
    config = FitConfig(bounded_expression=bounded)
    problem = FitProblem(model, stored_targets(ds), config, ds.params)
    for stage in (s for s in config.stages if s.name in ("face", "refine")):
        calls = []
        started = time.perf_counter()
        first, last = problem.run_stage(stage, lambda e, calls=calls: calls.append(e.loss))
        e = problem.values["expression"]
        outside = float(((e < -0.01) | (e > 1.01)).float().mean())
        print(
            f"{'L-BFGS-B' if bounded else 'penalty'} {stage.name}: {len(calls)} loss evaluations "
            f"(of {stage.iterations} iterations), loss {first:.6g} -> {last:.6g}, "
            f"{100 * outside:.0f}% of the coefficients outside [0, 1], lowest {float(e.min()):.2f}, "
            f"{time.perf_counter() - started:.0f} s",
            flush=True,
        )
