"""The novel-pose benchmark's tables that are read off its per-frame scores (``bench
novel_pose`` writes them into its Markdown; ``bench report`` quotes them): the view split by
camera angle, and quality against how far a frame lies from what training showed. No torch: the
report imports them."""

from __future__ import annotations

import statistics


def view_breakdown(
    runs: list[dict], keys: tuple[str, ...] = ("lpips_vgg", "debris", "holes")
) -> dict[int, dict[str, float]]:
    """The ``view`` split by camera angle: {35 | 70: {key: mean}} for each of ``keys`` (per-frame
    scores: the full image's by default, ``face_lpips_vgg``, ``closeup_lpips_vgg``), means over
    the frames and then the seeds."""
    by_angle: dict[int, dict[str, list[float]]] = {}
    for r in runs:
        per: dict[int, dict[str, list[float]]] = {}
        for f in r["splits"]["view"]["per_frame"].values():
            angle = round(f["view_deg"])
            d = per.setdefault(angle, {k: [] for k in keys})
            for k in d:
                d[k].append(f[k])
        for angle, d in per.items():
            acc = by_angle.setdefault(angle, {k: [] for k in d})
            for k, v in d.items():
                acc[k].append(statistics.fmean(v))
    return {a: {k: statistics.fmean(v) for k, v in d.items()} for a, d in sorted(by_angle.items())}


YAW_BINS = ((-5.0, 0.0), (0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 50.0), (50.0, 80.0))
POSE_BINS = ((0.0, 20.0), (20.0, 30.0), (30.0, 40.0), (40.0, 55.0), (55.0, 90.0))


def by_novelty(runs: list[dict], train_yaw: dict[int, list[float]]) -> dict[str, list[dict]]:
    """Full-image LPIPS-VGG and debris of every scored frame of every seed, binned by how far the
    camera is outside the training frames' yaw range (degrees beyond it, < 0: inside) and, for
    the training camera's frames (near, far), by the pose's distance to the nearest training
    pose: what the coverage warnings' margins are set from (``avatar.coverage``). train_yaw:
    seed -> the training frames' [min, max] yaw."""
    frames, posed = [], []
    for r in runs:
        lo, hi = train_yaw[r["seed"]]
        for split, scored in r["splits"].items():
            for f in scored["per_frame"].values():
                frames.append({**f, "beyond": max(lo - f["yaw_deg"], f["yaw_deg"] - hi)})
                if split in ("near", "far"):
                    posed.append(f)

    def binned(rows, key, bins):
        out = []
        for a, b in bins:
            sel = [f for f in rows if a <= key(f) < b]
            if sel:
                out.append(
                    {
                        "bin": [a, b],
                        "frames": len(sel),
                        "lpips_vgg": statistics.fmean(f["lpips_vgg"] for f in sel),
                        "debris": statistics.fmean(f["debris"] for f in sel),
                    }
                )
        return out

    return {
        "yaw_beyond": binned(frames, lambda f: f["beyond"], YAW_BINS),
        "pose": binned(posed, lambda f: f["pose_deg"], POSE_BINS),
    }
