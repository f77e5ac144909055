"""Where a blink is lost (issue 39): the lid gap along the blink action, as the fit's model sees
it, as MediaPipe reads it on renders, and on a trained avatar.

    .venv/bin/python -m bench blink_sweep --dataset $V/dataset --avatar $V/avatar-product-s0 \
        --name blink_sweep --out bench/results/expressions/blink

Both lids' ``eyeBlinkLeft`` and ``eyeBlinkRight`` (or the ``--actions`` given, e.g.
``eyeWideLeft,eyeWideRight``; ``all``: every coefficient, so ``--blinks 0`` is the rest face)
are set to each value of ``--blinks``, every other coefficient kept. The gap is signed: the
lower lid's landmark minus the upper one's (159-145, 386-374), across the eye-corner line
(33-263), over the corner distance; it is negative once the upper landmark has passed the
lower one. Three sources:

- ``anny``: the painted neutral Anny face rendered head-on (``align.face_mesh.render_face``):
  MediaPipe on each render against the correspondence points the fit matches (``model``);
- ``fitted``: with ``--dataset``, the frame the target shows most closed (or ``--frame``), its
  fitted parameters with the blink swept: the correspondence points posed and projected;
- ``avatar``: with ``--avatar``, MediaPipe on the avatar's render of that frame, same sweep,
  and a sheet: target | render with the fitted blink | render at each swept value | the fitted
  render without the Gaussians attached to vertices the blink moves (where the eye's look lives).

Writes ``<name>.json``, ``<name>.md`` and, with an avatar, ``<name>.jpg``.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import torch

from bench.machine import header_line, run_header, write_result
from bench.stats import zero_crossing

RESULTS = Path(__file__).resolve().parent / "results" / "expressions"
LIDS = ((159, 145), (386, 374))
CORNERS = (33, 263)
BLINKS = ("eyeBlinkLeft", "eyeBlinkRight")


def signed_lid_gap(marks: torch.Tensor | np.ndarray | None) -> float:
    """Mean signed lid gap over the corner distance of one face's [478, >=2] pixel landmarks
    (module docstring); NaN without a face."""
    if marks is None:
        return float("nan")
    xy = torch.as_tensor(np.asarray(marks), dtype=torch.float64)[:, :2]
    axis = xy[CORNERS[1]] - xy[CORNERS[0]]
    scale = axis.norm()
    if scale <= 0:
        return float("nan")
    normal = torch.stack([-axis[1], axis[0]]) / scale  # image y points down: lower lid is +
    if normal[1] < 0:
        normal = -normal
    return float(sum(((xy[b] - xy[a]) @ normal) for a, b in LIDS) / (len(LIDS) * scale))


def with_actions(params, names: list[str], actions: tuple[str, ...], value: float):
    """``params`` with each of ``actions`` (expression names) set to ``value``."""
    e = params.expression.clone()
    for n in actions:
        e[..., names.index(n)] = value
    return dataclasses.replace(params, expression=e)


def anny_sweep(model, reg, ids, values: list[float], actions: tuple[str, ...]) -> dict:
    from eva_engine.align.face_mesh import detect_face_mesh, render_face
    from eva_engine.eval.expression_fidelity import fitted_landmarks

    out = {"mediapipe": [], "model": []}
    for v in values:
        ex = {n: v for n in actions}
        r = render_face(model, ((0.0, 0.0),), expression=ex)[0]
        out["mediapipe"].append(signed_lid_gap(detect_face_mesh(r["rgb"])))
        p = model.params_from_pose({"expression": ex})
        points = fitted_landmarks(model, p, reg, ids, r["K"][None], r["viewmat"][None])[0]
        out["model"].append(signed_lid_gap(points))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path)
    ap.add_argument("--avatar", type=Path)
    ap.add_argument("--frame", type=int, help="default: the frame whose detected eyes are most closed")
    ap.add_argument("--blinks", default="0,0.25,0.5,0.75,1", help="the values the actions are set to")
    ap.add_argument(
        "--actions", default=",".join(BLINKS), help="the expression actions swept together, or all"
    )
    ap.add_argument("--name", default="blink_sweep")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    from eva_engine.align.face_mesh import detect_face_mesh, load_correspondence
    from eva_engine.body import load_body_model
    from eva_engine.eval.expression_fidelity import fitted_landmarks

    values = [float(v) for v in args.blinks.split(",")]
    actions = tuple(args.actions.split(","))
    model = load_body_model("anny")
    corr = load_correspondence(model)
    reg, ids = corr.regressor(model)
    names = list(model.expression_names)
    swept = list(actions)  # as asked: ["all"] stays one word in the files
    if actions == ("all",):
        actions = tuple(names)
    if unknown := [a for a in actions if a not in names]:
        raise SystemExit(f"--actions: {', '.join(unknown)} not among the body model's expression names")
    doc: dict = {
        **run_header(),
        "actions": swept,
        "blinks": values,
        "anny": anny_sweep(model, reg, ids, values, actions),
    }
    sheet = None
    if args.dataset is not None:
        from eva_engine.data import load_dataset

        ds = load_dataset(args.dataset)
        stored = ds.keypoint_extras.get("face_mesh")
        if ds.params is None or stored is None:
            raise SystemExit(f"{args.dataset} has no fitted parameters or face-mesh detections")
        detected = [signed_lid_gap(m) if m[:468, 2].amax() > 0 else float("inf") for m in stored]
        i = args.frame if args.frame is not None else int(np.argmin(detected))
        p = ds.params[[i]]
        K, view = ds.K[[i]], ds.viewmat[[i]]

        def model_gap(q) -> float:
            return signed_lid_gap(fitted_landmarks(model, q, reg, ids, K, view)[0])

        doc["fitted"] = {
            "dataset": str(args.dataset),
            "frame": i,
            "detected": detected[i],
            "fitted_blinks": [round(float(p.expression[0, names.index(n)]), 3) for n in actions],
            "fitted": model_gap(p),
            "model": [model_gap(with_actions(p, names, actions, v)) for v in values],
        }
        if args.avatar is not None:
            from eva_engine.avatar import Camera, load_saved_avatar

            av = load_saved_avatar(args.avatar).avatar.eval()
            f = ds[i]
            h, w = f.image.shape[:2]
            cam = Camera(f.K.float(), f.viewmat.float(), w, h)
            bg = torch.ones(3)

            def render(q) -> np.ndarray:
                with torch.no_grad():
                    img = av(q[0], cam, bg).image
                return (img.clamp(0, 1).numpy() * 255).round().astype(np.uint8)

            target = (f.image.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
            images = [render(p)] + [render(with_actions(p, names, actions, v)) for v in values]
            gaps = [signed_lid_gap(detect_face_mesh(im)) for im in images]
            # The Gaussians whose vertex the actions move, hidden: what is left of the eye.
            rest = [av.body(with_actions(p, names, actions, v)).rest[0] for v in (0.0, 1.0)]
            moved = ((rest[1] - rest[0]).norm(dim=-1) > 1e-4)[av.gaussians.vertex_ids]
            opacities = av.gaussians.splats["opacities"].data
            kept = opacities.clone()
            opacities[moved] = -30.0
            images.append(render(p))
            opacities.copy_(kept)
            doc["avatar"] = {
                "avatar": str(args.avatar),
                "target_mediapipe": signed_lid_gap(detect_face_mesh(target)),
                "fitted": gaps[0],
                "mediapipe": gaps[1:],
                "gaussians": int(moved.numel()),
                "gaussians_moved_by_blink": int(moved.sum()),
            }
            xy = stored[i, :468, :2]
            (x0, y0), (x1, y1) = xy.min(0).values.int().tolist(), xy.max(0).values.int().tolist()
            pad = (x1 - x0) // 6
            y0, x0 = max(0, y0 - pad), max(0, x0 - pad)
            sheet = np.concatenate([im[y0 : y1 + pad, x0 : x1 + pad] for im in [target, *images]], axis=1)

    args.out.mkdir(parents=True, exist_ok=True)
    write_result(args.out, args.name, doc, markdown(doc))
    if sheet is not None:
        from PIL import Image

        Image.fromarray(sheet).save(args.out / f"{args.name}.jpg", quality=90)
    print(markdown(doc))


def markdown(doc: dict) -> str:
    def row(label: str, gaps: list[float]) -> str:
        cells = " | ".join(f"{g:+.3f}" for g in gaps)
        closes = zero_crossing(doc["blinks"], gaps)
        return f"| {label} | {cells} | {closes if closes is not None else '–'} |"

    head = " | ".join(f"{v:g}" for v in doc["blinks"])
    actions = doc.get("actions", list(BLINKS))  # files before --actions swept the blinks
    every = actions == ["all"]
    swept = "every expression coefficient" if every else ", ".join(actions)
    lines = [
        f"# Lid gap along {swept}",
        "",
        header_line(doc),
        f"- machine: {doc['machine']}",
        "",
        "Signed lid gap (lower minus upper landmark, 159-145 and 386-374) over the eye-corner",
        f"distance, with {swept} set to each value; negative: the upper landmark has passed the",
        "lower one. Last column: the value where the gap first reaches zero.",
        "",
        f"| source | {head} | closes at |",
        "|---|" + "---:|" * (len(doc["blinks"]) + 1),
        row("Anny render, MediaPipe", doc["anny"]["mediapipe"]),
        row("Anny, correspondence points", doc["anny"]["model"]),
    ]
    fitted = doc.get("fitted")
    if fitted:
        lines.append(row(f"frame {fitted['frame']}, fitted face, correspondence points", fitted["model"]))
    avatar = doc.get("avatar")
    if avatar:
        lines.append(row(f"frame {fitted['frame']}, avatar render, MediaPipe", avatar["mediapipe"]))
    if fitted:
        lines += [
            "",
            f"Frame {fitted['frame']} of `{fitted['dataset']}`: detected gap {fitted['detected']:+.3f}; "
            + ("the coefficients as fitted (the JSON)" if every else _fitted(actions, fitted))
            + f", whose correspondence gap is {fitted['fitted']:+.3f}.",
        ]
    if avatar:
        lines += [
            f"MediaPipe on the target frame: {avatar['target_mediapipe']:+.3f}; on the avatar's render "
            f"as fitted: {avatar['fitted']:+.3f} (`{avatar['avatar']}`).",
            "",
            f"The actions move the vertices of {avatar['gaussians_moved_by_blink']} of the avatar's "
            f"{avatar['gaussians']} Gaussians.",
            "",
            "Sheet: target | render, as fitted | render at each value above | render, as fitted, "
            "without the Gaussians the actions move.",
        ]
    return "\n".join(lines) + "\n"


def _fitted(names: list[str], fitted: dict) -> str:
    """The swept actions' fitted coefficients, in words."""
    return "fitted " + ", ".join(f"{n} {v}" for n, v in zip(names, fitted["fitted_blinks"], strict=True))


if __name__ == "__main__":
    main()
