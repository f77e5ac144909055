"""Benchmark of eva_engine.render.rasterize on body-like scenes (CPU by default).

For N in {2k, 20k, 100k} Gaussians on a 1.7 m human-shaped surface and images of 256^2 and 512^2,
measures forward and forward+backward wall time and peak memory of the tiled rasterizer (the
default, hand-written backward) and, side by side, of the plain-autograd reference. Each
(config, backend) runs in its own subprocess so that its peak RSS (ru_maxrss) is its own.

    .venv/bin/python bench/rasterizer.py            # full grid, writes bench/results/rasterizer.{json,md}
    .venv/bin/python bench/rasterizer.py --quick    # fewer repeats, N <= 20k

Targets (2 CPU cores): 20k @ 512^2 forward+backward <= 100 ms, forward >= 20 FPS, peak memory
<= 0.5 GB.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from machine import cpu_name

from eva_engine.demo import quat_from_z

RESULTS = Path(__file__).resolve().parent / "results"
THREADS = 2  # the target machine's core count; --threads overrides
# The autograd reference keeps ~16 float32 values per Gaussian-pixel pair alive for backward;
# configs whose estimate exceeds this are skipped rather than pushing a shared machine into swap.
REFERENCE_MAX_BYTES = 2 * 1024**3
REFERENCE_BYTES_PER_PAIR = 64


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
    counts = torch.distributions.Multinomial(n, weights / weights.sum()).sample().long().tolist()
    pts, nrm = [], []
    for (kind, args, _), k in zip(parts, counts, strict=True):
        p, q = (_ellipsoid_points if kind == "ell" else _capsule_points)(k, *args, gen=gen)
        pts.append(p)
        nrm.append(q)
    means, normals = torch.cat(pts), torch.cat(nrm)
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
        means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
        viewmat=viewmat, K=K, width=size, height=size, background=torch.ones(3),
    )  # fmt: skip


# ----------------------------------------------------------------------------- one measurement


def _rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def measure(n: int, size: int, backend: str, mode: str, repeats: int, threads: int) -> dict:
    """Time `repeats` runs (after one warm-up) of forward or forward+backward in this process."""
    from eva_engine.render import RasterConfig, rasterize

    torch.set_num_threads(threads)
    scene = body_scene(n, size)
    cfg = RasterConfig(backend=backend)
    grads = ("means", "quats", "scales", "opacities", "colors")
    rss_before = _rss_bytes()
    times, pairs = [], 0
    for i in range(repeats + 1):
        inputs = dict(scene)
        if mode == "fwd+bwd":
            for k in grads:
                inputs[k] = scene[k].clone().requires_grad_(True)
        t0 = time.perf_counter()
        if mode == "fwd":
            with torch.no_grad():
                out = rasterize(**inputs, config=cfg)
        else:
            out = rasterize(**inputs, config=cfg)
            (out.image.sum() + out.alpha.sum()).backward()
        elapsed = time.perf_counter() - t0
        pairs = out.num_intersections * cfg.tile_size**2
        if i > 0:
            times.append(elapsed)
    median = statistics.median(times)
    return dict(
        n=n, size=size, backend=backend, mode=mode, repeats=repeats,
        median_ms=1e3 * median, min_ms=1e3 * min(times),
        peak_rss_delta_mb=(_rss_bytes() - rss_before) / 2**20,
        peak_rss_mb=_rss_bytes() / 2**20,
        intersections=out.num_intersections, pairs=pairs,
        pairs_per_s=pairs / median,
        coverage=float(out.alpha.mean()),
    )  # fmt: skip


def _run_child(n: int, size: int, backend: str, mode: str, repeats: int, threads: int) -> dict:
    cmd = [sys.executable, __file__, "--child", f"{n},{size},{backend},{mode},{repeats},{threads}"]
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        return dict(n=n, size=size, backend=backend, mode=mode, error=proc.stderr.strip()[-2000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- report


def _interpreter() -> str:
    """The Python that ran this, relative to the repository when it lives there (.venv/bin/python)."""
    exe = Path(sys.executable).absolute()
    root = Path(__file__).resolve().parents[1]
    return str(exe.relative_to(root)) if exe.is_relative_to(root) else str(exe)


def _machine(threads: int) -> dict:
    return dict(
        cpu=cpu_name(), logical_cores=os.cpu_count(), torch_threads=threads, torch=torch.__version__,
        python=platform.python_version(), platform=platform.platform(),
        load_average_at_start=[round(x, 2) for x in os.getloadavg()],
    )  # fmt: skip


def _markdown(report: dict) -> str:
    m = report["machine"]
    lines = [
        "# Rasterizer benchmark",
        "",
        f"- date: {report['date']}",
        f"- command: `{report['command']}`",
        f"- machine: {m['cpu']}, {m['logical_cores']} logical cores, torch {m['torch']} "
        f"({m['torch_threads']} threads), Python {m['python']}; load average at start "
        f"{m['load_average_at_start']} (other work on the machine makes timings noisy)",
        "- scene: N Gaussians on a 1.7 m body surface (discs 5-10 mm), camera 2.75 m away, "
        "white background; peak memory is the RSS growth of a fresh process during the runs",
        "- pairs = Gaussian-tile intersections x 64 pixels (Gaussian-pixel pairs evaluated)",
        "",
        "| N | image | backend | mode | median ms | min ms | FPS | Mpairs/s | peak RSS delta MB | note |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["results"]:
        head = f"| {r['n']} | {r['size']}² | {r['backend']} | {r['mode']} |"
        if "skipped" in r or "error" in r:
            lines.append(f"{head} - | - | - | - | - | {r.get('skipped') or 'error: ' + r['error'][-200:]} |")
            continue
        lines.append(
            f"{head} {r['median_ms']:.1f} | {r['min_ms']:.1f} | {1e3 / r['median_ms']:.1f} | "
            f"{r['pairs_per_s'] / 1e6:.1f} | {r['peak_rss_delta_mb']:.0f} | |"
        )
    lines += ["", "## Targets (20k Gaussians @ 512², 2 cores)", ""]
    for t in report["targets"]:
        lines.append(f"- {t}")
    return "\n".join(lines) + "\n"


def _targets(results: list[dict]) -> list[str]:
    def find(mode):
        for r in results:
            key = (r["n"], r["size"], r["backend"], r["mode"])
            if key == (20_000, 512, "tiled", mode) and "median_ms" in r:
                return r
        return None

    out = []
    fb, fw = find("fwd+bwd"), find("fwd")
    if fb:
        ok = "met" if fb["median_ms"] <= 100 else "NOT met"
        out.append(f"forward+backward <= 100 ms: {fb['median_ms']:.1f} ms ({ok})")
    if fw:
        fps = 1e3 / fw["median_ms"]
        out.append(f"forward >= 20 FPS: {fps:.1f} FPS ({'met' if fps >= 20 else 'NOT met'})")
    peaks = [r["peak_rss_delta_mb"] for r in (fb, fw) if r]
    if peaks:
        ok = "met" if max(peaks) <= 512 else "NOT met"
        out.append(f"peak memory <= 0.5 GB: {max(peaks):.0f} MB RSS growth ({ok})")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="fewer repeats and N <= 20k")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=THREADS, help="torch threads (default 2)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    args = parser.parse_args()
    if args.child:
        n, size, backend, mode, repeats, threads = args.child.split(",")
        print(json.dumps(measure(int(n), int(size), backend, mode, int(repeats), int(threads))))
        return
    machine = _machine(args.threads)

    sizes = (256, 512)
    ns = (2_000, 20_000) if args.quick else (2_000, 20_000, 100_000)
    repeats = 3 if args.quick else 5
    results = []
    for n in ns:
        for size in sizes:
            pairs_estimate = None
            for backend in ("tiled", "autograd"):
                for mode in ("fwd", "fwd+bwd"):
                    if backend == "autograd" and pairs_estimate is not None:
                        need = pairs_estimate * REFERENCE_BYTES_PER_PAIR
                        if need > REFERENCE_MAX_BYTES:
                            results.append(
                                dict(n=n, size=size, backend=backend, mode=mode,
                                     skipped=f"skipped: reference would need ~{need / 2**30:.1f} GB")
                            )  # fmt: skip
                            print(results[-1], flush=True)
                            continue
                    r = _run_child(n, size, backend, mode, repeats, args.threads)
                    if backend == "tiled" and "pairs" in r:
                        pairs_estimate = r["pairs"]
                    results.append(r)
                    print({k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.items()}, flush=True)
    report = dict(
        date=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        command=" ".join([_interpreter(), "bench/rasterizer.py", *sys.argv[1:]]),
        machine=machine,
        results=results,
    )
    report["targets"] = _targets(results)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "rasterizer.json").write_text(json.dumps(report, indent=2) + "\n")
    (args.out / "rasterizer.md").write_text(_markdown(report))
    print(_markdown(report))


if __name__ == "__main__":
    main()
