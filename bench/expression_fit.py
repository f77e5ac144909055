"""One rendered face, fitted (issue 39): how much of a blink and an open jaw the face stage of the
fit recovers from MediaPipe's face mesh, and whether the true expression is the stage's optimum.

    .venv/bin/python -m bench expression_fit --name one_face --out bench/results/expressions

The painted Anny face is rendered head-on (``align.face_mesh.render_face``) neutral and with
``--truth`` (default: both eyes 80% closed, the jaw half open); MediaPipe's face mesh runs on both
renders. The product's stages that move the expression (``align.stages.default_stages``: "face",
free coefficients, then "refine", which keeps them in their range) then fit it with nothing but
the detected face mesh as targets: from the neutral face, from the true expression, without the
opening term (``FitStage.w_openings``), and the face stage alone (its coefficients clamped to
the range afterwards, as ``fit_sequence`` does). Reported per
run: the inner-lip and lid gaps (``eval.expression_fidelity``, over the eye-corner distance) of
the detected landmarks, of the true face and of each fit, and the largest fitted coefficients.
Writes ``<name>.json`` and ``<name>.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch

from bench.machine import header_line, run_header, write_result

RESULTS = Path(__file__).resolve().parent / "results" / "expressions"


GROUPS = ("jaw", "lips", "lids", "brows")


def recovered(fitted: float, neutral: float, truth: float) -> float:
    """The share of the true change of a gap the fit recovered; NaN when the truth does not change it
    (e.g. a brow raise leaves the lips and lids alone)."""
    change = truth - neutral
    return round((fitted - neutral) / change, 3) if abs(change) > 5e-3 else float("nan")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--truth", default="eyeBlinkLeft=0.8,eyeBlinkRight=0.8,jawOpen=0.5")
    ap.add_argument("--name", default="one_face")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    from eva_engine.align.evaluate import expression_error_by_group, targets_from_params
    from eva_engine.align.face_mesh import NUM_LANDMARKS, detect_face_mesh, load_correspondence, render_face
    from eva_engine.align.fit import fit_sequence
    from eva_engine.align.stages import FitConfig, default_stages
    from eva_engine.body import load_body_model
    from eva_engine.eval.expression_fidelity import fitted_landmarks, openings, surface_gaps

    truth_expr = {k: float(v) for k, v in (item.split("=") for item in args.truth.split(","))}
    model = load_body_model("anny")
    corr = load_correspondence(model)
    reg, ids = corr.regressor(model)
    names = list(model.expression_names)

    def params(expression: dict[str, float]):
        return model.params_from_pose({"expression": expression})

    def detected(rgb) -> torch.Tensor:
        mesh = torch.zeros(1, NUM_LANDMARKS, 3)
        mesh[0, :, :2] = torch.from_numpy(detect_face_mesh(rgb)).float()
        mesh[0, :, 2] = 1.0
        return mesh

    def gaps(landmarks: torch.Tensor) -> dict[str, float]:
        return {k: round(float(v[0]), 4) for k, v in openings(landmarks).items()}

    pairs = {"mouth 13-14": (13, 14), "lids 159-145": (159, 145), "lids 386-374": (386, 374)}

    def gaps_mm(p) -> dict[str, float]:
        mm = (1000 * surface_gaps(model, p, reg, ids, tuple(pairs.values()))[0]).tolist()
        return {k: round(v, 2) for k, v in zip(pairs, mm, strict=True)}

    correspondence = {
        "neutral": gaps_mm(params({})),
        "jawOpen 1": gaps_mm(params({"jawOpen": 1.0})),
        "eyeBlink 1": gaps_mm(params({"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0})),
    }
    truth = params(truth_expr)
    render = render_face(model, ((0.0, 0.0),), expression=truth_expr)[0]
    neutral_render = render_face(model, ((0.0, 0.0),))[0]
    K, view = render["K"], render["viewmat"]
    mesh = detected(render["rgb"])
    projected = {
        "truth": gaps(fitted_landmarks(model, truth, reg, ids, K[None], view[None])),
        "neutral": gaps(fitted_landmarks(model, params({}), reg, ids, K[None], view[None])),
    }
    doc = {
        **run_header(),
        "truth": truth_expr,
        "correspondence_gaps_mm": correspondence,
        "detected": {"truth render": gaps(mesh), "neutral render": gaps(detected(neutral_render["rgb"]))},
        "projected": projected,
        "fits": {},
    }
    base = targets_from_params(model, truth, K, view, image_size=(512, 512))
    keypoints = base.keypoints.clone()
    keypoints[..., 2] = 0.0  # nothing but the face mesh
    # The stages of the product's fit that move the expression: "face" (free coefficients), then
    # "refine" (the range penalty keeps them in [0, 1]); the depth term has no targets here.
    stages = tuple(s for s in default_stages() if s.name in ("face", "refine"))

    def without_openings(stages):
        return tuple(dataclasses.replace(s, w_openings=0.0) for s in stages)

    runs = {
        "from neutral": (stages, params({})),
        "from the truth": (stages, truth),
        "no opening term, from neutral": (without_openings(stages), params({})),
        "face stage alone, from neutral": (stages[:1], params({})),
        "face stage alone, no opening term": (without_openings(stages[:1]), params({})),
    }
    neutral_mm = expression_error_by_group(model, params({}), truth)
    doc["neutral_mm"] = {k: round(v, 3) for k, v in neutral_mm.items() if k in GROUPS and v == v}
    targets = dataclasses.replace(base, keypoints=keypoints, face_mesh=mesh)
    for label, (run_stages, init) in runs.items():
        fit = fit_sequence(model, targets, init=init, config=FitConfig(stages=run_stages)).params
        e = fit.expression[0]
        top = sorted(range(len(names)), key=lambda i: -float(e[i]))[:6]
        g = gaps(fitted_landmarks(model, fit, reg, ids, K[None], view[None]))
        doc["fits"][label] = {
            "gaps": g,
            "recovered": {m: recovered(g[m], projected["neutral"][m], projected["truth"][m]) for m in g},
            "expression_mm": {
                k: round(v, 3) for k, v in expression_error_by_group(model, fit, truth).items() if k in GROUPS
            },
            "top_coefficients": {names[i]: round(float(e[i]), 3) for i in top},
        }
        print(label, doc["fits"][label], file=sys.stderr, flush=True)

    lines = [
        "# One rendered face: how much of a blink and an open jaw the face stage recovers",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        f"- truth: {truth_expr}; the painted Anny face, head-on, 512 px",
        "",
        "The correspondence's gaps on the rest face, mm: "
        + "; ".join(f"{k}: {v}" for k, v in correspondence.items()),
        "",
        "Gaps: inner lips (13-14) and lids (159-145, 386-374) over the eye-corner distance (33-263).",
        "",
        f"- MediaPipe on the true render: {doc['detected']['truth render']}; on the neutral render: "
        f"{doc['detected']['neutral render']}",
        f"- the true face's correspondence points: {projected['truth']}; "
        f"the neutral face's: {projected['neutral']}",
        "",
        "Expression error: per facial-action group, mm (``align.evaluate.expression_error_by_group``; "
        "only that group's actions kept in the fit and the truth); a neutral face's: "
        + ", ".join(f"{k} {v:.2f}" for k, v in doc["neutral_mm"].items())
        + ".",
        "",
        "| fit | mouth gap | eyes gap | mouth change recovered | eyes change recovered "
        "| expression error, mm | largest coefficients |",
        "|---|---:|---:|---:|---:|---|---|",
    ]
    for label, f in doc["fits"].items():
        top = ", ".join(f"{k} {v:.2f}" for k, v in f["top_coefficients"].items())
        err = ", ".join(f"{k} {v:.2f}" for k, v in f["expression_mm"].items() if v == v)
        share = {m: "-" if v != v else f"{v:.0%}" for m, v in f["recovered"].items()}
        lines.append(
            f"| {label} | {f['gaps']['mouth']:.3f} | {f['gaps']['eyes']:.3f} | {share['mouth']} "
            f"| {share['eyes']} | {err} | {top} |"
        )
    write_result(args.out, args.name, doc, lines, show=True)


if __name__ == "__main__":
    main()
