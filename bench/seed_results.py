"""The result documents of ``bench paper_tables``, without torch: when two documents are of the
same setting, and one document from several (one process per seed, ``<name>_seed*.json``).
``paper_tables --merge``, ``compare_settings`` and ``bench report`` (which must not import the
training stack) read them through this module.

A document: ``{"date", "command", "machine", "load_average", "total_seconds", "config":
{..., "seeds", "train_config": {method: config}}, "methods": {method: aggregate}}``; each
method's ``runs`` are per-seed entries ``{"seed", "n_gaussians", "train_seconds", "densified",
<region>: {<metric>: value, "box_px", ...}}``.
"""

from __future__ import annotations

import json
from pathlib import Path

from bench.stats import mean_std

REGIONS = ("full", "hand", "face")
METRICS = ("psnr", "ssim", "lpips_vgg", "lpips_alex")
LOWER_IS_BETTER = {"psnr": False, "ssim": False, "lpips_vgg": True, "lpips_alex": True}


def results_config(train_config: dict) -> dict:
    """A method's train config without the entries that never change a result, so that runs made
    before such an entry existed compare equal: the LPIPS cache size (memory), the thread count
    (compared at the top level, where it has moved), LPIPS on every step (``lpips_every`` 1),
    the weight MLP's centres not detached, per-frame pose correction when off, regularisers when
    all their weights are 0, and the skinning-field settings of mesh skinning."""
    out = {k: v for k, v in train_config.items() if k != "threads"}
    loss = {k: v for k, v in out.get("loss", {}).items() if k != "lpips_cache_mb"}
    if loss.get("lpips_every", 1) == 1:
        loss.pop("lpips_every", None)
    out["loss"] = loss
    avatar = dict(out.get("avatar", {}))
    if not avatar.get("detach_weight_inputs", False):
        avatar.pop("detach_weight_inputs", None)
    out["avatar"] = avatar
    if not (out.get("pose_correction") or {}).get("enabled", False):
        out.pop("pose_correction", None)
    if not any(v for k, v in (out.get("regularizers") or {}).items() if k.startswith("lambda_")):
        out.pop("regularizers", None)
    avatar = dict(out.get("avatar", {}))
    if avatar.get("skinning", "mesh") == "mesh" and not avatar.get("latent_bones"):
        for key in ("skinning", "field_resolution", "latent_bones"):
            avatar.pop(key, None)
    out["avatar"] = avatar
    return out


def same_settings(a: dict, b: dict) -> bool:
    """Two result configs of one benchmark setting: equal but for the seeds, the data-derived
    entries and the set of methods (a method both ran must have run with the same config, up to
    the entries ``results_config`` drops)."""
    keys = ("size", "preset", "iterations", "refine", "threads", "pixel_norm")
    if any(a.get(k) != b.get(k) for k in keys):
        return False
    defaults = {"synth": "controlled", "scale": 1.0}
    if any(a.get(k, v) != b.get(k, v) for k, v in defaults.items()):
        return False
    ta, tb = a.get("train_config", {}), b.get("train_config", {})
    return all(results_config(ta[m]) == results_config(tb[m]) for m in ta.keys() & tb.keys())


def aggregate(runs: list[dict]) -> dict:
    """Per-method summary over its per-seed runs (the result file's shape)."""
    out = {
        "seeds": [r["seed"] for r in runs],
        "n_gaussians": mean_std([r["n_gaussians"] for r in runs]),
        "train_seconds": mean_std([r["train_seconds"] for r in runs]),
        "densified": mean_std([r["densified"] for r in runs]),
    }
    for region in REGIONS:
        if all(region in r for r in runs):
            out[region] = {m: mean_std([r[region][m] for r in runs]) for m in METRICS}
            out[region]["box_px"] = mean_std([r[region]["box_px"] for r in runs])
    out["runs"] = runs
    return out


def union_of_runs(docs: list[dict]) -> dict[str, dict[int, dict]]:
    """{method or row: {seed: run}} over ``docs`` (one process per seed): a seed run twice keeps
    its first run."""
    runs: dict[str, dict[int, dict]] = {}
    for doc in docs:
        for method, entry in doc["methods"].items():
            for run in entry["runs"]:
                runs.setdefault(method, {}).setdefault(run["seed"], run)
    return runs


def merged_header(docs: list[dict]) -> dict:
    """The run header of one document made from ``docs``: the last date, every command, the
    first's machine and the seconds they took together."""
    return {
        "date": max(d["date"] for d in docs),
        "command": " && ".join(d["command"] for d in docs),
        "machine": docs[0]["machine"],
        "total_seconds": sum(d["total_seconds"] for d in docs),
    }


def merge(docs: list[dict]) -> dict:
    """One result document from several of the same settings (e.g. one process per seed): the
    union of their runs (a seed run twice keeps its first run), re-aggregated."""
    if not docs:
        raise ValueError("nothing to merge")
    for doc in docs[1:]:
        if not same_settings(docs[0]["config"], doc["config"]):
            raise ValueError("cannot merge results of different settings (see their config)")
    runs = union_of_runs(docs)
    seeds = sorted({s for by_seed in runs.values() for s in by_seed})
    return {
        **merged_header(docs),
        "load_average": [max(x) for x in zip(*(d["load_average"] for d in docs), strict=True)],
        "wall_seconds": max(d["total_seconds"] for d in docs),
        "config": {
            **docs[0]["config"],
            "seeds": seeds,
            "train_config": {m: c for d in docs for m, c in d["config"]["train_config"].items()},
        },
        "methods": {m: aggregate([by_seed[s] for s in sorted(by_seed)]) for m, by_seed in runs.items()},
    }


def load_seeds(folder: Path, name: str) -> dict:
    """One document from ``folder/<name>_seed*.json`` (``merge``); FileNotFoundError without any."""
    files = sorted(folder.glob(f"{name}_seed*.json"))
    if not files:
        raise FileNotFoundError(f"no results {folder}/{name}_seed*.json")
    return merge([json.loads(f.read_text()) for f in files])


def runs_by_seed(doc: dict) -> dict[str, dict[int, dict]]:
    """{method: {seed: run entry}} of a document."""
    return {method: {r["seed"]: r for r in entry["runs"]} for method, entry in doc["methods"].items()}
