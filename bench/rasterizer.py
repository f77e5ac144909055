"""Benchmark of eva_engine.render.rasterize on body-like scenes (CPU by default): today against before.

For N in {2k, 20k, 100k} Gaussians on a 1.7 m human-shaped surface and images of 256^2 and 512^2,
measures forward and forward+backward wall time, CPU time and peak memory of the default
rasterizer in three variants, each run in its own fresh process (so its peak RSS is its own):

- ``before``: the rasterizer as it was at ``--before`` (default 008d8b2, main before the compiled
  kernels; extracted with ``git archive``), its default tiled backend;
- ``torch``: this tree with the pure-torch kernels (``kernel="torch"``, the fallback);
- ``cpp``: this tree with the compiled C++ kernels (``kernel="cpp"``, the default where they build).

The variants are interleaved round by round (``--rounds``), so load from other work on the machine
hits them alike; the report gives the medians over all rounds, their ratios, the load average and
the CPU time (less sensitive to load than wall time). ``--reference`` adds the plain-autograd
reference backend.

    .venv/bin/python -m bench rasterizer            # full grid, writes bench/results/rasterizer.{json,md}
    .venv/bin/python -m bench rasterizer --quick    # fewer repeats and rounds, N <= 20k

Targets (2 CPU cores): 20k @ 512^2 forward+backward <= 60 ms, forward >= 40 FPS; peak
memory <= 0.5 GB.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from bench.machine import cpu_name, run_header, write_result

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results"
THREADS = 2  # the target machine's core count; --threads overrides
BEFORE = "008d8b2"  # main before the compiled kernels
VARIANTS = ("before", "torch", "cpp")


# ----------------------------------------------------------------------------- scene


def _capsule_points(n: int, a, b, radius: float, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """n points on the side of a capsule from a to b, with outward normals."""
    a, b = torch.tensor(a), torch.tensor(b)
    axis = b - a
    length = axis.norm()
    axis = axis / length
    helper = torch.tensor([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else torch.tensor([0.0, 0.0, 1.0])
    u = torch.linalg.cross(axis, helper)
    u = u / u.norm()
    v = torch.linalg.cross(axis, u)
    t = torch.rand(n, 1, generator=gen)
    phi = torch.rand(n, 1, generator=gen) * 2 * math.pi
    normal = torch.cos(phi) * u + torch.sin(phi) * v
    return a + t * axis * length + radius * normal, normal


def _ellipsoid_points(n: int, center, radii, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    d = torch.randn(n, 3, generator=gen)
    d = d / d.norm(dim=-1, keepdim=True)
    radii = torch.tensor(radii)
    normal = d / radii
    return torch.tensor(center) + d * radii, normal / normal.norm(dim=-1, keepdim=True)


def body_scene(n: int, size: int, seed: int = 0) -> dict:
    """N small Gaussians on a 1.7 m figure (Y up, facing +Z) and a camera 2.75 m in front of it.

    Parts (area-weighted): head, torso, pelvis, upper/lower arms and legs. Gaussians are flat
    discs tangent to the surface (scales ~5-10 mm in-plane, 1-2 mm along the normal), like a
    trained avatar's. The camera frames the whole body in a size x size image.
    """
    gen = torch.Generator().manual_seed(seed)
    parts = [  # (kind, args, relative area)
        ("ell", ((0.0, 1.58, 0.0), (0.09, 0.12, 0.10)), 0.06),
        ("ell", ((0.0, 1.22, 0.0), (0.17, 0.25, 0.11)), 0.24),
        ("ell", ((0.0, 0.95, 0.0), (0.16, 0.12, 0.10)), 0.10),
        ("cap", ((-0.2, 1.42, 0.0), (-0.45, 1.15, 0.0), 0.05), 0.06),
        ("cap", ((0.2, 1.42, 0.0), (0.45, 1.15, 0.0), 0.05), 0.06),
        ("cap", ((-0.45, 1.15, 0.0), (-0.62, 0.9, 0.05), 0.04), 0.05),
        ("cap", ((0.45, 1.15, 0.0), (0.62, 0.9, 0.05), 0.04), 0.05),
        ("cap", ((-0.1, 0.9, 0.0), (-0.11, 0.5, 0.0), 0.08), 0.14),
        ("cap", ((0.1, 0.9, 0.0), (0.11, 0.5, 0.0), 0.08), 0.14),
        ("cap", ((-0.11, 0.5, 0.0), (-0.12, 0.08, -0.02), 0.055), 0.05),
        ("cap", ((0.11, 0.5, 0.0), (0.12, 0.08, -0.02), 0.055), 0.05),
    ]
    weights = torch.tensor([p[2] for p in parts])
    # Seeded, so every variant (each in its own process) renders the same scene.
    pick = torch.multinomial(weights, n, replacement=True, generator=gen)
    counts = torch.bincount(pick, minlength=len(parts)).tolist()
    pts, nrm = [], []
    for (kind, args, _), k in zip(parts, counts, strict=True):
        p, q = (_ellipsoid_points if kind == "ell" else _capsule_points)(k, *args, gen=gen)
        pts.append(p)
        nrm.append(q)
    means, normals = torch.cat(pts), torch.cat(nrm)
    from eva_engine.geometry import quat_from_z

    quats = quat_from_z(normals)  # flat discs tangent to the surface
    scales = torch.cat(
        [0.005 + 0.005 * torch.rand(n, 2, generator=gen), 0.001 + 0.001 * torch.rand(n, 1, generator=gen)], -1
    )
    opacities = 0.5 + 0.5 * torch.rand(n, generator=gen)
    colors = torch.rand(n, 3, generator=gen)
    # OpenCV camera at (0, 0.88, 2.75) looking down -Z: x_cam = X, y_cam = -Y, z_cam = -Z.
    rot = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
    center = torch.tensor([0.0, 0.88, 2.75])
    viewmat = torch.eye(4)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = -rot @ center
    focal = 0.9 * size * 2.75 / 1.75
    K = torch.tensor([[focal, 0.0, size / 2], [0.0, focal, size / 2], [0.0, 0.0, 1.0]])
    return dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmat=viewmat,
        K=K,
        width=size,
        height=size,
        background=torch.ones(3),
    )


# ----------------------------------------------------------------------------- one measurement


def _rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def measure(n: int, size: int, variant: str, mode: str, repeats: int, threads: int) -> dict:
    """Time ``repeats`` runs (after one warm-up) of forward or forward+backward in this process.

    variant: "before" (whatever eva_engine is importable, default config), "torch" or "cpp"
    (kernel of this tree's RasterConfig), or "autograd" (the reference backend).
    """
    from eva_engine.render import RasterConfig, rasterize

    torch.set_num_threads(threads)
    scene = body_scene(n, size)
    if variant == "autograd":
        cfg = RasterConfig(backend="autograd")
    elif variant in ("torch", "cpp"):
        cfg = RasterConfig(kernel=variant)
    else:
        cfg = RasterConfig()
    grads = ("means", "quats", "scales", "opacities", "colors")
    rss_before = _rss_bytes()
    times, cpu_times, pairs = [], [], 0
    for i in range(repeats + 1):
        inputs = dict(scene)
        if mode == "fwd+bwd":
            for k in grads:
                inputs[k] = scene[k].clone().requires_grad_(True)
        c0, t0 = time.process_time(), time.perf_counter()
        if mode == "fwd":
            with torch.no_grad():
                out = rasterize(**inputs, config=cfg)
        else:
            out = rasterize(**inputs, config=cfg)
            (out.image.sum() + out.alpha.sum()).backward()
        elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
        pairs = out.num_intersections * cfg.tile_size**2
        if i > 0:
            times.append(elapsed)
            cpu_times.append(cpu)
    return dict(
        n=n,
        size=size,
        variant=variant,
        mode=mode,
        repeats=repeats,
        times_ms=[1e3 * t for t in times],
        cpu_ms=[1e3 * t for t in cpu_times],
        peak_rss_delta_mb=(_rss_bytes() - rss_before) / 2**20,
        peak_rss_mb=_rss_bytes() / 2**20,
        intersections=out.num_intersections,
        pairs=pairs,
        coverage=float(out.alpha.detach().mean()),
    )


def _run_child(
    code_root: Path, n: int, size: int, variant: str, mode: str, repeats: int, threads: int, wait: str | None
) -> dict:
    cmd = [
        sys.executable,
        "-m",
        "bench.rasterizer",
        "--child",
        f"{n},{size},{variant},{mode},{repeats},{threads}",
    ]
    # The child runs in code_root, first on its path: its eva_engine is this tree's or the extracted
    # "before"; ``bench`` comes from this tree, after it.
    env = dict(
        os.environ, OMP_NUM_THREADS=str(threads), PYTHONPATH=os.pathsep.join([str(code_root), str(ROOT)])
    )
    env.pop("EVA_RASTER_KERNEL", None)
    if wait:
        env["OMP_WAIT_POLICY"] = wait
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=code_root)
    if proc.returncode != 0:
        return dict(n=n, size=size, variant=variant, mode=mode, error=proc.stderr.strip()[-2000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _extract(ref: str, into: Path) -> str:
    """``eva_engine`` as of git ``ref`` under ``into``; returns the full commit hash."""
    commit = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--verify", f"{ref}^{{commit}}"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", commit, "eva_engine"], capture_output=True, check=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return commit


def _build_kernels() -> str | None:
    """Build (or load) this tree's compiled kernels once, outside the timed runs; None if ok."""
    code = "from eva_engine.render.native import RASTER; RASTER.load(); print(RASTER.unavailable_reason())"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    reason = out.stdout.strip().splitlines()[-1] if out.stdout.strip() else out.stderr[-500:]
    return None if reason == "None" else reason


# ----------------------------------------------------------------------------- report


def _interpreter() -> str:
    """The Python that ran this, relative to the repository when it lives there (.venv/bin/python)."""
    exe = Path(sys.executable).absolute()
    return str(exe.relative_to(ROOT)) if exe.is_relative_to(ROOT) else str(exe)


def _load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def _machine(threads: int) -> dict:
    return dict(
        cpu=cpu_name(),
        logical_cores=os.cpu_count(),
        torch_threads=threads,
        torch=torch.__version__,
        python=platform.python_version(),
        platform=platform.platform(),
    )


def _summary(results: list[dict]) -> list[dict]:
    """One row per (n, size, variant, mode): medians over every timed run of every round."""
    groups: dict[tuple, list[dict]] = {}
    for r in results:
        groups.setdefault((r["threads"], r["n"], r["size"], r["variant"], r["mode"]), []).append(r)
    rows = []
    for (threads, n, size, variant, mode), runs in groups.items():
        ok = [r for r in runs if "times_ms" in r]
        row = dict(threads=threads, n=n, size=size, variant=variant, mode=mode)
        if not ok:
            row["note"] = next((r.get("skipped") or "error: " + r["error"][-300:] for r in runs), "")
            rows.append(row)
            continue
        times = [t for r in ok for t in r["times_ms"]]
        cpu = [t for r in ok for t in r["cpu_ms"]]
        median = statistics.median(times)
        row.update(
            runs=len(times),
            median_ms=median,
            min_ms=min(times),
            cpu_median_ms=statistics.median(cpu),
            fps=1e3 / median,
            pairs=ok[0]["pairs"],
            mpairs_per_s=ok[0]["pairs"] / median / 1e3,
            peak_rss_delta_mb=max(r["peak_rss_delta_mb"] for r in ok),
        )
        rows.append(row)
    order = {v: i for i, v in enumerate((*VARIANTS, "autograd"))}
    return sorted(
        rows, key=lambda r: (r["threads"], r["n"], r["size"], r["mode"] != "fwd", order[r["variant"]])
    )


def _find(summary: list[dict], threads: int, n: int, size: int, variant: str, mode: str) -> dict | None:
    for r in summary:
        key = (r["threads"], r["n"], r["size"], r["variant"], r["mode"])
        if key == (threads, n, size, variant, mode) and "median_ms" in r:
            return r
    return None


def _ratios(summary: list[dict]) -> list[dict]:
    """Speed-ups of ``cpp`` over ``before`` and over ``torch`` per (n, size, mode)."""
    out = []
    for r in summary:
        if r["variant"] != "cpp" or "median_ms" not in r:
            continue
        row = dict(threads=r["threads"], n=r["n"], size=r["size"], mode=r["mode"], cpp_ms=r["median_ms"])
        for other in ("before", "torch"):
            o = _find(summary, r["threads"], r["n"], r["size"], other, r["mode"])
            if o:
                row[f"{other}_ms"] = o["median_ms"]
                row[f"speedup_vs_{other}"] = o["median_ms"] / r["median_ms"]
                row[f"cpu_speedup_vs_{other}"] = o["cpu_median_ms"] / r["cpu_median_ms"]
        out.append(row)
    return out


def _targets(summary: list[dict], threads: list[int]) -> list[str]:
    out = []
    for t in threads:
        fb, fw = (
            _find(summary, t, 20_000, 512, "cpp", "fwd+bwd"),
            _find(summary, t, 20_000, 512, "cpp", "fwd"),
        )
        head = f"{t} thread{'s' if t > 1 else ''}:"
        if fb:
            ok = "met" if fb["median_ms"] <= 60 else "NOT met"
            out.append(f"{head} forward+backward <= 60 ms: {fb['median_ms']:.1f} ms ({ok})")
        if fw:
            ok = "met" if fw["fps"] >= 40 else "NOT met"
            out.append(f"{head} forward >= 40 FPS: {fw['fps']:.1f} FPS ({ok})")
        peaks = [r["peak_rss_delta_mb"] for r in (fb, fw) if r]
        if peaks:
            ok = "met" if max(peaks) <= 512 else "NOT met"
            out.append(f"{head} peak memory <= 0.5 GB: {max(peaks):.0f} MB RSS growth ({ok})")
    return out


def _markdown(report: dict) -> str:
    m = report["machine"]
    before = report.get("before_commit") or "unavailable"
    lines = [
        "# Rasterizer benchmark",
        "",
        f"- date: {report['date']}",
        f"- command: `{report['command']}`",
        f"- machine: {m['cpu']}, {m['logical_cores']} logical cores, torch {m['torch']}, Python "
        f"{m['python']}; torch threads {m['torch_threads']}, OMP_WAIT_POLICY "
        f"{report.get('omp_wait_policy') or 'unset (libgomp default: spin)'}",
        f"- load average (1, 5, 15 min) at start {report['load_average_at_start']}, at end "
        f"{report['load_average_at_end']}; per round {report['load_average_per_round']}. "
        + _load_remark(report["load_average_at_start"][0])
        + "; the variants ran interleaved round by round so the ratios compare like with like",
        f"- variants: `before` = commit {before[:12]} (`--before`; "
        + ("main before the compiled kernels, " if report["before_ref"] == BEFORE else "")
        + 'its default rasterizer); `torch` = this commit with `RasterConfig(kernel="torch")` (the '
        "fallback); `cpp` = this commit with the compiled C++ kernels (the default where they build)",
        f"- {report['rounds']} interleaved rounds x {report['repeats']} timed runs (after a warm-up) per "
        "variant, each round a fresh process per (config, variant, mode); medians over all runs",
        "- scene: N Gaussians on a 1.7 m body surface (discs 5-10 mm), camera 2.75 m away, white "
        "background; loss for the backward = image.sum() + alpha.sum(); peak memory is the RSS growth "
        "of the process during its runs",
        "- pairs = Gaussian-tile intersections x 64 pixels",
        "",
        "## Speed-up of the compiled kernels",
        "",
        "| threads | N | image | mode | before ms | torch ms | cpp ms | cpp vs before | cpp vs torch "
        "| CPU-time ratio vs before |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["ratios"]:

        def ms(key, r=r):
            return f"{r[key]:.1f}" if key in r else "-"

        def x(key, r=r):
            return f"{r[key]:.2f}x" if key in r else "-"

        lines.append(
            f"| {r['threads']} | {r['n']} | {r['size']}² | {r['mode']} | {ms('before_ms')} | "
            f"{ms('torch_ms')} | {ms('cpp_ms')} | {x('speedup_vs_before')} | {x('speedup_vs_torch')} | "
            f"{x('cpu_speedup_vs_before')} |"
        )
    lines += [
        "",
        "## All runs",
        "",
        "| threads | N | image | variant | mode | median ms | min ms | CPU ms | FPS | Mpairs/s "
        "| peak RSS delta MB | note |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["summary"]:
        head = f"| {r['threads']} | {r['n']} | {r['size']}² | {r['variant']} | {r['mode']} |"
        if "median_ms" not in r:
            lines.append(f"{head} - | - | - | - | - | - | {r.get('note', '')[:200]} |")
            continue
        lines.append(
            f"{head} {r['median_ms']:.1f} | {r['min_ms']:.1f} | {r['cpu_median_ms']:.1f} | {r['fps']:.1f} | "
            f"{r['mpairs_per_s']:.1f} | {r['peak_rss_delta_mb']:.0f} | |"
        )
    lines += ["", "## Targets (20k Gaussians @ 512², `cpp`; set for a 2-core machine)", ""]
    for t in report["targets"]:
        lines.append(f"- {t}")
    if report.get("notes"):
        lines += ["", "## Notes", ""] + [f"- {t}" for t in report["notes"]]
    return "\n".join(lines) + "\n"


def _load_remark(load_at_start: float) -> str:
    """What the 1-minute load at the start says about the wall times (the benchmark itself keeps
    up to ``threads`` cores busy, so only a start above one core's worth means other work)."""
    if load_at_start < 1.0:
        return "The machine was otherwise idle at the start (1-minute load below 1)"
    return "Other work shared the machine: wall times are inflated and noisy, CPU times (all threads) less so"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="fewer repeats and rounds, N <= 20k")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--threads", default=str(THREADS), help="torch threads, e.g. 2 or 1,2 (default 2)")
    parser.add_argument(
        "--omp-wait-policy",
        choices=("PASSIVE", "ACTIVE"),
        help="OMP_WAIT_POLICY for the runs; PASSIVE keeps OpenMP threads from spinning on a loaded machine",
    )
    parser.add_argument(
        "--before", default=BEFORE, help=f"git ref of the 'before' variant (default {BEFORE})"
    )
    parser.add_argument("--rounds", type=int, help="interleaved rounds (default 3, quick 2)")
    parser.add_argument("--reference", action="store_true", help="also run the plain-autograd reference")
    parser.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    args = parser.parse_args(argv)
    if args.child:
        n, size, variant, mode, repeats, threads = args.child.split(",")
        print(json.dumps(measure(int(n), int(size), variant, mode, int(repeats), int(threads))))
        return

    threads = [int(t) for t in args.threads.split(",")]
    load_start = _load()
    ns = (2_000, 20_000) if args.quick else (2_000, 20_000, 100_000)
    sizes = (256, 512)
    repeats = 3 if args.quick else 5
    rounds = args.rounds or (2 if args.quick else 3)
    notes = []
    reason = _build_kernels()
    if reason:
        notes.append(f"compiled kernels unavailable ({reason}): the cpp rows fail")
    with tempfile.TemporaryDirectory(prefix="eva-bench-before-") as tmp:
        roots = {"torch": ROOT, "cpp": ROOT, "autograd": ROOT}
        try:
            before_commit = _extract(args.before, Path(tmp))
            roots["before"] = Path(tmp)
        except (subprocess.CalledProcessError, FileNotFoundError) as err:
            before_commit = None
            notes.append(f"before variant skipped: no git checkout or ref {args.before!r} ({err})")
        variants = [v for v in VARIANTS if v in roots] + (["autograd"] if args.reference else [])
        results, per_round = [], []
        for round_ in range(rounds):
            for n, nt in ((n, nt) for nt in threads for n in ns):
                for size in sizes:
                    for mode in ("fwd", "fwd+bwd"):
                        for variant in variants:
                            if variant == "autograd" and n * size * size > 100_000 * 256 * 256:
                                results.append(
                                    dict(
                                        n=n,
                                        size=size,
                                        variant=variant,
                                        mode=mode,
                                        threads=nt,
                                        skipped="skipped: the reference's memory grows with the pairs",
                                    )
                                )
                                continue
                            r = _run_child(
                                roots[variant], n, size, variant, mode, repeats, nt, args.omp_wait_policy
                            )
                            r.update(round=round_, threads=nt)
                            results.append(r)
                            brief = {k: v for k, v in r.items() if k not in ("times_ms", "cpu_ms")}
                            if "times_ms" in r:
                                brief["median_ms"] = round(statistics.median(r["times_ms"]), 1)
                            print(brief, flush=True)
            per_round.append(_load())
    summary = _summary(results)
    report = dict(
        run_header(),  # its machine line replaced by the detailed record below
        machine=_machine(args.threads),
        omp_wait_policy=args.omp_wait_policy,
        load_average_at_start=load_start,
        load_average_per_round=per_round,
        load_average_at_end=_load(),
        before_ref=args.before,
        before_commit=before_commit,
        rounds=rounds,
        repeats=repeats,
        summary=summary,
        ratios=_ratios(summary),
        targets=_targets(summary, threads),
        notes=notes,
        results=results,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    write_result(args.out, "rasterizer", report, _markdown(report))
    print(_markdown(report))


if __name__ == "__main__":
    main()
